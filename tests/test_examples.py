"""The examples really run: the Makefile workflow and the shell pipeline, on small sizes."""
import json
import os
import subprocess
import sys

from conftest import CHART_COLOURS, ROOT, assert_chart_draws, assert_identified_star_marked


def _env():
    env = dict(os.environ)
    env["ST"] = os.path.join(os.path.dirname(sys.executable), "startrack")
    return env


def test_makefile_workflow(tmp_path):
    out = tmp_path / "out"
    proc = subprocess.run(["make", "-C", os.path.join(ROOT, "examples"), "N=6", f"OUT={out}",
                           f"ST={_env()['ST']}"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    docs = [json.loads(l) for l in (out / "solved.jsonl").read_text().splitlines()]
    assert len(docs) == 6 and sum(d["attitude"]["status"] == "ok" for d in docs) >= 5
    rows = json.load(open(out / "evaluate.json"))["rows"]
    assert len(rows) == 9
    assert_chart_draws(out / "evaluate.png", CHART_COLOURS)        # pyramid, voting, brightness
    assert_chart_draws(out / "errors.png", [(189, 103, 148)])        # solved frames (no track mode): tab:purple
    assert_identified_star_marked(out / "first-frame.png", docs[0])


def test_shell_pipeline(tmp_path):
    proc = subprocess.run(["bash", os.path.join(ROOT, "examples", "pipeline.sh"), str(tmp_path)], capture_output=True,
                          text=True, env=_env(), timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.startswith("RA 286.4")
    doc = json.load(open(tmp_path / "sky.json"))
    assert doc["attitude"]["status"] == "ok" and doc["identification"]["status"] == "ok"
    assert_identified_star_marked(tmp_path / "sky-solved.png", doc)
    assert (tmp_path / "sky.wcs.fits").exists()


def test_pictures_script_draws_one_picture_of_each_kind(tmp_path):
    """examples/pictures.sh, the documented way the committed pictures are made, runs; each picture is a PNG under
    300 KB, and so is each committed one."""
    import cv2

    proc = subprocess.run(["bash", os.path.join(ROOT, "examples", "pictures.sh"), str(tmp_path)], capture_output=True,
                          text=True, env=_env(), timeout=1200)
    assert proc.returncode == 0, proc.stderr[-2000:]
    kinds = ["sky-solved.png", "picture-centroid.png", "picture-identify.png", "picture-residuals.png",
             "picture-track.png", "picture-evaluate.png", "picture-constellations.png", "orion.png",
             "compare-false-stars.png", "robustness-focal-error.png"]
    for name in kinds:
        for path in (tmp_path / name, os.path.join(ROOT, "examples", name)):
            assert os.path.getsize(path) < 300_000, (path, os.path.getsize(path))
            img = cv2.imread(str(path))
            assert img is not None and img.shape[0] > 300 and img.shape[1] > 600, path
    doc = json.loads(subprocess.run([_env()["ST"], "solve", os.path.join(ROOT, "examples", "data", "sky.tiff"), "-q"],
                                    capture_output=True, text=True, env=_env(), timeout=600, check=True).stdout)
    assert_identified_star_marked(tmp_path / "sky-solved.png", doc)


def test_paper001_single_star_example(tmp_path):
    """examples/paper001_single_star.sh: the frames with one star found in the windows run paper 001's single-star
    mode (Case 2) and keep an attitude near the truth; the frames around them track with every star."""
    env = dict(_env(), PY=sys.executable, WORK=str(tmp_path / "work"))
    proc = subprocess.run(["bash", os.path.join(ROOT, "examples", "paper001_single_star.sh"), "4", str(tmp_path)],
                          capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    doc = json.load(open(tmp_path / "track-single-star.json"))
    rows = doc["rows"]
    assert len(rows) == 12 and doc["one_star_frames"] == doc["single_star_frames"] == [4, 5, 6, 7]
    assert "single-star" in proc.stdout.splitlines()[5]
    for r in rows:
        assert r["cross_arcsec"] is not None and r["cross_arcsec"] < 20, r       # 12 deg field: 42"/px
        if r["frame"] in (4, 5, 6, 7):
            assert r["found"] == 1 and r["empirical_stars"] >= 1 and r["exposure_ms"] == 0.2
        elif r["frame"] > 0:
            assert r["mode"] == "tracking" and r["found"] > 10
    assert doc["modes"]["single-star"] == 4 / 12
    assert (tmp_path / "track-single-star.png").stat().st_size > 10_000
