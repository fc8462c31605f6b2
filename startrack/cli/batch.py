"""Running a per-frame stage over a stream of frame documents, the same way in every command.

* **Streaming**: one frame document is read, processed, written and flushed
  before the next is read (memory O(1) in the number of frames), so
  ``identify | attitude`` answers each frame as it arrives.  With ``-j N`` up to
  ``2 N`` frames are in flight on N threads and the output keeps input order.
* **One document in, and it is invalid**: one line on stderr, exit status 2,
  nothing written (the contract of ``docs/formats.md``).  A bad first frame is
  held back until the next one arrives, so this needs no look-ahead of good frames.
* **Many documents**: an invalid frame is written on with its section marked
  ``"status": "failed"`` and the reason (nothing is dropped), a line goes to
  stderr (also with ``-q``), the batch goes on.
* **Exit status** (:class:`BatchTally`): 0 when every frame succeeded, 1 when any
  frame failed (status failed with a reason), 2 when any input was bad.  A failed
  frame gets one line on stderr (its source and reason), also with ``-q``.  The
  summary line counts ok / failed / bad input; ``-q`` hides it only when all is well.
* **Journal and resume**: a file output gets each frame's line as it finishes;
  ``--resume`` skips the frames already there (:class:`~startrack.formats.frame.FrameWriter`).
"""
from __future__ import annotations

import collections
import logging
import os
import queue
import threading
from dataclasses import dataclass, field

import click

from startrack.errors import BadInputError

__all__ = ["BatchTally", "StreamNames", "resolve_image_path", "run_frames", "section_status"]

log = logging.getLogger(__name__)


def section_status(doc, section: str) -> str | None:
    """The ``status`` string of ``doc[section]`` (``"ok"``, ``"failed"``) or ``None``."""
    sec = doc.get(section) if isinstance(doc, dict) else None
    if isinstance(sec, dict):
        status = sec.get("status")
        return getattr(status, "value", status)
    return None


@dataclass
class BatchTally:
    """Counts of a batch and the exit status they mean."""

    label: str
    quiet: bool = False
    unit: str = "frame"
    ok: int = 0
    failed: int = 0
    bad: int = 0
    skipped: int = 0
    notes: list = field(default_factory=list)

    @property
    def total(self) -> int:
        return self.ok + self.failed + self.bad

    def add(self, status: str | None, bad: bool = False) -> None:
        if bad:
            self.bad += 1
        elif status == "failed":
            self.failed += 1
        else:
            self.ok += 1

    def error(self, message: str) -> None:
        """An error line on stderr: shown also with ``-q``."""
        click.echo(f"startrack {self.label}: {message}", err=True)

    @property
    def exit_code(self) -> int:
        return 2 if self.bad else 1 if self.failed else 0

    def summary(self) -> str:
        parts = [f"{self.ok} ok", f"{self.failed} failed", f"{self.bad} bad input"]
        text = f"{self.label}: {self.total} {self.unit}(s), " + ", ".join(parts)
        if self.skipped:
            text += f"; {self.skipped} already in the output (--resume)"
        return text + "".join(f"; {n}" for n in self.notes)

    def finish(self) -> None:
        """Print the summary (unless ``-q`` and all is well) and exit with the batch's status."""
        if not self.quiet or self.exit_code:
            click.echo(self.summary(), err=True)
        if self.exit_code:
            raise SystemExit(self.exit_code)


class InternalFrameError(Exception):
    """A frame that hit a bug (not the input's fault): written as failed, the batch goes on, exit status 1."""


def _failed_doc(rec, section, exc):
    from startrack.formats.frame import FRAME_FORMAT

    out = dict(rec.doc) if isinstance(rec.doc, dict) else {"format": FRAME_FORMAT, "source": rec.source}
    out.setdefault("format", FRAME_FORMAT)
    out[section] = {"status": "failed", "reason": f"bad input: {exc}", "bad_input": True}
    return out


