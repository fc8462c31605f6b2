import json
import os

import numpy as np
import pytest

from startrack.errors import BadInputError
from startrack.formats import FrameWriter, atomic_open, dumps_frame, read_frames, validate_frame
from startrack.formats.hdf5 import read_hdf5, write_hdf5

CAMERA = {"width": 1024, "height": 1024, "focal_length_px": 2903.7, "cx": 511.5, "cy": 511.5}


def frame(**kw):
    doc = {"format": "startrack.frame/1", "camera": dict(CAMERA), "stars": [{"x": 1.0, "y": 2.0, "flux": 3.0}]}
    doc.update(kw)
    return doc


def test_validate_ok():
    validate_frame(frame(), "f.json", need=("camera", "stars"))


@pytest.mark.parametrize(
    "doc, field",
    [
        ({"camera": CAMERA}, "format"),
        (frame(format="startrack.kvector/1"), "format"),
        (frame(format="startrack.frame/2"), "format"),
        (frame(camera=dict(CAMERA, focal_length_px=None)), "camera.focal_length_px"),
        (frame(camera={k: v for k, v in CAMERA.items() if k != "cy"}), "camera.cy"),
        (frame(stars=[{"y": 1.0}]), "stars[0].x"),
        (frame(stars=[{"x": float("nan"), "y": 1.0}]), "stars[0].x"),
        (frame(stars=[{"x": "3", "y": 1.0}]), "stars[0].x"),
        (frame(stars="none"), "stars"),
    ],
)
def test_validate_refusals_name_the_field(doc, field):
    with pytest.raises(BadInputError) as info:
        validate_frame(doc, "f.json", need=("camera", "stars"))
    assert str(info.value).startswith("f.json: " + field)
    assert "\n" not in str(info.value)


def test_read_json_lines_pretty_and_array(tmp_path):
    lines = tmp_path / "a.jsonl"
    lines.write_text("\n".join(json.dumps(frame(i=i)) for i in range(3)) + "\n\n")
    recs = list(read_frames(str(lines)))
    assert [r.doc["i"] for r in recs] == [0, 1, 2]
    assert recs[1].source.endswith("a.jsonl:2")
    pretty = tmp_path / "p.json"
    pretty.write_text(json.dumps(frame(i=7), indent=2))
    assert [r.doc["i"] for r in read_frames(str(pretty))] == [7]
    arr = tmp_path / "arr.json"
    arr.write_text(json.dumps([frame(i=1), frame(i=2)], indent=1))
    assert [r.doc["i"] for r in read_frames(str(arr))] == [1, 2]


def test_bad_line_does_not_stop_the_stream(tmp_path):
    p = tmp_path / "a.jsonl"
    p.write_text(json.dumps(frame(i=0)) + "\n{not json\n" + json.dumps(frame(i=2)) + "\nNaN\n")
    recs = list(read_frames(str(p)))
    assert len(recs) == 4
    assert recs[0].doc["i"] == 0 and recs[2].doc["i"] == 2
    assert recs[1].error is not None and ":2" in str(recs[1].error)
    assert recs[3].error is not None   # a bare NaN is not JSON


def test_missing_file():
    with pytest.raises(BadInputError, match="no such file"):
        list(read_frames("/nonexistent/x.jsonl"))


def test_dumps_handles_numpy_and_nan():
    line = dumps_frame({"a": np.float32(1.5), "b": np.arange(3), "c": float("nan"), "d": np.int64(4)})
    assert json.loads(line) == {"a": 1.5, "b": [0, 1, 2], "c": None, "d": 4}


