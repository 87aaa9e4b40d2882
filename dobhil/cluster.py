"""Work spread over a Dask distributed cluster: a local one, or an existing scheduler.

dobhil does not schedule anything itself: :func:`open_client` gives a
``distributed.Client`` (a ``LocalCluster`` of worker processes, or a connection to a
scheduler the user runs), and :func:`map_ordered` runs one task per item and gives the
results back in the order of the items -- a task that raises becomes a row with its error,
a task whose worker died is rescheduled by Dask and marked ``retried``.

What this module adds to Dask, and why:

- A scheduler that does not answer is bad input (one line, exit 2, within seconds):
  distributed's ``connect`` retries a closed port until its timeout, but after the TCP
  connection it waits for the scheduler's handshake with no timeout at all, so a listener
  that never speaks Dask (a web server, a wrong port) would hang the command forever.
  :func:`_probe` bounds the whole connection, handshake included (see there).
- Worker processes run BLAS on one thread: tasks are already one per core, and a
  multithreaded OpenBLAS per worker would oversubscribe the cores.
- Dask's own logging (reconnect attempts, a worker killed) is kept off the terminal while a
  client is open: the user sees one line per problem, from dobhil.

Layer: the OS layer (beside files and realtime) -- it knows Dask, and of dobhil only its
errors; the sweep and the Monte-Carlo campaign hand it plain functions and items.
"""

from __future__ import annotations

import asyncio
import logging
import os
import re
import uuid
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeVar

from dobhil.errors import ConfigError, exception_line

if TYPE_CHECKING:
    import distributed

T = TypeVar("T")

#: seconds to wait for a scheduler to answer (and for a worker to join it); short enough
#: that a wrong address ends the whole command (imports included) within 10 s
CONNECT_TIMEOUT = 4.0
#: seconds beyond the timeout for the handshake of a port that did connect (see _probe)
HANDSHAKE_GRACE = 0.5

#: BLAS on one thread in every worker process (the variables act before numpy loads BLAS)
ONE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}

#: a local scheduler's HTTP server (health, metrics; no dashboard) on a free port of this host:
#: without it the scheduler takes 8787 on every interface, and warns when another has it
NO_DASHBOARD = {"dashboard": False, "dashboard_address": "127.0.0.1:0"}

#: what --scheduler accepts, for the error line
ALLOWED_ADDRESSES = "tcp://HOST:PORT or HOST:PORT (e.g. tcp://10.0.0.5:8786)"

_ADDRESS = re.compile(r"(?:tcp://)?(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):(?P<port>[0-9]{1,5})")


class ClusterError(ConfigError):
    """A scheduler that does not answer, has no workers, or was lost (one line, exit 2)."""


@dataclass(frozen=True)
class MapResult:
    """One item's outcome: its value, or the error its task raised (``"ExcType: msg"``);
    ``retried`` when Dask ran it again after its worker died."""

    value: Any
    error: str | None
    retried: bool


def check_address(address: str) -> str:
    """``tcp://host:port`` as given, or ``host:port`` made ``tcp://host:port``; anything
    else (another protocol, no port, a port out of range) is a ConfigError."""
    match = _ADDRESS.fullmatch(address.strip())
    if match is None or not 0 < int(match["port"]) < 65536:
        raise ConfigError(f"--scheduler {address!r}: not a scheduler address; allowed: {ALLOWED_ADDRESSES}, "
                          "or local")
    return f"tcp://{match['host']}:{int(match['port'])}"


@contextmanager
def open_client(scheduler: str | None = None, *, workers: int | None = None, processes: bool = True,
                timeout: float = CONNECT_TIMEOUT) -> Iterator[distributed.Client]:
    """A client of a new local cluster (``scheduler`` None: ``workers`` processes, one per
    core by default, one thread each) or of the scheduler at ``scheduler``; everything it
    started is closed on exit, however the block ends."""
    with _quiet_dask():
        if scheduler is None:
            with _local_client(workers or os.cpu_count() or 1, processes) as client:
                yield client
        else:
            with _remote_client(check_address(scheduler), timeout) as client:
                yield client


