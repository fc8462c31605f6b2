import time

from startrack.solve import _SearchClock


def _work(seconds):
    """Busy this process for ``seconds`` of CPU time (the search clock's unit)."""
    t = time.process_time()
    while time.process_time() - t < seconds:
        pass


def test_search_clock_does_not_count_setup():
    """Database builds and first-use compilation are set-up, not search time."""
    clock = _SearchClock(0.2)
    clock.setup(_work, 0.3)
    assert not clock.expired()
    _work(0.25)
    assert clock.expired()


def test_search_clock_counts_a_kind_as_setup_only_once():
    clock = _SearchClock(0.15)
    kind = f"test-kind-{time.monotonic_ns()}"
    clock.first_use(kind, _work, 0.2)           # first use: set-up
    assert not clock.expired()
    clock.first_use(kind, _work, 0.2)           # second use: search
    assert clock.expired()


def test_search_budget_is_cpu_time_not_wall_time():
    """A frame's search budget (solve --timeout-s) counts this process's CPU time: time the machine gives to other
    jobs does not count (on the wall clock a test suite on two processes failed all-sky frames an idle machine
    solved).  Sleeping stands for a machine busy with something else."""
    clock = _SearchClock(0.2)
    time.sleep(0.3)
    assert not clock.expired() and clock.remaining() > 0.1
    _work(0.25)                                 # this process's own work does count
    assert clock.expired()
