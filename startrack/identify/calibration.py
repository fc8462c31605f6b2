"""Paper 003's Eq. 9 calibration carried from frame to frame over a stream of frames.

The brightness-referenced search (:mod:`startrack.identify.brightness`) needs ``In_k``,
the intensity of a star of catalog magnitude ``k`` (Eqs. 7-9), to run its reference-star
mode and its magnitude window.  The paper obtains it "by averaging the intensity values
of an identified bright star in different images".  Over a stream, :class:`CalibrationCarry`
does that: every identified frame's brightest identified star gives ``In_k``
(``details["calibration"]`` of the accepted proposal); the next frame is searched with
the mean of the last ``window`` of them instead of starting again from nothing.  A
calibration given by the user (a sensor calibration) is the start, used until the first
frame is identified; without one, the frames before the first identification run the
four-star mode only.

Each frame records what it was searched with: ``calibration_used`` (``k:In_k`` or
None), ``calibration_source`` (``given``, ``carried`` or ``none``),
``calibration_from_frame`` (the latest frame, 0-based in the stream, whose star is in a
carried mean) and ``calibration_frames`` (how many frames the mean holds).  The frame's
own measurement stays in ``calibration``.
"""
from __future__ import annotations

import dataclasses
from collections import deque

from startrack.identify.brightness import intensity_calibration, parse_calibration

__all__ = ["CalibrationCarry", "carries_calibration"]


def carries_calibration(config) -> bool:
    """True when ``config`` (an algorithm's settings) takes Eq. 9's ``brightness_calibration``."""
    return dataclasses.is_dataclass(config) and any(f.name == "brightness_calibration"
                                                   for f in dataclasses.fields(config))


class CalibrationCarry:
    """Eq. 9's ``In_k`` carried over a stream of frames (identified frames calibrate the next).

    Parameters
    ----------
    given : str
        The user's ``k:In_k`` ("" for none): the start.
    window : int
        Identified frames averaged (the most recent ones).
    """

    def __init__(self, given: str = "", window: int = 10):
        if window < 1:
            from startrack.errors import BadInputError

            raise BadInputError("window", None, f"must be at least 1, got {window}")
        self.given = parse_calibration(given)
        self.given_text = given or ""
        self.samples: deque = deque(maxlen=int(window))     # (frame index, k, In_k)

    def current(self):
        """``(text, fields)``: the ``k:In_k`` to search the next frame with, and the fields that record it."""
        if self.samples:
            k = self.samples[-1][1]
            # Restate every sample at the same k (Eq. 9) and average, as the paper averages its reference star.
            cal = intensity_calibration([(k, in_k * 2.512 ** (k_i - k)) for _, k_i, in_k in self.samples], k)
            text = f"{cal[0]:g}:{cal[1]:.6g}"
            return text, {"calibration_used": text, "calibration_source": "carried",
                          "calibration_from_frame": int(self.samples[-1][0]),
                          "calibration_frames": len(self.samples)}
        if self.given is not None:
            return self.given_text, {"calibration_used": self.given_text, "calibration_source": "given"}
        return "", {"calibration_used": None, "calibration_source": "none"}

    def config_for(self, config):
        """``(config with the current calibration, fields recording it)``."""
        text, fields = self.current()
        return dataclasses.replace(config, brightness_calibration=text), fields

    def update(self, result, frame_index: int) -> None:
        """Take an identified frame's measurement (``details["calibration"]``); a failed frame gives none."""
        if not result.ok:
            return
        cal = parse_calibration(str((result.details or {}).get("calibration") or ""))
        if cal is not None:
            self.samples.append((int(frame_index), cal[0], cal[1]))