@contextmanager
def _local_client(workers: int, processes: bool) -> Iterator[distributed.Client]:
    from distributed import Client, LocalCluster
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=processes,
                      dashboard_address=None, scheduler_kwargs=NO_DASHBOARD, silence_logs=logging.CRITICAL,
                      **({"env": ONE_THREAD_ENV} if processes else {})) as cluster, Client(cluster) as client:
        yield client


@contextmanager
def _remote_client(address: str, timeout: float) -> Iterator[distributed.Client]:
    from distributed import Client
    _probe(address, timeout)
    try:
        client = Client(address, timeout=timeout)
    except (OSError, asyncio.TimeoutError) as exc:   # the scheduler went between probe and client
        raise _no_answer(address, timeout, _reason(exc)) from None
    with client:
        try:
            client.wait_for_workers(1, timeout=timeout)
        except (asyncio.TimeoutError, TimeoutError):
            raise ClusterError(f"--scheduler {address}: the scheduler has no workers (waited {timeout:g} s); "
                               f"start some: dask worker {address}") from None
        yield client


def _probe(address: str, timeout: float) -> None:
    """Connect to ``address`` and do Dask's handshake within about ``timeout`` seconds, or
    raise :class:`ClusterError` saying which step got no answer.

    Why: ``distributed.Client(address, timeout=...)`` bounds the TCP connection but then
    awaits the scheduler's handshake reply with no timeout (``distributed.comm.connect``,
    2026.8.0), so a port that accepts and never speaks hangs it forever. The public
    ``distributed.comm.connect`` under our own ``asyncio.wait_for`` bounds both; the
    comm is closed and the real client connects next (a second, quick handshake). The
    outer bound has :data:`HANDSHAKE_GRACE` more, so a port that never connects fails in
    ``connect`` (with its reason: refused, unknown host) and only a silent one reaches it."""
    from distributed.comm import connect

    async def handshake() -> None:
        comm = await asyncio.wait_for(connect(address, timeout=timeout), timeout + HANDSHAKE_GRACE)
        await comm.close()

    try:
        asyncio.run(handshake())
    except asyncio.TimeoutError:   # (3.11+: builtin TimeoutError, an OSError: caught first)
        raise _no_answer(address, timeout, "the port accepted a connection but never replied to Dask's "
                         "handshake") from None
    except OSError as exc:
        raise _no_answer(address, timeout, _reason(exc)) from None
    except Exception as exc:   # whatever a stranger's bytes make of Dask's decoder
        # (a web server's reply read as a frame length: numpy asked for exabytes) is one answer:
        # not a scheduler
        raise ClusterError(f"--scheduler {address}: something answered, but not a Dask scheduler "
                           f"({type(exc).__name__} decoding its reply)") from None


def _reason(exc: BaseException) -> str:
    """distributed's "Timed out trying to connect" carries the last attempt's error as its
    cause, itself wrapping the socket's (connection refused, name not known): the innermost
    error that says something is the useful part."""
    said = exc
    while exc.__cause__ is not None:
        exc = exc.__cause__
        said = exc if str(exc) else said
    return exception_line(said, named=False)


def _no_answer(address: str, timeout: float, why: str) -> ClusterError:
    return ClusterError(f"--scheduler {address}: no Dask scheduler answered within {timeout:g} s ({why})")


#: the families of loggers Dask writes to (tornado and asyncio: its event loop's)
DASK_LOGGERS = ("distributed", "tornado", "asyncio")


@contextmanager
def _quiet_dask() -> Iterator[None]:
    """Dask's loggers at CRITICAL while inside (each restored on exit): its reconnect attempts
    and worker deaths reach the user as dobhil's one line (or as ``retried``), not as pages.
    Every existing logger of the families is set, not only the top one: Dask's logging config
    gives some children levels of their own (``distributed.client: warning``), which a
    parent's level does not override."""
    import distributed  # noqa: F401 -- its import configures its loggers; set them after that
    names = [name for name in [*DASK_LOGGERS, *logging.root.manager.loggerDict]
             if name.split(".")[0] in DASK_LOGGERS]
    saved = {name: logging.getLogger(name).level for name in names}
    for name in saved:
        logging.getLogger(name).setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        for name, level in saved.items():
            logging.getLogger(name).setLevel(level)


