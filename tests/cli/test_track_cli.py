"""track through the real entry point."""
import json

from conftest import run_cli


def test_render_then_track(tmp_path):
    seq = tmp_path / "seq" / "frame.png"
    frames = run_cli("render", "--fov-deg", "12", "--size", "1024x768", "--frames", "12", "--rate-deg-s", "0.3,0.4,0",
                     "--frame-interval-s", "0.1", "--time", "2026-11-21T22:00:00Z", "--blackout", "5:2",
                     "--seed", "4", "-o", seq, check=True).stdout
    db = tmp_path / "db.h5"
    run_cli("build-kvector", "--fov-deg", "12", "--size", "1024x768", "--mag-max", "6.0", "-o", db, check=True)
    proc = run_cli("track", "-d", db, input=frames, check=True)
    docs = [json.loads(l) for l in proc.stdout.splitlines()]
    modes = [d["track"]["mode"] for d in docs]
    assert modes[0] == "lis" and modes[1:5] == ["track"] * 4 and modes[5:7] == ["lost", "lost"]
    assert modes[-3:] == ["track"] * 3
    assert all(d["attitude"]["status"] == "ok" for i, d in enumerate(docs) if i not in (5, 6))
    assert docs[3]["track"]["t_s"] == 0.3


def test_out_of_order_time_stamps_refused(tmp_path):
    seq = tmp_path / "seq" / "frame.png"
    frames = run_cli("render", "--fov-deg", "12", "--size", "1024x768", "--frames", "3", "--frame-interval-s", "0.1",
                     "--time", "2026-11-21T22:00:00Z", "--seed", "4", "-o", seq, check=True).stdout.splitlines()
    db = tmp_path / "db.h5"
    run_cli("build-kvector", "--fov-deg", "12", "--size", "1024x768", "--mag-max", "6.0", "-o", db, check=True)
    stream = "\n".join([frames[0], frames[2], frames[1]]) + "\n"
    proc = run_cli("track", "-d", db, input=stream)
    assert proc.returncode == 2 and "out-of-order" in proc.stderr and "Traceback" not in proc.stderr
    docs = [json.loads(l) for l in proc.stdout.splitlines()]
    assert len(docs) == 3 and docs[2]["track"]["status"] == "failed"
