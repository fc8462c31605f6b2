"""Running a per-frame stage over a stream of frame documents, the same way in every command.

* One document in, and it is invalid: one line on stderr, exit status 2, nothing
  written (the contract of ``docs/formats.md``).
* Many documents: an invalid frame is written on with its section marked
  ``"status": "failed"`` and the reason (nothing is dropped), a line goes to
  stderr, the batch goes on, and the command ends with exit status 2.
* A frame the stage cannot solve is not an error: the stage writes its
  ``failed`` section and the exit status stays 0.
"""
from __future__ import annotations

import click

from startrack.errors import BadInputError


def run_frames(input_path: str, output: str, section: str, process, quiet: bool, label: str,
               need: tuple = ()) -> None:
    """Apply ``process(doc, source, index, total) -> doc`` to every frame of ``input_path``; write to ``output``.

    ``process`` raises :class:`BadInputError` for input it cannot use.
    """
    from startrack.formats.frame import FRAME_FORMAT, FrameWriter, read_frames, validate_frame
    from startrack.progress import ProgressBar

    records = list(read_frames(input_path))
    if not records:
        raise BadInputError("<stdin>" if input_path == "-" else input_path, None, "holds no frame document")
    single = len(records) == 1
    bar = ProgressBar(label, quiet)
    n_bad = 0
    n_failed = 0
    with FrameWriter(output) as writer:
        for i, rec in enumerate(records):
            try:
                if rec.error is not None:
                    raise rec.error
                validate_frame(rec.doc, rec.source, need)
                out = process(rec.doc, rec.source, i, len(records))
                if isinstance(out.get(section), dict) and out[section].get("status") == "failed":
                    n_failed += 1
            except BadInputError as exc:
                if single:
                    raise
                n_bad += 1
                if not quiet:
                    click.echo(f"startrack {label}: {exc}", err=True)
                out = dict(rec.doc) if isinstance(rec.doc, dict) else {"format": FRAME_FORMAT, "source": rec.source}
                out.setdefault("format", FRAME_FORMAT)
                out[section] = {"status": "failed", "reason": f"bad input: {exc}"}
            writer.write(out)
            bar(i + 1, len(records))
    if not quiet:
        click.echo(f"{label}: {len(records)} frame(s), {len(records) - n_failed - n_bad} ok, {n_failed} failed"
                   + (f", {n_bad} with bad input" if n_bad else ""), err=True)
    if n_bad:
        raise SystemExit(2)
