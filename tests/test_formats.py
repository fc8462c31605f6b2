import json
import os

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from startrack.errors import BadInputError
from startrack.formats import FrameWriter, atomic_open, dumps_frame, read_frames, validate_frame
from startrack.formats.hdf5 import read_hdf5, write_hdf5
from startrack.records import Status

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


def _old_json_value(value):
    """records._json_value before its exact-type fast paths (the reference of the test below)."""
    import math

    from startrack.records import enum_types

    if isinstance(value, enum_types()):
        return value.value
    if isinstance(value, dict):
        return {str(k): _old_json_value(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_old_json_value(v) for v in value]
    if isinstance(value, np.ndarray):
        return _old_json_value(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return value if math.isfinite(value) else None
    return value


_LEAVES = st.one_of(st.none(), st.booleans(), st.integers(-2**70, 2**70), st.floats(allow_nan=True, allow_infinity=True),
                    st.text(max_size=5), st.sampled_from(["ok", "failed"]).map(lambda v: Status(v)),
                    st.integers(-1000, 1000).map(np.int64), st.floats(-1e30, 1e30).map(np.float64),
                    st.floats(-1e6, 1e6, width=32).map(np.float32), st.booleans().map(np.bool_),
                    st.lists(st.floats(-1e6, 1e6), max_size=4).map(np.array),
                    st.lists(st.integers(-5, 5), max_size=4).map(lambda v: np.array(v, dtype=np.int32)))
_KEYS = st.one_of(st.text(max_size=4), st.integers(-5, 5), st.booleans(), st.none(), st.floats(-1e20, 1e20))


def _distinct_keys(d) -> bool:
    """A dict whose keys stay distinct written as JSON strings (1 and "1", None and "null" do not: no JSON object
    holds both, and the encoder writes both where a copy keeps one)."""
    from startrack.formats.frame import _json_key

    return len({k if type(k) is str else _json_key(k) for k in d}) == len(d)


_DOCS = st.recursive(_LEAVES, lambda inner: st.one_of(st.lists(inner, max_size=4), st.tuples(inner, inner),
                                                      st.dictionaries(_KEYS, inner, max_size=4).filter(_distinct_keys)),
                     max_leaves=25)


def _same_json(line: str, want: str) -> bool:
    """Two JSON texts of the same values, in the same order, ints and floats told apart (re-encoded alike: the
    float digits of orjson's line and the standard library's are the same, their exponents written otherwise)."""
    return line.isascii() and json.dumps(json.loads(line)) == json.dumps(json.loads(want))


@pytest.fixture(params=["orjson", "json"])
def encoder(request, monkeypatch):
    """dumps_frame with orjson (the first document imports it) and without (the standard library's encoder alone,
    as where orjson is not installed)."""
    from startrack.formats import frame

    monkeypatch.setattr(frame, "_ORJSON", [None if request.param == "orjson" else False])
    return request.param


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(doc=_DOCS)
def test_json_values_and_lines_are_the_copys(encoder, doc):
    """records._json_value's fast paths give its old values; dumps_frame's line (the document straight to the encoder
    when it can take it) holds the values of the document copied through _to_json, NaN, NumPy values and keys of
    every kind included, in ASCII; the standard library's encoder alone writes the copy's very line."""
    import math

    from startrack.formats.frame import _to_json
    from startrack.records import _json_value

    def same(a, b):
        if isinstance(a, float) and isinstance(b, float):
            return a == b or (math.isnan(a) and math.isnan(b))
        if type(a) is not type(b):
            return False
        if isinstance(a, dict):
            return list(a) == list(b) and all(same(a[k], b[k]) for k in a)
        if isinstance(a, list):
            return len(a) == len(b) and all(map(same, a, b))
        return a == b

    assert same(_json_value(doc), _old_json_value(doc))
    try:
        want = json.dumps(_to_json(doc), separators=(",", ":"), allow_nan=False)
    except (TypeError, ValueError) as exc:       # (a value JSON has no place for): refused alike
        with pytest.raises(type(exc)):
            dumps_frame(doc)
        return
    wrapped = {"frame": [doc, np.arange(2.0)]}
    want_wrapped = json.dumps(_to_json(wrapped), separators=(",", ":"), allow_nan=False)
    if encoder == "json":
        assert dumps_frame(doc) == want
        assert dumps_frame(wrapped) == want_wrapped
    else:
        assert _same_json(dumps_frame(doc), want)
        assert _same_json(dumps_frame(wrapped), want_wrapped)


def test_a_solve_documents_line_is_the_copys(encoder, monkeypatch):
    """The frame document of a real solve (NumPy values, many floats) gives the copy's values (its very line with the
    standard library's encoder), straight: with orjson, without the standard library's encoder."""
    from startrack import Solver
    from startrack.formats import frame
    from startrack.formats.frame import _to_json
    from startrack.records import solve_result_to_frame

    path = os.path.join(os.path.dirname(__file__), "data", "real", "2019-07-29T204726_Alt60_Azi135_Try1.tiff")
    doc = solve_result_to_frame(Solver().solve(path))
    assert doc["solve"]["status"] == "ok"
    want = json.dumps(_to_json(doc), separators=(",", ":"), allow_nan=False)
    if encoder == "orjson":
        def refuse(_doc):
            raise AssertionError("the standard library's encoder was used")

        monkeypatch.setattr(frame, "_ENCODE", refuse)
        line = dumps_frame(doc)
        assert _same_json(line, want)
    else:
        line = dumps_frame(doc)
        assert line == want
    assert json.loads(line)["attitude"]["quaternion"] == [float(v) for v in doc["attitude"]["quaternion"]]


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