def map_ordered(client: distributed.Client, fn: Callable[[T], Any], items: Sequence[T], *,
                progress: Callable[[int], None] | None = None, key_prefix: str = "dobhil",
                arrived: Callable[[int, Any, str | None], None] | None = None) -> list[MapResult]:
    """``fn(item)`` for each item, one Dask task each, the results in the order of ``items``
    whatever order they finish in. ``progress(1)`` after each task, ``arrived(index, value,
    error)`` too when given (what came back, for a progress line that counts failures); a
    task that raises gives ``MapResult(None, "ExcType: msg", ...)`` and the others go on."""
    from distributed import as_completed
    token = uuid.uuid4().hex[:12]   # keys of two maps (two users of one scheduler) never meet
    topic = f"{key_prefix}-attempts-{token}"
    futures = {client.submit(_attempt, fn, topic, i, item, pure=False, key=f"{key_prefix}-{token}-{i}"): i
               for i, item in enumerate(items)}
    outcomes: dict[int, tuple[Any, str | None]] = {}
    for future in as_completed(futures):
        outcomes[futures[future]] = _outcome(future)
        future.release()   # the value is here now: free it on the worker
        if arrived:
            arrived(futures[future], *outcomes[futures[future]])
        if progress:
            progress(1)
    retried = _retried(client, topic)
    return [MapResult(value, error, i in retried) for i, (value, error) in sorted(outcomes.items())]


def map_values(client: distributed.Client, fn: Callable[[T], Any], items: Sequence[T], *,
               progress: Callable[[int], None] | None = None, key_prefix: str = "dobhil") -> list[Any]:
    """:func:`map_ordered` for work where every item must succeed (the chunks of one result):
    the values, or :class:`ClusterError` naming how many tasks failed and the first error."""
    results = map_ordered(client, fn, items, progress=progress, key_prefix=key_prefix)
    failed = [(i, r.error) for i, r in enumerate(results) if r.error is not None]
    if failed:
        raise ClusterError(f"{len(failed)} of {len(items)} tasks failed on the Dask workers; "
                           f"task {failed[0][0]}: {failed[0][1]}")
    return [r.value for r in results]


def _attempt(fn: Callable[[T], Any], topic: str, index: int, item: T) -> Any:
    """Runs on a worker: say that item ``index`` starts (an event on ``topic``), then run it.
    A second start of one index means its first worker died under it (:func:`_retried`)."""
    from distributed import get_worker
    get_worker().log_event(topic, index)
    return fn(item)


def _outcome(future: distributed.Future) -> tuple[Any, str | None]:
    """The value, or the task's exception as ``"ExcType: msg"`` on one line. A future the
    cluster cancelled (the scheduler went away) ends the map: no row could be trusted."""
    if future.status == "cancelled":
        raise ClusterError("the Dask scheduler went away during the run (its tasks were cancelled)")
    if future.status == "error":
        exc = future.exception()
        return None, exception_line(exc)
    return future.result(), None


def _retried(client: distributed.Client, topic: str) -> set[int]:
    """Indices that started more than once: their worker died and Dask ran them again.

    Why events: the scheduler's count of a task's failures is not public; the task's own
    start events (``Worker.log_event``, read with ``Client.get_events``) are. A worker
    sends an event on the same stream as its task's result, so by the time a result is
    here the start of that attempt is at the scheduler. Stolen tasks had not started, so
    they are not counted. (Dask keeps the last 100,000 events of a topic
    (``distributed.scheduler.events-log-length``): a map of more items may miss a retry.)"""
    starts = Counter(msg for _, msg in client.get_events(topic))
    return {index for index, count in starts.items() if count > 1}
