"""Issue 41 (reliability v3): no silent wrong table, no destroyed input, every cache checked, errors named.

Each test's docstring says what main did before the fix.
"""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import assert_refused, run_cli


@pytest.fixture(scope="module")
def db20(tmp_path_factory):
    """A small k-vector database (20 deg field, Hp <= 4)."""
    path = tmp_path_factory.mktemp("rel-db") / "db.h5"
    run_cli("build-kvector", "--fov-deg", "20", "--mag-max", "4", "-o", path, "-q", check=True)
    return path


# -- item 1: a wrong table, silently -----------------------------------------------------------------------------

def test_make_frames_never_returns_a_frame_below_min_stars(catalog):
    """main: after 1000 attitudes make_frames kept the last frame whatever its star count (mean 3.3 stars under a
    ">= 1000 stars" condition).  Now: every frame returned meets the condition, and an unmet one is an error."""
    from startrack.camera import Camera
    from startrack.errors import ParameterError
    from startrack.evaluate import Condition, make_frames

    cam = Camera.from_fov(20, 512, 512)
    cat = catalog.filter_magnitude(None, 4.0)
    frames = make_frames(cat, cam, Condition(min_stars=6), 20, 3, mag_limit=4.0)
    assert all(len(stars) >= 6 for stars, _, _ in frames)
    with pytest.raises(ParameterError) as info:
        make_frames(cat, cam, Condition(min_stars=1000), 1, 3, mag_limit=4.0)
    assert info.value.parameter == "min_stars" and "1000" in info.value.problem
    with pytest.raises(ParameterError) as info:
        make_frames(cat, cam, Condition(false_stars=50, min_stars=3, min_catalog_stars=500), 1, 3, mag_limit=4.0)
    assert info.value.parameter == "min_catalog_stars"


def test_evaluate_refuses_an_unmet_min_stars(db20):
    """main: `evaluate --min-stars 1000` exit 0 with a table row ">= 1000 stars" over frames of ~3 stars."""
    proc = run_cli("evaluate", "-d", db20, "--fov-deg", "20", "--size", "512x512", "-a", "pyramid", "-n", "2",
                   "--seed", "1", "--min-stars", "1000", "-q")
    assert_refused(proc, "--min-stars", "no frame with at least 1000 stars")


# -- item 2: an output that is an input --------------------------------------------------------------------------

def _eight_documents(path):
    from startrack.camera import Camera

    camera = Camera.from_fov(20, 512, 512).to_dict()
    docs = [{"format": "startrack.frame/1", "frame": k, "camera": camera,
             "stars": [{"x": 10.0 + k, "y": 20.0, "flux": 100.0}]} for k in range(8)]
    path.write_text("".join(json.dumps(d) + "\n" for d in docs))
    return path.read_bytes()


def test_an_output_that_is_an_input_is_refused(db20, tmp_path):
    """main: `identify inout.jsonl -o inout.jsonl` turned 8 documents into 2 lines, then blamed "invalid JSON".
    Now: exit 2 naming the file, before anything is written, through a link, a hard link or stdin too."""
    inout = tmp_path / "inout.jsonl"
    before = _eight_documents(inout)
    (tmp_path / "link.jsonl").symlink_to(inout)
    os.link(inout, tmp_path / "hard.jsonl")
    for out in (inout, tmp_path / "link.jsonl", tmp_path / "hard.jsonl"):
        proc = run_cli("identify", inout, "-d", db20, "-o", out)
        assert_refused(proc, str(out), "is also an input of this command")
        assert inout.read_bytes() == before
    proc = run_cli("attitude", "-o", inout, input=before.decode())  # stdin is a pipe here: not a file
    assert proc.returncode == 2 and "is also an input" not in proc.stderr  # (bad frames: no identification)
    inout.write_bytes(before)
    with open(inout, "rb") as stdin:  # `< inout.jsonl -o inout.jsonl`
        proc = subprocess.run([sys.executable, "-m", "startrack", "attitude", "-o", str(inout)], stdin=stdin,
                              capture_output=True, text=True, timeout=120)
    assert_refused(proc, "is also an input of this command (<stdin>)")
    assert inout.read_bytes() == before
    # the other commands inherit it: a database over the catalog it is built from, a camera over its camera
    cat = tmp_path / "cat.h5"
    run_cli("catalog-filter", "--mag-max", "3", "-o", cat, check=True)
    catalog_bytes = cat.read_bytes()
    proc = run_cli("catalog-filter", "--catalog", cat, "--mag-max", "2", "-o", cat)
    assert_refused(proc, str(cat), "is also an input")
    proc = run_cli("build-kvector", "--catalog", cat, "--fov-deg", "20", "-o", cat)
    assert_refused(proc, str(cat), "is also an input")
    assert cat.read_bytes() == catalog_bytes
    # and an output that is not an input is written as before
    proc = run_cli("catalog-filter", "--catalog", cat, "--mag-max", "2", "-o", tmp_path / "cat2.h5")
    assert proc.returncode == 0, proc.stderr