def test_frame_writer_is_a_journal_and_resumes(tmp_path):
    """Each line is on disk as soon as it is written; a cut-off last line is dropped on resume."""
    out = tmp_path / "out.jsonl"
    out.write_text("old content\n")
    with FrameWriter(str(out)):
        pass  # a run that writes nothing still leaves an (empty) output, like `>`
    assert out.read_text() == ""
    with pytest.raises(RuntimeError):
        with FrameWriter(str(out)) as w:
            w.write(frame(i=1))
            w.write(frame(i=2))
            assert [json.loads(l)["i"] for l in out.read_text().splitlines()] == [1, 2]
            raise RuntimeError("crash in the middle")
    with open(out, "a") as fh:
        fh.write('{"format": "startrack.frame/1", "i"')  # what kill -9 in mid-write leaves
    w = FrameWriter(str(out), resume=True)
    assert w.n_done == 2
    assert w.skip(frame(i=1)) and w.skip(frame(i=2)) and not w.skip(frame(i=3))
    with w:
        w.write(frame(i=3))
    assert [json.loads(l)["i"] for l in out.read_text().splitlines()] == [1, 2, 3]
    assert sorted(os.listdir(tmp_path)) == ["out.jsonl"]


def test_atomic_output_never_replaces_special_files_and_writes_through_links(tmp_path):
    from startrack.formats.atomic import atomic_open

    with atomic_open("/dev/null") as fh:
        fh.write("discarded")
    assert os.path.exists("/dev/null") and not os.path.isfile("/dev/null")
    with pytest.raises(BadInputError, match="No space left"):
        with atomic_open("/dev/full") as fh:
            fh.write("x" * 10000)
    assert not os.path.isfile("/dev/full")
    target = tmp_path / "target.txt"
    target.write_text("old")
    link = tmp_path / "link.txt"
    link.symlink_to(target)
    with atomic_open(str(link)) as fh:
        fh.write("new")
    assert link.is_symlink() and target.read_text() == "new"
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    import threading

    got = []
    reader = threading.Thread(target=lambda: got.append(open(fifo).read()))  # noqa: SIM115
    reader.start()
    with atomic_open(str(fifo)) as fh:
        fh.write("through the pipe")
    reader.join(10)
    assert got == ["through the pipe"] and not fifo.is_file()
    assert sorted(os.listdir(tmp_path)) == ["link.txt", "pipe", "target.txt"]


def test_stale_temporaries_of_dead_processes_are_cleaned(tmp_path):
    import subprocess
    import sys

    from startrack.formats.atomic import atomic_open

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    pid = int(dead.stdout)
    stale = tmp_path / f".out.txt.st{pid}-0123abcd.part.txt"
    stale.write_text("left by kill -9")
    mine = tmp_path / f".out.txt.st{os.getpid()}-0123abcd.part.txt"
    mine.write_text("a live writer's")
    with atomic_open(str(tmp_path / "out.txt")) as fh:
        fh.write("ok")
    assert not stale.exists() and mine.exists()
    assert (tmp_path / "out.txt").read_text() == "ok"


def test_atomic_open_unwritable_directory():
    with pytest.raises(BadInputError, match="does not exist"):
        with atomic_open("/nonexistent-dir/out.txt") as fh:
            fh.write("x")


def test_hdf5_round_trip_and_refusals(tmp_path):
    p = str(tmp_path / "db.h5")
    write_hdf5(p, "startrack.kvector/1", {"fov_deg": 20.0}, {"a": np.arange(5000), "b": (np.ones(3), {"unit": "deg"})},
               attrs={"catalog_sha256": "abc"})
    f = read_hdf5(p, "startrack.kvector/1")
    assert f.params == {"fov_deg": 20.0}
    assert f.attrs["catalog_sha256"] == "abc" and f.attrs["startrack_version"]
    np.testing.assert_array_equal(f["a"], np.arange(5000))
    with pytest.raises(BadInputError, match="format: is 'startrack.kvector/1', expected 'startrack.catalog/1'"):
        read_hdf5(p, "startrack.catalog/1")
    with pytest.raises(BadInputError, match="major version"):
        read_hdf5(p, "startrack.kvector/2")
    txt = tmp_path / "x.h5"
    txt.write_text("hello")
    with pytest.raises(BadInputError, match="not an HDF5 file"):
        read_hdf5(str(txt), "startrack.catalog/1")
    with pytest.raises(BadInputError, match="dataset is missing"):
        f["nope"]
