"""Independent tasks on this machine or on a Dask cluster, results in input order.

Batches (images to solve, chunks of Monte Carlo attitudes, frames to render) are
lists of independent tasks.  :func:`ordered_map` runs one function over them

* in this process (``jobs=1``, no scheduler),
* in ``jobs`` worker processes of this machine (``multiprocessing``: forked when
  that is safe, so that they inherit this process's imports, open index and
  loaded kernels; else spawned), or
* on a Dask distributed cluster (``scheduler="local"`` starts a ``LocalCluster``
  of ``jobs`` single-threaded worker processes; ``scheduler="tcp://host:8786"``
  connects to a running ``dask scheduler`` with its ``dask worker`` processes,
  from a laptop to SLURM/PBS through dask-jobqueue),

and yields the results **in input order**, each as soon as it and every task
before it are done.  At most ``window`` tasks are in flight, so memory stays
bounded whatever the number of tasks, and a caller that writes each result as it
arrives (and flushes) loses only the tasks in flight when it is killed.

When a Dask worker dies, the scheduler gives its tasks to the other workers
(up to ``distributed.scheduler.allowed-failures`` times); a task that raises is
retried ``retries`` times.  A task that still fails is reported as a
:class:`TaskFailure` in its place: the batch goes on.

Workers keep what is expensive to load (catalog, databases, compiled kernels)
between tasks through :func:`worker_cache`, a dictionary that lives as long as
the worker process.

Dask is an optional dependency (the ``[cluster]`` extra); nothing here imports it
unless a scheduler is given.
"""
from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

from startrack.errors import BadInputError

__all__ = ["BatchProgress", "TaskFailure", "check_readable_on_workers", "chunks", "default_chunk", "fork_safe",
           "idle_cpus", "ordered_map", "pool_workers", "usable_cpus", "worker_cache", "worker_startup_s"]


@dataclass(frozen=True)
class TaskFailure:
    """A task that raised (after its retries) or whose workers kept dying."""

    index: int
    error: str


@dataclass
class BatchProgress:
    """Counts for a progress line: tasks done, failed and in flight, and the rate."""

    total: int
    done: int = 0
    failed: int = 0
    in_flight: int = 0
    started: float = 0.0

    @property
    def per_second(self) -> float:
        elapsed = time.perf_counter() - self.started
        return self.done / elapsed if elapsed > 0 else 0.0

    def line(self, unit: str = "tasks") -> str:
        return (f"{self.done}/{self.total} {unit} done, {self.failed} failed, {self.in_flight} in flight, "
                f"{self.per_second:.1f}/s")


# One dictionary per worker process.  In a Dask worker it hangs on the Worker
# object (so a worker restarted by its nanny starts empty); in a spawned
# multiprocessing worker or in this process it is this process's own.
_PROCESS_CACHE: dict = {}


def worker_cache() -> dict:
    """The cache of the process (or Dask worker) that runs the current task."""
    # A Dask worker has ``distributed`` loaded already; anywhere else importing
    # it would cost most of a second of start-up for nothing.
    if "distributed" not in sys.modules:
        return _PROCESS_CACHE
    try:
        from distributed import get_worker

        worker = get_worker()
    except (ImportError, ValueError):
        return _PROCESS_CACHE
    cache = getattr(worker, "_startrack_cache", None)
    if cache is None:
        cache = {}
        worker._startrack_cache = cache
    return cache


def _describe(exc: BaseException) -> str:
    text = str(exc).splitlines()[0] if str(exc) else ""
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def ordered_map(fn: Callable, items: Iterable, *, jobs: int = 1, scheduler: str | None = None,
                window: int | None = None, retries: int = 1,
                progress: Callable[[BatchProgress], None] | None = None) -> Iterator[tuple[int, object]]:
    """Run ``fn(item)`` for every item; yield ``(index, result)`` in input order.

    Parameters
    ----------
    fn : callable
        A module-level function (it is pickled to worker processes).  It should
        return a result for every item, failures included; an exception becomes
        a :class:`TaskFailure` in the item's place.
    items : iterable
        The tasks' arguments; read lazily, ``window`` ahead of the output.
    jobs : int
        Worker processes on this machine (``scheduler=None`` or ``"local"``).
    scheduler : str or None
        ``None`` (this machine), ``"local"`` (a Dask ``LocalCluster`` of ``jobs``
        workers) or the address of a running Dask scheduler.
    window : int or None
        Most tasks in flight; default four per worker.
    retries : int
        Extra attempts of a task that raised (Dask only; a dead worker's tasks
        are always moved to another worker).
    progress : callable or None
        Called with a :class:`BatchProgress` after every finished task.

    Yields
    ------
    (int, object)
        The item's index and ``fn(item)``, or a :class:`TaskFailure`.
    """
    if not (isinstance(jobs, int) and jobs >= 1):
        raise BadInputError("jobs", None, f"must be a whole number >= 1, got {jobs!r}")
    if window is not None and not window >= 1:
        raise BadInputError("window", None, f"must be >= 1, got {window!r}")
    if scheduler is not None:
        yield from _dask_map(fn, items, jobs, scheduler, window, retries, progress)
    elif jobs == 1:
        yield from _serial_map(fn, items, progress)
    else:
        yield from _pool_map(fn, items, jobs, window or 4 * jobs, progress)


