"""track through the real entry point."""
import json

from conftest import assert_refused, run_cli


def test_render_then_track(tmp_path):
    seq = tmp_path / "seq" / "frame.png"
    frames = run_cli("render", "--fov-deg", "12", "--size", "1024x768", "--frames", "12", "--rate-deg-s", "0.3,0.4,0",
                     "--frame-interval-s", "0.1", "--blackout", "5:2", "--seed", "4", "-o", seq, check=True).stdout
    db = tmp_path / "db.h5"
    run_cli("build-kvector", "--fov-deg", "12", "--size", "1024x768", "--mag-max", "6.0", "-o", db, check=True)
    # No option but the database: the frames carry their time and exposure.
    proc = run_cli("track", "-d", db, input=frames)
    # A frame without image.time: --frame-interval-s fills the gap (one interval after the previous frame).
    lines = frames.splitlines()
    gap = json.loads(lines[8])
    del gap["image"]["time"]
    gapped = "\n".join(lines[:8] + [json.dumps(gap)] + lines[9:]) + "\n"
    assert_refused(run_cli("track", "-d", db, input=json.dumps(gap) + "\n"), "image.time")
    filled = [json.loads(l) for l in run_cli("track", "-d", db, "--frame-interval-s", "0.1", "-q",
                                             input=gapped).stdout.splitlines()]
    assert [round(d["track"]["t_s"], 6) for d in filled[7:10]] == [0.7, 0.8, 0.9]
    assert proc.returncode == 1, proc.stderr        # two blacked-out frames have no attitude
    assert "10 of 12 frame(s) with an attitude" in proc.stderr and "2 lost" in proc.stderr
    docs = [json.loads(l) for l in proc.stdout.splitlines()]
    modes = [d["track"]["mode"] for d in docs]
    assert modes[0] == "lost-in-space" and modes[1:5] == ["tracking"] * 4 and modes[5:7] == ["lost", "lost"]
    assert modes[-3:] == ["tracking"] * 3
    assert all(d["attitude"]["status"] == "ok" for i, d in enumerate(docs) if i not in (5, 6))
    assert abs(docs[3]["track"]["t_s"] - 0.3) < 1e-9
    # Failed frames keep their truth and render sections.
    assert docs[5]["attitude"]["status"] == "failed" and docs[5]["truth"]["blackout"] and "render" in docs[5]
    # plot --kind track draws the errors; refuses a stream without any attitude.
    out = tmp_path / "track.png"
    run_cli("plot", "--kind", "track", "-o", out, input=proc.stdout, check=True)
    assert out.stat().st_size > 1000
    dark = "\n".join(l for i, l in enumerate(proc.stdout.splitlines()) if i in (5, 6)) + "\n"
    assert_refused(run_cli("plot", "--kind", "track", "-o", tmp_path / "x.png", input=dark), "attitude")


def test_render_writes_time_and_exposure(tmp_path):
    docs = [json.loads(l) for l in run_cli("render", "--fov-deg", "12", "--size", "320x240", "--frames", "3",
                                           "--frame-interval-s", "0.25", "--exposure-ms", "40", "--seed", "1",
                                           "-o", tmp_path / "s" / "f.png", check=True).stdout.splitlines()]
    times = [d["image"]["time"] for d in docs]
    from startrack.timeutil import parse_time

    t = [parse_time(x) for x in times]
    assert [(b - t[0]).total_seconds() for b in t] == [0.0, 0.25, 0.5]
    assert times[0].startswith("1991-04-02")          # no --time: the catalog's epoch (J1991.25)
    assert all(d["image"]["exposure_ms"] == 40 for d in docs)


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
    assert len(docs) == 3 and docs[2]["attitude"]["status"] == "failed" and "truth" in docs[2]
