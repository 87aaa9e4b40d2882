"""dobhil.cluster on an in-process Dask cluster (the module's ``dask_client``): addresses,
the order of results, errors as rows, a scheduler without workers, one that never answers."""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator

import pytest

from dobhil.cluster import NO_DASHBOARD, ClusterError, MapResult, check_address, map_ordered, map_values, open_client
from dobhil.errors import ConfigError


@pytest.mark.parametrize(("given", "expected"), [
    ("tcp://127.0.0.1:8786", "tcp://127.0.0.1:8786"),
    ("127.0.0.1:8786", "tcp://127.0.0.1:8786"),
    (" scheduler.lab-2.local:8786 ", "tcp://scheduler.lab-2.local:8786"),
    ("[::1]:8786", "tcp://[::1]:8786"),
    ("tcp://host:08786", "tcp://host:8786"),
])
def test_an_address_is_made_tcp(given: str, expected: str) -> None:
    assert check_address(given) == expected


@pytest.mark.parametrize("given", ["", "garbage", "local", "host", "tcp://host", "tcp://host:", "host:0",
                                   "host:65536", "host:123456", "tls://host:8786", "inproc://x/1/2",
                                   "http://host:80", "tcp://ho st:1", "host:port", "tcp://:8786"])
def test_anything_else_is_refused_naming_what_is_allowed(given: str) -> None:
    with pytest.raises(ConfigError, match=r"not a scheduler address; allowed: tcp://HOST:PORT or HOST:PORT"):
        check_address(given)


_ONE_FINISHED = threading.Event()


def _zero_waits_for_one(item: int) -> int:
    """Item 1 finishes before item 0 starts to finish (2 worker threads, one process)."""
    if item == 0 and not _ONE_FINISHED.wait(30):
        raise TimeoutError("item 1 never finished")
    if item == 1:
        _ONE_FINISHED.set()
    return item * 10


def test_results_come_in_the_order_of_the_items_not_of_finishing(dask_client: object) -> None:
    _ONE_FINISHED.clear()
    seen: list[int] = []
    results = map_ordered(dask_client, _zero_waits_for_one, [0, 1, 2, 3], progress=seen.append)  # type: ignore[arg-type]
    assert results == [MapResult(0, None, False), MapResult(10, None, False),
                       MapResult(20, None, False), MapResult(30, None, False)]
    assert seen == [1, 1, 1, 1]


def _fails_on_odd(item: int) -> float:
    if item % 2:
        raise ValueError(f"item {item} is odd,\nsee here")
    return 1 / item if item else 0.0


def test_a_task_that_raises_is_a_row_with_its_error_and_the_map_goes_on(dask_client: object) -> None:
    results = map_ordered(dask_client, _fails_on_odd, list(range(6)), key_prefix="t")  # type: ignore[arg-type]
    assert [r.error for r in results] == [None, "ValueError: item 1 is odd, see here", None,
                                          "ValueError: item 3 is odd, see here", None,
                                          "ValueError: item 5 is odd, see here"]
    assert [r.value for r in results] == [0.0, None, 0.5, None, 0.25, None]
    assert not any(r.retried for r in results)


def test_two_maps_of_one_prefix_do_not_share_results(dask_client: object) -> None:
    """Keys carry a token per map: the same prefix and index on one scheduler (two users,
    two sweeps) must not hand one map the other's result."""
    first = map_ordered(dask_client, _fails_on_odd, [2], key_prefix="same")  # type: ignore[arg-type]
    second = map_ordered(dask_client, _fails_on_odd, [4], key_prefix="same")  # type: ignore[arg-type]
    assert (first[0].value, second[0].value) == (0.5, 0.25)


def test_an_empty_map_is_empty(dask_client: object) -> None:
    assert map_ordered(dask_client, _fails_on_odd, []) == []  # type: ignore[arg-type]