def _serial_map(fn, items, progress):
    state = BatchProgress(total=_length(items), started=time.perf_counter())
    for i, item in enumerate(items):
        try:
            result = fn(item)
        except Exception as exc:  # noqa: BLE001 - a task's failure is reported in its place
            result = TaskFailure(i, _describe(exc))
        state.done += 1
        state.failed += isinstance(result, TaskFailure)
        if progress:
            progress(state)
        yield i, result


def _length(items) -> int:
    try:
        return len(items)
    except TypeError:
        return 0


def _windowed(items, window, submit, collect, progress):
    """Keep at most ``window`` tasks submitted; yield ``(index, result)`` in input order.

    ``submit(item)`` starts a task and returns its handle; ``collect(index, handle)`` waits for it
    and returns its result (a :class:`TaskFailure` when it failed).
    """
    state = BatchProgress(total=_length(items), started=time.perf_counter())
    pending = {}
    source = enumerate(items)
    exhausted = False
    next_out = 0
    while True:
        while not exhausted and len(pending) < window:
            try:
                i, item = next(source)
            except StopIteration:
                exhausted = True
                break
            pending[i] = submit(i, item)
        if next_out not in pending:
            return
        state.in_flight = len(pending)
        result = collect(next_out, pending.pop(next_out))
        state.done += 1
        state.failed += isinstance(result, TaskFailure)
        state.in_flight = len(pending)
        if progress:
            progress(state)
        yield next_out, result
        next_out += 1


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity mask where the system has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _own_running_tasks() -> int:
    """This process's threads that are running now (``/proc/self/task/*/stat`` state R), at least 1."""
    n = 0
    try:
        for task in os.listdir("/proc/self/task"):
            try:
                with open(f"/proc/self/task/{task}/stat") as fh:
                    n += fh.read().rsplit(")", 1)[1].split()[0] == "R"
            except OSError:
                continue
    except OSError:
        return 1
    return max(1, n)


def idle_cpus() -> int:
    """CPUs left for this process's workers: the usable CPUs minus what other processes keep busy, at least 1.

    On Linux, "busy" is the number of other runnable tasks now (``/proc/loadavg``'s running count,
    this process's own running threads excluded (a math library's idle worker threads spin for a while after
    each call); the least of three readings a few milliseconds apart, so that a passing
    task does not count); elsewhere the 1-minute load average less this process.
    """
    cpus = usable_cpus()
    others = None
    try:
        readings = []
        for k in range(3):
            if k:
                time.sleep(0.002)
            with open("/proc/loadavg") as fh:
                readings.append(int(fh.read().split()[3].split("/")[0]) - _own_running_tasks())
        others = max(0, min(readings))
    except (OSError, ValueError, IndexError):
        try:
            others = max(0.0, os.getloadavg()[0] - 1.0)
        except (AttributeError, OSError):
            others = 0.0
    return max(1, min(cpus, int(cpus - others + 0.5)))


def fork_safe() -> bool:
    """Whether worker processes may be forked from this one.

    Forking copies this process's memory (imports, memory-mapped index, loaded
    kernels) but only its calling thread: safe on Linux while this process runs a
    single thread and numba has not started its parallel threading layer (whose
    OpenMP/TBB threads do not survive a fork).  Elsewhere (macOS, Windows), spawn.
    """
    import threading

    if not sys.platform.startswith("linux") or threading.active_count() != 1:
        return False
    if "numba" in sys.modules:
        par = sys.modules.get("numba.np.ufunc.parallel")
        if par is not None and getattr(par, "_is_initialized", True):
            return False
    return True


def worker_startup_s(spawn_startup_s: float) -> float:
    """Wall time until one worker of this machine's pool takes its first task.

    Forked workers: measured here, as one fork of this process (a child that
    exits at once, waited for): what a worker's start copies is this process's
    page tables, the same for every worker.  Spawned workers redo this
    process's start-up (interpreter, imports, index, kernels):
    ``spawn_startup_s``, the caller's measure of its own.
    """
    if not fork_safe():
        return float(spawn_startup_s)
    _flush_std()
    t0 = time.perf_counter()
    pid = os.fork()
    if pid == 0:        # the child: no cleanup, no buffered output of the parent's
        os._exit(0)
    os.waitpid(pid, 0)
    return time.perf_counter() - t0