def test_library_writers_refuse_a_registered_input(tmp_path):
    """main had no notion of an input in its writers.  Now atomic_open and FrameWriter refuse a file the
    process reads (read_frames registers it), and forget an input whose inode was deleted and reused."""
    from startrack.errors import BadInputError
    from startrack.formats.atomic import atomic_open
    from startrack.formats.frame import FrameWriter, read_frames

    path = tmp_path / "in.jsonl"
    before = _eight_documents(path)
    records = read_frames(str(path))
    next(records)
    with pytest.raises(BadInputError, match="is also an input"):
        with atomic_open(str(path)) as fh:
            fh.write("x")
    with pytest.raises(BadInputError, match="is also an input"):
        with FrameWriter(str(path)) as writer:
            writer.write({"format": "startrack.frame/1"})
    assert path.read_bytes() == before
    records.close()
    os.remove(path)
    with atomic_open(str(path)) as fh:  # a new file, perhaps on the deleted input's inode: writable
        fh.write("new\n")
    assert path.read_text() == "new\n"


# -- item 4: --resume trusts any document ------------------------------------------------------------------------

def test_resume_refuses_another_commands_document(db20, tmp_path):
    """main: `solve --resume` counted a `centroid` document of the same image as solved (exit 0, nothing solved).
    Now: every line kept must be this command's result with a status; another command's is refused (exit 2)."""
    image = os.path.join(os.path.dirname(__file__), "..", "data", "real", "2019-07-29T204726_Alt40_Azi45_Try1.tiff")
    out = tmp_path / "solved.jsonl"
    centroid_doc = {"format": "startrack.frame/1", "image": {"path": image}, "stars": [],
                    "centroid": {"method": "cog", "n_stars": 0}}
    out.write_text(json.dumps(centroid_doc) + "\n")
    before = out.read_bytes()
    proc = run_cli("solve", image, "-o", out, "--resume", "-q")
    assert_refused(proc, f"{out}:1: solve: is missing", "another command's result")
    assert out.read_bytes() == before
    # identify (and every run_frames command): the same rule, and an unknown status is not "done"
    docs = tmp_path / "in.jsonl"
    _eight_documents(docs)
    proc = run_cli("identify", docs, "-d", db20, "-o", out, "--resume", "-q")
    assert_refused(proc, f"{out}:1: identification: is missing")
    first = json.loads(docs.read_text().splitlines()[0])
    out.write_text(json.dumps({**first, "identification": {"status": "pending"}}) + "\n")
    proc = run_cli("identify", docs, "-d", db20, "-o", out, "--resume", "-q")
    assert_refused(proc, f"{out}:1: identification.status: is 'pending'")
    # its own output resumes as before: the 8 frames once each
    out.unlink()
    run_cli("identify", docs, "-d", db20, "-o", out, "-q")
    lines = out.read_text().splitlines()
    out.write_text("\n".join(lines[:3]) + "\n")
    proc = run_cli("identify", docs, "-d", db20, "-o", out, "--resume")
    assert [json.loads(line)["frame"] for line in out.read_text().splitlines()] == list(range(8)), proc.stderr


# -- item 5: the pattern index has no checksum --------------------------------------------------------------------

@pytest.fixture(scope="module")
def small_catalog(catalog):
    return catalog.filter_magnitude(None, 4.0)