def _threaded(records, work, jobs):
    """Yield ``work(rec)`` for every record, in order, with up to ``2 jobs`` in flight.

    A reader thread fills a bounded queue, so a finished frame is written while
    the next input is still awaited (a pipe held open between frames).
    """
    from concurrent.futures import ThreadPoolExecutor

    window = 2 * jobs
    inbox: queue.Queue = queue.Queue(maxsize=window)
    end = object()
    failure: list = []

    def reader():
        try:
            for rec in records:
                inbox.put(rec)
        except BaseException as exc:  # noqa: BLE001 - handed to the main thread
            failure.append(exc)
        finally:
            inbox.put(end)

    threading.Thread(target=reader, daemon=True, name="startrack-reader").start()
    pending: collections.deque = collections.deque()
    eof = False
    with ThreadPoolExecutor(jobs) as pool:
        while True:
            while pending and pending[0].done():
                yield pending.popleft().result()
            if eof and not pending:
                break
            if not eof and len(pending) < window:
                try:
                    rec = inbox.get(timeout=0.02 if pending else None)
                except queue.Empty:
                    continue
                if rec is end:
                    eof = True
                    if failure:
                        raise failure[0]
                    continue
                pending.append(pool.submit(work, rec))
            else:
                pending[0].result()
    if failure:
        raise failure[0]


class StreamNames:
    """Output names per frame when the number of frames is not known in advance.

    The first frame gets ``pattern`` itself; when a second frame arrives the first
    file is renamed to ``NAME-0000.EXT`` and every frame gets its number, so one
    frame writes ``sky.png`` and many write ``sky-0000.png``, ``sky-0001.png`` ...
    (the names :func:`startrack.render.numbered_path` gives when the count is known).
    """

    def __init__(self, pattern: str | None):
        self.pattern = pattern
        self._lock = threading.Lock()
        self._many = False

    def numbered(self, index: int) -> str:
        import os

        root, ext = os.path.splitext(self.pattern)
        return f"{root}-{index:04d}{ext}"

    def __call__(self, index: int) -> str | None:
        import contextlib
        import os

        if self.pattern is None:
            return None
        with self._lock:
            if index == 0 and not self._many:
                return self.pattern
            if not self._many:
                self._many = True
                with contextlib.suppress(OSError):
                    os.replace(self.pattern, self.numbered(0))
            return self.numbered(index)


def resolve_image_path(rec) -> None:
    """Make a relative ``image.path`` of a document read from a file resolve against that file's directory.

    A relative path stays relative (now to the current directory), so the document this command writes
    names its image relative to its own directory again (:class:`~startrack.formats.frame.FrameWriter`).
    """
    from startrack.formats.frame import resolve_path

    doc = rec.doc
    if rec.base_dir and isinstance(doc, dict) and isinstance(doc.get("image"), dict):
        path = doc["image"].get("path")
        if isinstance(path, str) and path and path != "-" and not os.path.isabs(path):
            resolved = resolve_path(path, rec.base_dir)
            try:
                resolved = os.path.relpath(resolved)
            except ValueError:      # another drive (Windows): keep it absolute
                pass
            doc["image"]["path"] = resolved