def pool_workers(jobs: int, n_tasks: int, task_s: float, startup_s: float, idle: int | None = None) -> int:
    """How many worker processes a batch should use (1: none, run it in this process).

    ``n_tasks`` tasks of ``task_s`` seconds each (measured on one of them) take
    ``n_tasks task_s`` here, or about ``startup_s + n_tasks task_s / k`` with ``k``
    workers (they start side by side); ``k`` is at most ``jobs``, the tasks and
    the CPUs this process may use that other processes leave idle (``idle``, a
    reading of :func:`idle_cpus` the caller made; read here when not given: more
    processes than idle CPUs only share them).  Workers are used only when that
    estimate is shorter.
    """
    k = min(int(jobs), int(n_tasks), idle_cpus() if idle is None else int(idle))
    serial = n_tasks * task_s
    if k <= 1 or not startup_s + serial / k < serial:
        return 1
    return k


def _forked_worker_init():
    """A forked worker starts with the default signal handlers: the parent's (SIGTERM raising an exception to
    clean up its temporary files) would turn the pool's terminate into a traceback and a hang."""
    import signal

    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _fork_pool(jobs):
    import multiprocessing as mp

    _flush_std()
    return mp.get_context("fork").Pool(jobs, _forked_worker_init)


def _flush_std():
    """Flush this process's standard streams (a forked worker flushes its copy of their buffers on exit)."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (AttributeError, OSError, ValueError):
            pass


def _pool_map(fn, items, jobs, window, progress):
    import multiprocessing as mp

    def collect(index, handle):
        try:
            return handle.get()
        except Exception as exc:  # noqa: BLE001 - a task's failure is reported in its place
            return TaskFailure(index, _describe(exc))

    # fork when safe (workers start in milliseconds with everything loaded), else spawn: numba's
    # threading layer must not be forked.
    with (_fork_pool(jobs) if fork_safe() else mp.get_context("spawn").Pool(jobs)) as pool:
        yield from _windowed(items, window, lambda _i, item: pool.apply_async(fn, (item,)), collect, progress)


def _connect(scheduler: str, jobs: int):
    """A Dask client (and the LocalCluster it owns, if any)."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise BadInputError("scheduler", None, "needs Dask: pip install 'startrack[cluster]'") from None
    import logging

    if scheduler == "local":
        cluster = LocalCluster(n_workers=jobs, threads_per_worker=1, processes=True, dashboard_address=None,
                               silence_logs=logging.ERROR)
        return Client(cluster), cluster
    if "://" not in scheduler and ":" not in scheduler:
        raise BadInputError("scheduler", None, f"expected 'local' or an address like tcp://host:8786, got {scheduler!r}")
    try:
        return Client(scheduler, timeout="10s"), None
    except (OSError, TimeoutError) as exc:
        raise BadInputError("scheduler", None, f"cannot reach the Dask scheduler at {scheduler}: {_describe(exc)}") from None


def _dask_map(fn, items, jobs, scheduler, window, retries, progress):
    from distributed import wait

    client, cluster = _connect(scheduler, jobs)

    def submit(i, item):
        return client.submit(fn, item, retries=retries, pure=False, key=f"startrack-{os.getpid()}-{i}")

    def collect(index, future):
        wait(future)
        if future.status == "finished":
            result = future.result()
        else:
            exc = future.exception()
            result = TaskFailure(index, _describe(exc) if exc is not None else future.status)
        future.release()
        return result

    try:
        n_workers = max(1, len(client.scheduler_info().get("workers", {})) or jobs)
        yield from _windowed(items, window or 4 * n_workers, submit, collect, progress)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _first_unreadable(paths: list) -> str | None:
    for p in paths:
        if not (os.path.isfile(p) and os.access(p, os.R_OK)):
            return p
    return None


def check_readable_on_workers(paths: list, scheduler: str, jobs: int = 1) -> None:
    """Refuse a batch whose input files some Dask worker cannot read.

    Workers read the images themselves, so the paths must name files on a
    filesystem every worker shares (NFS, a cluster filesystem, or this machine).
    Raises :class:`BadInputError` naming the first unreadable path and the worker.
    """
    if scheduler == "local" or not paths:
        return
    client, cluster = _connect(scheduler, jobs)
    try:
        absolute = [os.path.abspath(p) for p in paths]
        found = client.run(_first_unreadable, absolute)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    if not found:
        raise BadInputError("scheduler", None, f"no Dask worker is connected to {scheduler}")
    for worker, path in sorted(found.items()):
        if path is not None:
            raise BadInputError(path, None, f"cannot be read by Dask worker {worker}: images must be on a "
                                "filesystem every worker shares")


def chunks(total: int, size: int) -> list[tuple[int, int]]:
    """``(start, stop)`` ranges of at most ``size`` covering ``range(total)``."""
    size = max(1, int(size))
    return [(start, min(total, start + size)) for start in range(0, total, size)]


def default_chunk(total: int, workers: int, per_worker: int = 8, most: int = 2000) -> int:
    """A chunk size giving each worker several chunks (progress, load balance), bounded for memory."""
    return max(1, min(most, math.ceil(total / max(1, workers * per_worker))))