def _overwrite(path, offset, size=4096, seed=0):
    with open(path, "r+b") as fh:
        fh.seek(offset)
        fh.write(np.random.default_rng(seed).bytes(size))


def _array_offset(path, name):
    with open(path, "rb") as fh:
        fh.seek(8)
        head_len = int(np.frombuffer(fh.read(8), dtype=np.uint64)[0])
        header = json.loads(fh.read(head_len - 16))
    return head_len + header["arrays"][name]["offset"]


def test_a_damaged_pattern_index_is_named_and_never_reaches_a_kernel(small_catalog, tmp_path):
    """main: 4 KB overwritten in the star-vector block gave "internal error: ValueError: cannot convert float NaN to
    integer" on every later solve, 15 blocks a segmentation fault, elsewhere nothing.  Now every damage is refused
    with the file and the array named (checksums, then every index a kernel follows checked)."""
    from dataclasses import replace

    from startrack.errors import BadInputError
    from startrack.patterns import build_index, check_index, open_index, save_index

    index = build_index(small_catalog)
    path = str(tmp_path / "p.idx")
    save_index(index, path)
    good = open(path, "rb").read()
    assert len(open_index(path).keys) == len(index.keys)
    damage = [(_array_offset(path, "star_vec"), "data_sha256"), (_array_offset(path, "patterns") + 64, "data_sha256"),
              (len(good) - 100, "data_sha256"), (40, None)]
    for offset, field in damage:
        open(path, "wb").write(good)
        open_index(path)
        _overwrite(path, offset, size=min(4096, len(good) - offset))
        with pytest.raises(BadInputError) as info:
            open_index(path)
        assert info.value.source == path and (field is None or info.value.field == field), str(info.value)
    # an index whose checksums hold but whose rows lie (built wrong, or forged) is refused before any kernel
    bad_rows = index.patterns.copy()
    bad_rows[5, 2] = len(index.star_id) + 7
    with pytest.raises(BadInputError, match="patterns: names a star row beyond"):
        check_index(replace(index, patterns=bad_rows), "forged")
    prefix = index.level_prefix.copy()
    prefix[1, 100] = 10**9
    with pytest.raises(BadInputError, match="level_prefix"):
        save_index(replace(index, level_prefix=prefix), str(tmp_path / "forged.idx"))
    vec = index.star_vec.copy()
    vec[3] = np.nan
    with pytest.raises(BadInputError, match="star_vec"):
        check_index(replace(index, star_vec=vec), "forged")


def test_damaged_cached_index_is_rebuilt_and_one_process_builds(small_catalog, tmp_path, monkeypatch, caplog):
    """main: a damaged cached index was never named nor rebuilt (until `cache clear`), and two processes on an
    empty cache both built it (no lock around the index).  Now: a warning names the file, it is rebuilt, and a
    second process waits for the first one's build."""
    from startrack.patterns import default_index, default_index_path

    monkeypatch.setenv("STARTRACK_CACHE", str(tmp_path / "cache"))
    first = np.array(default_index(small_catalog).star_vec)  # a copy: the damage below is in place
    path = default_index_path(small_catalog)
    _overwrite(path, _array_offset(path, "star_vec"))
    with caplog.at_level("WARNING", logger="startrack"):
        again = default_index(small_catalog)
    assert path in caplog.text and "data_sha256" in caplog.text and "rebuilding" in caplog.text
    assert np.array_equal(np.asarray(again.star_vec), first)
    os.remove(path)
    builds = tmp_path / "builds.txt"
    code = ("import time\n"
            "import startrack.patterns as P\n"
            "from startrack.catalog import load_catalog\n"
            "build = P.build_index\n"
            "def slow(*a, **k):\n"
            f"    open({str(builds)!r}, 'a').write('x')\n"
            "    time.sleep(3)\n"
            "    return build(*a, **k)\n"
            "P.build_index = slow\n"
            "P.default_index(load_catalog().filter_magnitude(None, 4.0))\n")
    env = {**os.environ, "STARTRACK_CACHE": str(tmp_path / "cache")}
    procs = [subprocess.Popen([sys.executable, "-c", code], env=env) for _ in range(2)]
    assert [p.wait(300) for p in procs] == [0, 0]
    assert builds.read_text() == "x"
