"""Progress bars on stderr (tqdm), for long commands.

Library functions take an optional ``progress`` callable ``progress(done, total)``;
commands pass a :class:`ProgressBar`.  A bar is drawn only when stderr is a
terminal and the command is not ``--quiet``: a log file or a pipe gets no
progress lines, and errors are never hidden.  Nothing here imports click.
"""
from __future__ import annotations

import sys

__all__ = ["ProgressBar"]


class ProgressBar:
    """``ProgressBar(label, quiet)(done, total)``: a tqdm bar driven by ``(done, total)`` calls.

    Parameters
    ----------
    label : str
        Shown before the bar (the command's name).
    quiet : bool
        No bar at all.
    stream : file, optional
        Where to draw (default stderr); a bar is drawn only when it is a terminal.
    unit : str, optional
        What is counted (``"frame"``): the bar then shows frames per second.
    """

    def __init__(self, label: str, quiet: bool = False, stream=None, unit: str = ""):
        self.stream = stream or sys.stderr
        self.unit = unit
        self.enabled = not quiet and hasattr(self.stream, "isatty") and self.stream.isatty()
        self.label = label
        self._bar = None

    def __call__(self, done: int, total: int) -> None:
        if not self.enabled:
            return
        if self._bar is None:
            from tqdm import tqdm

            self._bar = tqdm(total=total, desc=self.label, file=self.stream, unit=self.unit, leave=True,
                             dynamic_ncols=True, mininterval=0.1)
        if total != self._bar.total:
            self._bar.total = total
        self._bar.update(done - self._bar.n)
        if done >= total:
            self.close()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