def test_a_listener_that_never_speaks_dask_is_no_scheduler(silent_listener: str) -> None:
    """The workaround (:func:`dobhil.cluster._probe`): distributed alone waits for this
    handshake forever."""
    with pytest.raises(ConfigError, match=rf"--scheduler tcp://{silent_listener}: no Dask scheduler answered "
                       r"within 0.5 s \(the port accepted a connection but never replied to Dask's handshake\)"), \
            open_client(silent_listener, timeout=0.5):
        pass


@pytest.fixture
def chatty_stranger() -> Iterator[str]:
    """A port that answers anything with an HTTP error (a web server where the scheduler
    should be) and keeps the connection open."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen(8)

        def answer() -> None:
            conn, _ = sock.accept()
            with conn:
                conn.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n" * 4)
                conn.recv(1 << 16)
                conn.settimeout(5)
                try:
                    conn.recv(1 << 16)   # until the client hangs up
                except OSError:
                    pass

        thread = threading.Thread(target=answer, daemon=True)
        thread.start()
        yield f"127.0.0.1:{sock.getsockname()[1]}"
        thread.join(10)


def test_a_port_that_answers_but_not_as_dask_is_no_scheduler(chatty_stranger: str) -> None:
    with pytest.raises(ClusterError, match=rf"^--scheduler tcp://{chatty_stranger}: (something answered, but not "
                       r"a Dask scheduler \(\w+ decoding its reply\)|no Dask scheduler answered within 2 s .*)$"), \
            open_client(chatty_stranger, timeout=2):
        pass


def test_a_closed_port_is_no_scheduler(closed_port: str) -> None:
    """The reason is the last attempt's: refused, or (on a loaded machine, distributed's
    attempts have a fifth of the timeout each) that attempt timing out."""
    with pytest.raises(ConfigError, match=rf"--scheduler tcp://{closed_port}: no Dask scheduler answered within 0.5 s "
                       r"\((\[Errno 111\] Connection refused|Timed out trying to connect to \S+ after 0.5 s)\)$"), \
            open_client(f"tcp://{closed_port}", timeout=0.5):
        pass


def test_a_scheduler_without_workers_is_refused_after_the_wait() -> None:
    from distributed import LocalCluster
    with LocalCluster(n_workers=0, processes=False, protocol="tcp", dashboard_address=None,
                      scheduler_kwargs=NO_DASHBOARD) as empty:
        address = empty.scheduler_address
        with pytest.raises(ConfigError, match=rf"{address}: the scheduler has no workers \(waited 0.5 s\); "
                           rf"start some: dask worker {address}"), open_client(address, timeout=0.5):
            pass


def test_a_scheduler_with_workers_runs_the_map() -> None:
    """The remote path end to end (tcp, the probe then the client) on an in-process cluster."""
    from distributed import LocalCluster
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp",
                      dashboard_address=None, scheduler_kwargs=NO_DASHBOARD) as cluster, \
            open_client(cluster.scheduler_address) as client:
        assert [r.value for r in map_ordered(client, _fails_on_odd, [0, 2, 4])] == [0.0, 0.5, 0.25]


def test_map_values_gives_values_or_one_error_naming_the_first_failure(dask_client: object) -> None:
    assert map_values(dask_client, _fails_on_odd, [0, 2]) == [0.0, 0.5]  # type: ignore[arg-type]
    with pytest.raises(ClusterError, match=r"^2 of 4 tasks failed on the Dask workers; task 1: ValueError: item 1 "
                       r"is odd, see here$"):
        map_values(dask_client, _fails_on_odd, [0, 1, 2, 3])  # type: ignore[arg-type]


def test_dask_loggers_are_quiet_inside_and_restored_after(dask_client: object) -> None:
    """Children Dask's config gives a level of their own (``distributed.client``) are quiet
    too; the module fixture's client keeps them quiet, so look at a nested one's exit."""
    import logging
    client_log = logging.getLogger("distributed.client")
    before = client_log.level
    client_log.setLevel(logging.WARNING)
    try:
        with open_client(workers=1, processes=False):
            assert client_log.getEffectiveLevel() == logging.CRITICAL
            assert logging.getLogger("distributed").getEffectiveLevel() == logging.CRITICAL
        assert client_log.level == logging.WARNING
    finally:
        client_log.setLevel(before)
