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
from collections.abc import Callable, Generator, Iterable, Iterator, Sequence
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

#: seconds a local cluster may take to start: a base for the scheduler and the imports, and
#: more per worker process (each imports numpy, scipy and dobhil: about 2 s on a busy 2-core
#: machine); past it the command ends in one line instead of waiting
START_TIMEOUT_BASE = 30.0
START_TIMEOUT_PER_WORKER = 10.0

#: tasks in flight (submitted, their rows not yet given back) per worker thread of a
#: streamed map, and the least window: enough that a slow task does not idle the others,
#: few enough that a campaign's memory stays flat. The window is at most half the events
#: the scheduler keeps of a topic (``distributed.admin.low-level-log-length``, 1000 by
#: default in 2026.8.0), so every start of a window's tasks is still there to count (_retried)
WINDOW_PER_THREAD = 16
WINDOW_MIN = 64

#: the name of the thread that starts a local cluster (see _start_local)
START_THREAD = "dobhil-local-cluster"

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


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity where the OS has one)."""
    affinity = getattr(os, "sched_getaffinity", None)
    return len(affinity(0)) if affinity is not None else os.cpu_count() or 1


def local_workers(requested: int | None) -> tuple[int, str | None]:
    """The worker processes of a local cluster for ``--workers requested`` (None: one per
    core), and a one-line note when the request was capped. Capped at :func:`usable_cores`:
    each task is one CPU-bound run, so more processes than cores only time-share the cores
    (no run ends sooner) while each costs its own interpreter's memory and start-up -- a
    thousand of them is a machine that stops answering. The results do not depend on the
    number of workers, so capping changes nothing but the wall time. A remote scheduler's
    workers are the user's and are never capped."""
    cores = usable_cores()
    if requested is None:
        return cores, None
    if requested > cores:
        return cores, (f"--workers {requested}: capped at {cores}, the cores this machine gives this process "
                       "(more local processes than cores run no faster); a --scheduler's workers are not capped")
    return requested, None


def start_timeout(workers: int) -> float:
    return START_TIMEOUT_BASE + START_TIMEOUT_PER_WORKER * workers


@contextmanager
def open_client(scheduler: str | None = None, *, workers: int | None = None, processes: bool = True,
                timeout: float = CONNECT_TIMEOUT, start_within: float | None = None) -> Iterator[distributed.Client]:
    """A client of a new local cluster (``scheduler`` None: ``workers`` processes, one per
    usable core by default, one thread each -- the commands cap a user's ``--workers`` with
    :func:`local_workers` first; started within ``start_within`` seconds,
    :func:`start_timeout` by default) or of the scheduler at ``scheduler``; everything it
    started is closed on exit, however the block ends."""
    with _quiet_dask():
        if scheduler is None:
            n = workers or usable_cores()
            with _local_client(n, processes, start_within or start_timeout(n)) as client:
                yield client
        else:
            with _remote_client(check_address(scheduler), timeout) as client:
                yield client


@contextmanager
def _local_client(workers: int, processes: bool, within: float) -> Iterator[distributed.Client]:
    from distributed import Client
    cluster = _start_local(workers, processes, within)
    with cluster, Client(cluster) as client:
        yield client


def _start_local(workers: int, processes: bool, within: float) -> Any:
    """A started ``LocalCluster``, or :class:`ClusterError` after ``within`` seconds.

    Why a thread: ``LocalCluster`` (2026.8.0) has no start-up timeout; it waits for every
    worker process however long they take. Started in a daemon thread, it is given up on
    after ``within`` seconds: the error line is said, and the half-started cluster's
    processes (daemonic) end with this one."""
    import threading
    from distributed import LocalCluster
    made: list[Any] = []
    failed: list[BaseException] = []
    lock = threading.Lock()
    abandoned = [False]

    def start() -> None:
        try:
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=processes,
                                   dashboard_address=None, scheduler_kwargs=NO_DASHBOARD,
                                   silence_logs=logging.CRITICAL, **({"env": ONE_THREAD_ENV} if processes else {}))
        except BaseException as exc:   # said on the caller's thread, as one line
            with lock:
                failed.append(exc)
            return
        with lock:
            made.append(cluster)
            late = abandoned[0]
        if late:   # given up on: nobody else will close it
            cluster.close()
    thread = threading.Thread(target=start, name=START_THREAD, daemon=True)
    thread.start()
    thread.join(within)
    with lock:
        abandoned[0] = not made and not failed
    if abandoned[0]:
        raise ClusterError(f"the local cluster of {workers} worker process{'es' if workers != 1 else ''} did not "
                           f"start within {within:g} s; give fewer --workers, or run a scheduler and its "
                           "workers yourself (--scheduler)")
    if failed:
        raise ClusterError(f"the local cluster of {workers} workers did not start: {exception_line(failed[0])}")
    return made[0]


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


