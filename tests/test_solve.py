import time

from startrack.solve import _SearchClock


def test_search_clock_does_not_count_setup():
    """Database builds and first-use compilation are set-up, not search time."""
    clock = _SearchClock(0.2)
    clock.setup(time.sleep, 0.3)
    assert not clock.expired()
    time.sleep(0.25)
    assert clock.expired()


def test_search_clock_counts_a_kind_as_setup_only_once():
    clock = _SearchClock(0.15)
    kind = f"test-kind-{time.monotonic_ns()}"
    clock.first_use(kind, time.sleep, 0.2)      # first use: set-up
    assert not clock.expired()
    clock.first_use(kind, time.sleep, 0.2)      # second use: search
    assert clock.expired()
