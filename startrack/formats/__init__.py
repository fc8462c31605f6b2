"""Reading, validating and writing startrack's files (``docs/formats.md``).

* Frame documents (``startrack.frame/1``): JSON objects, one per image, and
  JSON Lines for many images; see :mod:`startrack.formats.frame`.
* HDF5 catalogs and databases (``startrack.catalog/1``, ``startrack.kvector/1``,
  ``startrack.labels/1``): see :mod:`startrack.formats.hdf5`.
* Every output is written to a temporary file beside its destination and renamed
  into place (:mod:`startrack.formats.atomic`), so a crash never leaves a
  half-written file.
"""
from startrack.formats.atomic import atomic_open, atomic_path
from startrack.formats.frame import (
    FRAME_FORMAT,
    FrameWriter,
    check_format_tag,
    dumps_frame,
    read_frames,
    read_json_file,
    validate_frame,
)

__all__ = [
    "FRAME_FORMAT",
    "FrameWriter",
    "atomic_open",
    "atomic_path",
    "check_format_tag",
    "dumps_frame",
    "read_frames",
    "read_json_file",
    "validate_frame",
]