def map_streaming(client: distributed.Client, fn: Callable[[T], Any], items: Iterable[T], *,
                  index: Callable[[T], int], key_prefix: str = "dobhil", window: int | None = None,
                  arrived: Callable[[int, Any, str | None], None] | None = None
                  ) -> Generator[tuple[int, MapResult], None, None]:
    """:func:`map_ordered` for any number of items: ``items`` is consumed only as far as
    ``window`` tasks are in flight (submitted, their results not yet given back; by default
    :data:`WINDOW_PER_THREAD` per worker thread), and ``(index(item), result)`` pairs are
    yielded in the items' order as soon as an item and all before it are done. Memory holds
    the window, never the whole map. ``arrived`` as in :func:`map_ordered`, as each task comes
    back. Items must come with consecutive indices from 0 (``index``)."""
    from distributed import as_completed
    window = window or stream_window(client)
    token = uuid.uuid4().hex[:12]
    topic = f"{key_prefix}-attempts-{token}"
    source = iter(items)
    pending: dict[Any, int] = {}                      # future -> index
    done: dict[int, tuple[Any, str | None]] = {}      # back, waiting for an earlier index
    ready: list[tuple[int, tuple[Any, str | None]]] = []   # in order, waiting for their retry count
    running = as_completed()
    following = 0

    def submit() -> None:
        while len(pending) + len(done) + len(ready) < window:
            item = next(source, None)
            if item is None:
                return
            i = index(item)
            future = client.submit(_attempt, fn, topic, i, item, pure=False, key=f"{key_prefix}-{token}-{i}")
            pending[future] = i
            running.add(future)
    try:
        submit()
        for future in running:
            i = pending.pop(future)
            done[i] = _outcome(future)
            future.release()
            if arrived:
                arrived(i, *done[i])
            while following in done:
                ready.append((following, done.pop(following)))
                following += 1
            if len(ready) >= window // 2 or not pending:
                yield from _flagged(client, topic, ready)
                ready = []
            submit()
        yield from _flagged(client, topic, ready)
    finally:   # a consumer that stops early: the rest is not run
        if pending:
            client.cancel(list(pending))


def stream_window(client: distributed.Client) -> int:
    import dask
    kept = int(dask.config.get("distributed.admin.low-level-log-length"))
    threads = sum(client.nthreads().values()) or 1
    return max(min(WINDOW_MIN, kept // 2), min(kept // 2, WINDOW_PER_THREAD * threads))


def _flagged(client: distributed.Client, topic: str,
             ready: Sequence[tuple[int, tuple[Any, str | None]]]) -> Iterator[tuple[int, MapResult]]:
    """The ready results with ``retried`` from the topic's start events (one read per batch)."""
    if not ready:
        return
    retried = _retried(client, topic)
    for i, (value, error) in ready:
        yield i, MapResult(value, error, i in retried)


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
    they are not counted. (Dask keeps the last 1,000 events of a topic by default
    (``distributed.admin.low-level-log-length``): :func:`map_ordered` of more items may miss
    a retry; :func:`map_streaming` reads them a window at a time, within that.)"""
    starts = Counter(msg for _, msg in client.get_events(topic))
    return {index for index, count in starts.items() if count > 1}
