"""The identification record (issue 13's typed records; from :mod:`startrack.records` once it lands)."""
from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

__all__ = ["Identification", "Match", "ReasonCode", "Status", "to_section"]


class Status(str, enum.Enum):
    OK = "ok"
    FAILED = "failed"

    def __str__(self) -> str:
        return self.value


class ReasonCode(str, enum.Enum):
    TOO_FEW_STARS = "too_few_stars"
    NO_PATTERN = "no_pattern"
    FALSE_MATCH_PROBABILITY = "false_match_probability"
    VERIFICATION_FAILED = "verification_failed"
    TIMEOUT = "timeout"
    OTHER = "other"

    def __str__(self) -> str:
        return self.value


class Match(NamedTuple):
    """One identified star: ``star`` indexes the frame's stars, ``id`` is the catalog id (HIP)."""

    star: int
    id: int


@dataclass
class Identification:
    """The ``identification`` section: which detected star is which catalog star."""

    status: Status = Status.OK
    algorithm: str = "pyramid"
    matches: list = field(default_factory=list)
    time_ms: float | None = None
    reason: str | None = None
    reason_code: ReasonCode | str | None = None
    false_match_probability: float | None = None
    trials: int | None = None
    tolerance_arcsec: float | None = None
    focal_scale: float | None = None
    quaternion_estimate: np.ndarray | None = None
    details: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.status == Status.OK

    @classmethod
    def failed(cls, algorithm, reason, reason_code=ReasonCode.OTHER, **kw):
        return cls(Status.FAILED, algorithm, [], reason=reason, reason_code=reason_code, **kw)


def to_section(rec: Identification) -> dict:
    out = {"status": str(rec.status), "algorithm": rec.algorithm,
           "matches": [{"star": int(m.star), "id": int(m.id)} for m in rec.matches]}
    for key in ("time_ms", "reason", "reason_code", "false_match_probability", "trials", "tolerance_arcsec",
                "focal_scale"):
        v = getattr(rec, key)
        if v is not None:
            out[key] = str(v) if isinstance(v, enum.Enum) else v
    if rec.quaternion_estimate is not None:
        out["quaternion_estimate"] = [float(v) for v in rec.quaternion_estimate]
    out.update(rec.details)
    return out