def run_frames(input_path: str, output: str, section: str, process, quiet: bool, label: str,
               need: tuple = (), jobs: int = 1, resume: bool = False, records=None, status=None,
               unit: str = "frame", note=None, finish: bool = True):
    """Apply ``process(doc, source, index, total) -> doc`` to every frame of ``input_path``; write to ``output``.

    ``process`` raises :class:`BadInputError` for input it cannot use; a frame it
    cannot solve carries ``status: failed`` in ``doc[section]``.  ``total`` is
    ``None`` (frames stream in; their number is not known in advance).  Ends with
    :meth:`BatchTally.finish` (exit status 0, 1 or 2).  ``records`` replaces
    reading ``input_path`` (an iterable of :class:`~startrack.formats.frame.FrameRecord`);
    ``status(doc) -> "ok" | "failed"`` replaces reading ``doc[section]["status"]``;
    ``note() -> str`` adds to the summary line.  With ``finish=False`` the
    :class:`BatchTally` is returned instead (the caller prints its own summary
    and exits with :attr:`BatchTally.exit_code`).
    """
    from startrack.formats.frame import FrameWriter, read_frames, validate_frame
    from startrack.progress import ProgressBar

    name = "<stdin>" if input_path == "-" else input_path
    if jobs < 1:
        raise BadInputError("--jobs", None, f"must be at least 1, got {jobs}")
    if resume and output == "-":
        raise BadInputError("--resume", None, "needs an output file (-o FILE) to resume into")
    writer = FrameWriter(output, resume=resume, section=section)
    if records is None:
        records = read_frames(input_path)
    tally = BatchTally(label, quiet, unit)
    bar = ProgressBar(label, quiet)

    def work(item):
        index, rec = item
        try:
            if rec.error is not None:
                raise rec.error
            validate_frame(rec.doc, rec.source, need)
            out = process(rec.doc, rec.source, index, None)
            return rec, out, None
        except BadInputError as exc:
            return rec, _failed_doc(rec, section, exc), exc
        except Exception as exc:  # noqa: BLE001 - one frame's bug must not sink the batch
            if os.environ.get("STARTRACK_DEBUG"):
                raise
            from startrack.errors import input_of

            msg = str(exc).splitlines()[0] if str(exc) else ""
            where = input_of(exc)   # a file this frame named (its image) that the exception came from reading
            inner = f" while reading {where[0]}{f': {where[1]}' if where[1] else ''}" if where and where[2] else ""
            reason = f"internal error{inner}: {type(exc).__name__}: {msg}"
            out = _failed_doc(rec, section, f"{type(exc).__name__}: {msg}")
            out[section] = {"status": "failed", "reason": reason}
            return rec, out, InternalFrameError(f"{rec.source}: {reason}")

    def numbered():
        index = 0
        for rec in records:
            resolve_image_path(rec)
            if rec.error is None and writer.skip(rec.doc):
                tally.skipped += 1
                continue
            yield index, rec
            index += 1

    results = map(work, numbered()) if jobs <= 1 else _threaded(numbered(), work, jobs)
    held = None  # a bad first frame, written only once we know it is not the only one
    n_seen = 0
    with writer:
        for rec, out, exc in results:
            n_seen += 1
            if held is not None:
                _write_bad(writer, tally, *held)
                held = None
            if isinstance(exc, InternalFrameError):
                tally.error(str(exc))
                writer.write(out)
                tally.add("failed")
                continue
            if exc is not None and n_seen == 1:
                held = (rec, out, exc)
                continue
            if exc is not None:
                _write_bad(writer, tally, rec, out, exc)
            else:
                writer.write(out)
                st = status(out) if status is not None else section_status(out, section)
                tally.add(st)
                sec = out.get(section) if isinstance(out, dict) else None
                why = sec.get("reason") if isinstance(sec, dict) and st == "failed" else None
                log.info("%s %d (%s): %s%s", unit, n_seen, rec.source, st or "ok", f": {why}" if why else "")
                if st == "failed":
                    # one line per failed frame, also with -q: -q hides progress, never a failure
                    tally.error(f"{rec.source}: {section} failed: {why or 'no reason given'}")
            bar(tally.total, tally.total + 1)
        if held is not None:
            if n_seen == 1 and tally.skipped == 0:
                raise held[2]
            _write_bad(writer, tally, *held)
        if n_seen == 0 and tally.skipped == 0:
            raise BadInputError(name, None, "holds no frame document")
    bar(tally.total, tally.total)
    if note is not None:
        tally.notes.append(note())
    if not finish:
        return tally
    tally.finish()
    return tally


def _write_bad(writer, tally, rec, out, exc):  # noqa: ARG001 - the caller's signature
    tally.error(str(exc))
    writer.write(out)
    tally.add(None, bad=True)
