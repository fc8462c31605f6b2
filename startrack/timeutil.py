"""Times in files are ISO-8601 strings; inside, decimal Julian years and seconds."""
from __future__ import annotations

import datetime as _dt

from startrack.errors import BadInputError

_J2000 = _dt.datetime(2000, 1, 1, 12, 0, 0, tzinfo=_dt.timezone.utc)


def parse_time(text: str, source: str = "time") -> _dt.datetime:
    """Parse an ISO-8601 time (``Z`` or an offset; naive times are UTC)."""
    try:
        t = _dt.datetime.fromisoformat(str(text).strip().replace("Z", "+00:00"))
    except ValueError:
        raise BadInputError(source, None, f"not an ISO-8601 time: {text!r}") from None
    if t.tzinfo is None:
        t = t.replace(tzinfo=_dt.timezone.utc)
    return t.astimezone(_dt.timezone.utc)


def format_time(t: _dt.datetime) -> str:
    return t.astimezone(_dt.timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def julian_year(t: _dt.datetime) -> float:
    """Decimal Julian year (J2000.0 = 2000.0; 365.25 days a year), UTC taken as TT."""
    return 2000.0 + (t - _J2000).total_seconds() / (365.25 * 86400.0)


def search_clock() -> float:
    """Seconds of CPU time of this process: the clock of every search budget (``solve --timeout-s``, the blind
    and all-sky searches' deadlines).  A budget in CPU time gives a frame the same search whatever else the
    machine runs: on wall time a loaded machine (a batch beside other jobs, a test suite on two processes)
    failed frames that an idle one solves."""
    import time

    return time.process_time()
