"""startrack.cluster: ordered results on one machine and on Dask, failures in place, bounded windows."""
import os
import random
import sys
import time

import pytest

from startrack.cluster import TaskFailure, chunks, default_chunk, ordered_map, pool_workers, worker_cache


def _slow_square(x):
    # Later tasks finish first: the output must still come in input order.
    time.sleep(0.02 * (7 - x % 8) if x < 8 else 0.0)
    return x * x


def _fails_on_three(x):
    if x == 3:
        raise ValueError("three is bad\nsecond line")
    return x


def _counted(_x):
    cache = worker_cache()
    cache["calls"] = cache.get("calls", 0) + 1
    return os.getpid(), cache["calls"]


def test_serial_keeps_order_and_reports_failures_in_place():
    out = list(ordered_map(_fails_on_three, range(6)))
    assert [i for i, _ in out] == list(range(6))
    assert isinstance(out[3][1], TaskFailure) and out[3][1].error == "ValueError: three is bad"
    assert [r for i, r in out if i != 3] == [0, 1, 2, 4, 5]


def test_process_pool_keeps_input_order():
    out = list(ordered_map(_slow_square, range(12), jobs=2, window=3))
    assert out == [(i, i * i) for i in range(12)]


def _inherited(_x):
    return worker_cache().get("parent_marker")


def test_forked_workers_inherit_what_the_parent_loaded():
    from startrack.cluster import fork_safe

    # Forked when safe (Linux, one thread, numba's parallel layer not started), else spawned (a fresh process).
    forked = fork_safe()
    assert forked or not sys.platform.startswith("linux") or "numba.np.ufunc.parallel" in sys.modules \
        or __import__("threading").active_count() > 1
    worker_cache()["parent_marker"] = "loaded once"
    try:
        out = [r for _, r in ordered_map(_inherited, range(4), jobs=2)]
    finally:
        worker_cache().pop("parent_marker", None)
    assert out == (["loaded once"] if forked else [None]) * 4


def test_workers_only_when_they_pay_off(monkeypatch):
    import startrack.cluster as cluster

    monkeypatch.setattr(cluster, "idle_cpus", lambda: 2)
    # 10 tasks of 10 ms: 0.1 s here; 2 workers need 0.05 s plus their start-up.
    assert pool_workers(2, 10, 0.01, startup_s=0.02) == 2
    assert pool_workers(2, 10, 0.01, startup_s=0.06) == 1
    assert pool_workers(4, 10, 0.01, startup_s=0.0) == 2        # no more workers than idle CPUs
    assert pool_workers(2, 1, 1.0, startup_s=0.0) == 1          # one task: nothing to share
    monkeypatch.setattr(cluster, "idle_cpus", lambda: 1)
    assert pool_workers(2, 100, 1.0, startup_s=0.0) == 1        # the other CPUs are busy


def test_items_are_read_lazily_within_the_window():
    seen = []

    def source():
        for i in range(100):
            seen.append(i)
            yield i

    it = ordered_map(_slow_square, source(), jobs=2, window=4)
    first = next(it)
    assert first == (0, 0)
    assert len(seen) <= 5      # the window (4) plus the one that stopped the refill
    it.close()


def test_worker_cache_lives_as_long_as_the_process():
    results = [r for _, r in ordered_map(_counted, range(5))]
    assert [calls for _, calls in results][-1] - results[0][1] == 4


def test_progress_counts_done_and_failed():
    states = []
    list(ordered_map(_fails_on_three, range(5), progress=lambda s: states.append((s.done, s.failed))))
    assert states[-1] == (5, 1)


def test_bad_jobs_and_scheduler_are_refused():
    from startrack.errors import BadInputError

    with pytest.raises(BadInputError, match="jobs"):
        list(ordered_map(_slow_square, range(2), jobs=0))
    with pytest.raises(BadInputError, match="scheduler"):
        list(ordered_map(_slow_square, range(2), scheduler="nonsense"))


def test_chunks_cover_the_range_once():
    for total, size in [(0, 5), (1, 5), (10, 3), (100000, 2000)]:
        parts = chunks(total, size)
        covered = [i for a, b in parts for i in range(a, b)]
        assert covered == list(range(total))
        assert all(b - a <= size for a, b in parts)
    assert default_chunk(100000, 2) == 2000 and default_chunk(10, 2) == 1


def test_local_dask_cluster_keeps_order_and_retries():
    pytest.importorskip("distributed")
    import cloudpickle

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    items = list(range(16))
    random.Random(1).shuffle(items)
    out = list(ordered_map(_slow_square, items, jobs=2, scheduler="local", window=5))
    assert [i for i, _ in out] == list(range(16))
    assert [r for _, r in out] == [x * x for x in items]
    failed = list(ordered_map(_fails_on_three, range(5), jobs=1, scheduler="local", retries=1))
    assert isinstance(failed[3][1], TaskFailure) and "three is bad" in failed[3][1].error
    assert [r for i, r in failed if i != 3] == [0, 1, 2, 4]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_idle_cpus_does_not_count_this_processs_own_threads(monkeypatch):
    """`solve -j 2` never started its pool: a thread of this very process left running (a math library's
    worker spinning after a call) counted as another process's load, so idle_cpus() said 1 on an idle
    2-core machine.  Here a thread of ours runs while the machine's running count is read: with the
    machine otherwise idle (the running count all ours), every CPU is idle."""
    import threading

    import numpy as np

    from startrack import cluster

    monkeypatch.setattr(cluster, "usable_cpus", lambda: 2)
    busy = threading.Event()
    stop = threading.Event()

    def spin():
        a = np.random.default_rng(0).random(2_000_000)
        busy.set()
        while not stop.is_set():
            np.sort(a)              # releases the GIL: the thread is running, as the main one is
    t = threading.Thread(target=spin, daemon=True)
    t.start()
    busy.wait()
    try:
        own = cluster._own_running_tasks()
        real_open = open

        def fake_open(path, *a, **k):      # the machine's running count: our running threads only
            if path == "/proc/loadavg":
                import io
                return io.StringIO(f"0.00 0.00 0.00 {cluster._own_running_tasks()}/100 1\n")
            return real_open(path, *a, **k)
        monkeypatch.setattr("builtins.open", fake_open)
        idle = cluster.idle_cpus()
    finally:
        stop.set()
        t.join()
    assert own >= 2
    assert idle == 2
