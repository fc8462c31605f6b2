"""Faults (issue 17): kill -9 and resume, Ctrl-C while writing HDF5, device and FIFO outputs, closed pipes,
corrupt cached databases, undecodable images inside a batch, paths relative to their document."""
import json
import os
import signal
import struct
import subprocess
import sys
import threading
import time
import zlib

import numpy as np
import pytest
from conftest import assert_refused, run_cli


def _startrack(*args):
    return [sys.executable, "-m", "startrack", *map(str, args)]


def _complete_lines(path):
    if not os.path.exists(path):
        return 0
    with open(path, "rb") as fh:
        return fh.read().count(b"\n")


def bomb_png(path, width=60000, height=60000):
    """A tiny PNG whose header claims a huge image (a 'decompression bomb')."""
    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b""))
    path.write_bytes(png)
    return path


def test_kill_9_a_solve_batch_after_4_frames_then_resume(solve_cache, tmp_path):
    """16 rendered images; kill -9 once 4 documents are on disk; --resume: 16 documents, each image once."""
    run_cli("render", "--fov-deg", "20", "--size", "640x480", "--count", "16", "--mag-limit", "6", "--seed", "11",
            "-o", tmp_path / "img" / "sky.png", "-q", check=True)
    images = sorted(str(p) for p in (tmp_path / "img").iterdir())
    assert len(images) == 16
    out = tmp_path / "solved.jsonl"
    args = ["solve", *images, "--fov-deg", "20", "--timeout-s", "2", "-q", "-o", out]
    proc = subprocess.Popen(_startrack(*args), env={**os.environ, **solve_cache}, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 600
    while _complete_lines(out) < 4 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert proc.poll() is None, "the batch ended before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    before = out.read_bytes()
    n_before = before.count(b"\n")
    assert 4 <= n_before < 16
    resumed = run_cli(*args, "--resume", env=solve_cache, timeout=600)
    assert resumed.returncode in (0, 1) and "Traceback" not in resumed.stderr, resumed.stderr
    docs = [json.loads(l) for l in out.read_text().splitlines()]
    assert len(docs) == 16
    assert sorted(d["image"]["path"] for d in docs) == images  # each image exactly once
    assert out.read_bytes().startswith(before[:before.rfind(b"\n") + 1])  # finished frames kept as they were
    assert resumed.returncode == (0 if all(d["solve"]["status"] == "ok" for d in docs) else 1)
    # A second --resume finds nothing to do.
    again = run_cli(*args, "--resume", env=solve_cache, timeout=600)
    assert len(out.read_text().splitlines()) == 16 and again.returncode in (0, 1)
    assert [p for p in os.listdir(tmp_path) if ".part" in p] == []


def test_ctrl_c_while_writing_hdf5_leaves_the_old_file(tmp_path):
    """SIGINT at the moment the temporary file appears: exit 130, one line, old file intact, no temp left."""
    db = tmp_path / "db.h5"
    db.write_bytes(b"the previous database")
    interrupted = 0
    for attempt in range(3):
        proc = subprocess.Popen(_startrack("build-kvector", "--fov-deg", "20", "--mag-max", "6.5", "-o", db, "-q"),
                                stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 300
        while proc.poll() is None and time.monotonic() < deadline:
            if any(n.startswith(".db.h5.st") for n in os.listdir(tmp_path)):
                proc.send_signal(signal.SIGINT)
                break
            time.sleep(0.002)
        _, err = proc.communicate(timeout=300)
        assert "Traceback" not in err and "Exception ignored" not in err, err
        assert [n for n in os.listdir(tmp_path) if ".part" in n] == []
        if proc.returncode == 130:
            interrupted += 1
            assert len(err.strip().splitlines()) == 1 and "interrupted" in err
            assert db.read_bytes() == b"the previous database"
            break
        assert proc.returncode == 0  # finished before the signal: then the new file is complete
        db.write_bytes(b"the previous database")
    assert interrupted == 1


@pytest.fixture(scope="module")
def sky(tmp_path_factory):
    d = tmp_path_factory.mktemp("sky")
    run_cli("render", "--fov-deg", "20", "--size", "320x240", "--count", "3", "--mag-limit", "6", "--seed", "5",
            "-o", d / "sky.png", "-q", check=True)
    return sorted(str(p) for p in d.iterdir())


def test_outputs_onto_devices_fifos_and_links(sky, tmp_path):
    full = run_cli("centroid", sky[0], "-o", "/dev/full")
    assert_refused(full, "/dev/full", "No space left on device")
    assert not os.path.isfile("/dev/full")
    null_was_device = not os.path.isfile("/dev/null")  # (another program running as root may have replaced it)
    assert run_cli("centroid", sky[0], "-o", "/dev/null").returncode == 0
    assert null_was_device == (not os.path.isfile("/dev/null"))
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    got = []
    reader = threading.Thread(target=lambda: got.append(open(fifo).read()))  # noqa: SIM115
    reader.start()
    assert run_cli("centroid", *sky, "-o", fifo, "-q").returncode == 0
    reader.join(60)
    assert len(got[0].splitlines()) == 3 and not fifo.is_file()
    target = tmp_path / "real.jsonl"
    target.write_text("old\n")
    link = tmp_path / "link.jsonl"
    link.symlink_to(target)
    assert run_cli("centroid", *sky, "-o", link, "-q").returncode == 0
    assert link.is_symlink() and len(target.read_text().splitlines()) == 3


def test_closed_and_broken_pipes(sky):
    closed_in = subprocess.run(["bash", "-c", " ".join(_startrack("attitude")) + " <&-"], capture_output=True,
                               text=True, check=False)
    assert_refused(closed_in, "<stdin>", "closed")
    closed_out = subprocess.run(["bash", "-c", " ".join(_startrack("centroid", sky[0])) + " >&-"],
                                capture_output=True, text=True, check=False)
    assert closed_out.returncode == 2 and "closed" in closed_out.stderr and "Traceback" not in closed_out.stderr
    assert len(closed_out.stderr.strip().splitlines()) == 1
    head = subprocess.run(["bash", "-o", "pipefail", "-c", " ".join(_startrack(
        "render", "--stars-only", "--fov-deg", "20", "--count", "3000", "--seed", "1", "-q")) + " | head -1"],
        capture_output=True, text=True, check=False)
    assert head.returncode == 0 and len(head.stdout.splitlines()) == 1 and head.stderr == ""


def test_undecodable_image_is_a_failed_frame_of_the_batch(sky, tmp_path):
    bomb = bomb_png(tmp_path / "bomb.png")
    proc = run_cli("centroid", sky[0], bomb, sky[1])
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    docs = [json.loads(l) for l in proc.stdout.splitlines()]
    assert [len(docs[0]["stars"]) > 0, docs[1]["centroid"]["status"], len(docs[2]["stars"]) > 0] == [
        True, "failed", True]
    assert "60000x60000" in docs[1]["centroid"]["reason"] and "2 ok, 0 failed, 1 bad input" in proc.stderr
    assert_refused(run_cli("centroid", bomb), "bomb.png", "60000x60000", "STARTRACK_MAX_IMAGE_PIXELS")
    # The limit is configurable.
    small = run_cli("centroid", sky[0], env={"STARTRACK_MAX_IMAGE_PIXELS": "1000"})
    assert_refused(small, "320x240", "limit of 1000")


def test_eight_bit_colour_is_eight_bit(tmp_path):
    import cv2

    img = np.full((64, 80, 3), 20, np.uint8)
    img[30:33, 40:43] = 255
    cv2.imwrite(str(tmp_path / "colour.png"), img)
    doc = json.loads(run_cli("centroid", tmp_path / "colour.png", check=True).stdout)
    assert doc["image"]["bit_depth"] == 8
    assert doc["stars"] and doc["stars"][0]["saturated"] is True  # 255 of 255: saturated


def test_paths_resolve_against_their_document(sky, tmp_path):
    """A document in batch/ naming 'sky-0000.png' finds batch/sky-0000.png, from any directory."""
    batch = tmp_path / "batch"
    batch.mkdir()
    names = []
    for p in sky:
        os.symlink(p, batch / os.path.basename(p))
        names.append(os.path.basename(p))
    (batch / "render.jsonl").write_text("".join(json.dumps(
        {"format": "startrack.frame/1", "image": {"path": n}}) + "\n" for n in names))
    proc = subprocess.run(_startrack("centroid", "batch/render.jsonl", "-q"), cwd=tmp_path, capture_output=True,
                          text=True, check=False)
    assert proc.returncode == 0, proc.stderr
    docs = [json.loads(l) for l in proc.stdout.splitlines()]
    assert [os.path.basename(d["image"]["path"]) for d in docs] == names and all(d["stars"] for d in docs)


def test_corrupt_cached_database_is_rebuilt_and_builds_are_locked(tmp_path, caplog):
    from startrack.catalog import load_catalog
    from startrack.formats.hdf5 import cached_database
    from startrack.kvector import build_kvector, load_kvector, save_kvector

    cat = load_catalog().filter_magnitude(None, 4.0)
    path = str(tmp_path / "cached.h5")
    built = []

    def build():
        built.append(1)
        return build_kvector(cat, 20.0)

    first = cached_database(path, load_kvector, save_kvector, build)
    assert len(built) == 1 and cached_database(path, load_kvector, save_kvector, build) is not None
    assert len(built) == 1  # loaded, not rebuilt
    size = os.path.getsize(path)
    with open(path, "r+b") as fh:  # 4 KB of garbage in the middle of the data
        fh.seek(size // 2)
        fh.write(os.urandom(4096))
    with caplog.at_level("WARNING", logger="startrack"):
        again = cached_database(path, load_kvector, save_kvector, build)
    assert len(built) == 2 and "rebuilding" in caplog.text and path in caplog.text
    assert np.array_equal(again.kvector, first.kvector)
    # Two processes needing the same missing file: one builds, the other waits and loads it.
    os.remove(path)
    code = ("import sys, time\n"
            "from startrack.catalog import load_catalog\n"
            "from startrack.formats.hdf5 import cached_database\n"
            "from startrack.kvector import build_kvector, load_kvector, save_kvector\n"
            "cat = load_catalog().filter_magnitude(None, 4.0)\n"
            "def build():\n"
            f"    open({str(tmp_path / 'builds.txt')!r}, 'a').write('x')\n"
            "    time.sleep(2)\n"
            "    return build_kvector(cat, 20.0)\n"
            f"cached_database({path!r}, load_kvector, save_kvector, build)\n")
    procs = [subprocess.Popen([sys.executable, "-c", code]) for _ in range(2)]
    assert [p.wait(300) for p in procs] == [0, 0]
    assert (tmp_path / "builds.txt").read_text() == "x"


def test_plot_and_picture_names(tmp_path):
    doc = {"format": "startrack.frame/1", "stars": [], "attitude": {"status": "failed", "reason": "x"}}
    (tmp_path / "f.json").write_text(json.dumps(doc))
    proc = run_cli("plot", tmp_path / "f.json", "--kind", "residuals", "-o", tmp_path / "res.png")
    assert proc.returncode == 1 and "no picture written" in proc.stderr and not (tmp_path / "res.png").exists()
    assert_refused(run_cli("solve", tmp_path / "x.png", "--plot", tmp_path / "x.txt"), "x.txt", "extension")
