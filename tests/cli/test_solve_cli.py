"""solve, calibrate and plot through the real entry point, on the real images and on non-star images."""
import csv
import glob
import json
import math
import os
import time

import numpy as np
import pytest
from conftest import CHART_COLOURS, DATA, assert_chart_draws, assert_identified_star_marked, run_cli

REAL = sorted(glob.glob(os.path.join(DATA, "real", "*.tiff")))


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    env = {"STARTRACK_CACHE": str(tmp_path_factory.mktemp("cache"))}
    proc = run_cli("cache", "build", env=env, check=True, timeout=600)
    # The one-line notice is printed even though stderr is not a terminal here.
    assert "building the star index once" in proc.stderr
    listing = run_cli("cache", "list", env=env, check=True).stdout
    assert "patterns-" in listing
    return env


@pytest.fixture(scope="module")
def solved(cache, tmp_path_factory):
    out = tmp_path_factory.mktemp("solved")
    proc = run_cli("solve", *REAL, "-j", "2", "--wcs", out / "sky.wcs.fits", env=cache, check=True, timeout=600)
    return [json.loads(l) for l in proc.stdout.splitlines()], out


def test_blind_solve_of_the_real_images(solved):
    docs, out = solved
    ref = {r["file"]: r for r in csv.DictReader(open(os.path.join(DATA, "real", "solutions.csv")))}
    assert len(docs) == 8
    for d in docs:
        assert d["solve"]["status"] == "ok", d["solve"]
        a = d["attitude"]
        r = ref[os.path.basename(d["image"]["path"])]
        sep = math.hypot((a["ra"] - float(r["ra_deg"])) * math.cos(math.radians(a["dec"])), a["dec"] - float(r["dec_deg"]))
        assert sep * 3600 < 30
        assert d["solve"]["fov_deg"][0] == pytest.approx(float(r["fov_x_deg"]), abs=0.05)
    assert len(list(out.glob("sky.wcs-*.fits"))) == 8


def test_calibrate_then_solve_with_the_lens(solved, cache, tmp_path):
    docs, _ = solved
    frames = tmp_path / "solved.jsonl"
    frames.write_text("\n".join(json.dumps(d) for d in docs) + "\n")
    lens = tmp_path / "lens.json"
    proc = run_cli("calibrate", frames, "-o", lens, env=cache, check=True)
    assert "residual RMS" in proc.stderr
    cal = json.load(open(lens))
    c = cal["calibration"]
    assert c["rms_residual_after_px"] < c["rms_residual_before_px"]
    assert cal["fov_deg"][0] == pytest.approx(11.42, abs=0.02)
    assert all(v > 0 for v in c["sigma"].values())
    # Only what the data constrain is fitted: every fitted optional parameter is significant, and
    # each left out is reported with its significance (k2 is not constrained by 8 frames of 11 deg).
    z = c["significance_sigma"]
    assert all(z[k] >= 3.0 for k in ("k1", "k2") if k in z), z
    if "cx" in z:       # the principal point is kept or left out as a pair
        assert max(z["cx"], z["cy"]) >= 3.0, z
    assert "k2" in c["not_fitted"] and "k2" not in c["sigma"]
    assert "not fitted" in proc.stderr
    again = [json.loads(l) for l in run_cli("solve", *REAL[:3], "--camera", lens, env=cache, check=True).stdout.splitlines()]
    assert all(d["solve"]["status"] == "ok" for d in again)
    # The image centre and the principal point are both reported; with a calibrated lens they differ.
    for d in again:
        s = d["solve"]
        r = {row["file"]: row for row in csv.DictReader(open(os.path.join(DATA, "real", "solutions.csv")))}[
            os.path.basename(d["image"]["path"])]
        sep = math.hypot((s["center_ra"] - float(r["ra_deg"])) * math.cos(math.radians(s["center_dec"])),
                         s["center_dec"] - float(r["dec_deg"]))
        assert sep * 3600 < 30
        assert "ra" in s["principal_point"] and "dec" in s["principal_point"]


def test_exit_status_and_cache_command(cache, tmp_path):
    """0 all solved, 1 one failed, 2 one unreadable; `cache list` and `cache clear` on a scratch cache."""
    import cv2

    black = tmp_path / "black.png"
    cv2.imwrite(str(black), np.zeros((120, 160), np.uint8))
    assert run_cli("solve", REAL[0], "-q", env=cache).returncode == 0
    failed = run_cli("solve", REAL[0], black, "-q", env=cache)
    assert failed.returncode == 1 and "black.png" in failed.stderr      # -q hides progress, never failures
    missing = run_cli("solve", REAL[0], tmp_path / "missing.png", "-q", env=cache)
    assert missing.returncode == 2 and "missing.png" in missing.stderr
    scratch = {"STARTRACK_CACHE": str(tmp_path / "scratch")}
    (tmp_path / "scratch").mkdir()
    (tmp_path / "scratch" / "patterns-old.idx").write_bytes(b"x" * 1000)
    assert "patterns-old.idx" in run_cli("cache", "list", env=scratch, check=True).stdout
    run_cli("cache", "clear", env=scratch, check=True)
    assert not list((tmp_path / "scratch").iterdir())


def test_not_star_fields_fail_fast_and_cleanly(cache, tmp_path):
    import cv2

    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:480, 0:640]
    daylight = (120 + 60 * np.sin(xx / 23.0) * np.cos(yy / 17.0) + rng.normal(0, 8, (480, 640))).clip(0, 255)
    cv2.imwrite(str(tmp_path / "daylight.png"), daylight.astype(np.uint8))
    cv2.imwrite(str(tmp_path / "black.png"), np.zeros((480, 640), np.uint8))
    cv2.imwrite(str(tmp_path / "noise.png"), rng.normal(1000, 40, (480, 640)).astype(np.uint16))
    t0 = time.time()
    # The Hipparcos index's search: with the extra startrack[gaia], a frame it fails is searched again with the Gaia
    # index (fields under 3 deg), which the first such frame builds (a one-time ~30 s, README "Narrow fields").
    proc = run_cli("solve", tmp_path / "daylight.png", tmp_path / "black.png", tmp_path / "noise.png",
                   "--catalog", "hipparcos", env=cache)
    elapsed = time.time() - t0
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "3 image(s), 0 ok, 3 failed, 0 bad input" in proc.stderr
    docs = [json.loads(l) for l in proc.stdout.splitlines()]
    assert [d["solve"]["status"] for d in docs] == ["failed"] * 3
    assert all(d["solve"]["reason"] and "attitude" not in d for d in docs)
    assert all(d["solve"]["time_ms"] < 5000 for d in docs)
    assert elapsed < 30


def test_plot_kinds(solved, tmp_path):
    docs, _ = solved
    one = tmp_path / "one.jsonl"
    one.write_text(json.dumps(docs[2]) + "\n")
    run_cli("plot", one, "--kind", "image", "-o", tmp_path / "img.png", check=True)
    run_cli("plot", one, "--kind", "residuals", "-o", tmp_path / "res.png", check=True)
    assert_identified_star_marked(tmp_path / "img.png", docs[2])
    assert_chart_draws(tmp_path / "res.png", CHART_COLOURS[:1])       # the residual arrows


@pytest.mark.parametrize("fov,size,k1", [(5.0, "800x600", 0.0), (40.0, "1024x768", -0.05)])
def test_rendered_fields_solve_blind_with_named_outputs(cache, tmp_path, fov, size, k1):
    """A 5 deg and a 40 deg field with barrel distortion, no hint; outputs named after the image."""
    img = tmp_path / "field.png"
    truth = json.loads(run_cli("render", "--fov-deg", fov, "--size", size, "--ra", 150, "--dec", 40, "--roll", 30,
                               "--k1", k1, "--exposure-ms", 300, "--seed", 3, "-o", img, "-q", check=True).stdout)
    out = tmp_path / "out"
    proc = run_cli("solve", img, "--fits-out", f"{out}/", "--matches-out", f"{out}/", env=cache, check=True)
    d = json.loads(proc.stdout)
    assert d["solve"]["status"] == "ok", d["solve"]
    c = {"ra": d["solve"]["center_ra"], "dec": d["solve"]["center_dec"]}
    sep = math.degrees(math.acos(min(1.0, math.sin(math.radians(c["dec"])) * math.sin(math.radians(40))
                                     + math.cos(math.radians(c["dec"])) * math.cos(math.radians(40))
                                     * math.cos(math.radians(c["ra"] - 150)))))
    assert sep * 3600 < 60
    assert d["camera"]["fov_deg"][0] == pytest.approx(truth["camera"]["fov_deg"][0], rel=0.005)
    if k1:
        assert d["camera"]["distortion"]["k1"] == pytest.approx(k1, abs=0.01)
    from astropy.io import fits
    from astropy.wcs import WCS

    with fits.open(out / "field.new.fits") as hdul:
        assert hdul[0].data.shape == tuple(int(v) for v in size.split("x")[::-1])
        ra, dec = WCS(hdul[0].header).all_pix2world([d["stars"][0]["x"]], [d["stars"][0]["y"]], 0)
    rows = list(csv.DictReader(open(out / "field.matches.csv")))
    assert len(rows) == len(d["identification"]["matches"]) >= 10
    first = next(r for r in rows if float(r["x_px"]) == pytest.approx(d["stars"][0]["x"], abs=1e-3))
    assert float(first["ra_deg"]) == pytest.approx(float(ra[0]), abs=0.02)
    assert float(first["dec_deg"]) == pytest.approx(float(dec[0]), abs=0.02)


def test_solve_pool_writes_what_one_process_writes(cache, tmp_path, monkeypatch):
    """`-j 2` with its pool (forced here: the suite's machine is rarely idle): workers serialise their documents
    and this process writes their lines in input order; the file equals `-j 1`'s but for the times, relative
    image paths included (the output in another directory than the images)."""
    from click.testing import CliRunner

    from startrack import cluster
    from startrack.cli.main import cli
    from startrack.formats.frame import FrameWriter

    monkeypatch.setenv("STARTRACK_CACHE", cache["STARTRACK_CACHE"])
    monkeypatch.setattr(cluster, "idle_cpus", lambda: 2)
    monkeypatch.setattr(cluster, "worker_startup_s", lambda _spawn_s: 0.0)    # four images: workers pay off
    written = []        # the documents this process serialised itself
    write = FrameWriter.write
    monkeypatch.setattr(FrameWriter, "write", lambda self, doc: (written.append(doc), write(self, doc)))
    monkeypatch.chdir(tmp_path)
    images = [os.path.relpath(p, tmp_path) for p in REAL[:6]]
    (tmp_path / "out").mkdir()
    docs = {}
    for jobs in ("1", "2"):
        written.clear()
        result = CliRunner().invoke(cli, ["solve", *images, "-j", jobs, "-q", "--no-aberration", "-o",
                                          f"out/j{jobs}.jsonl"])
        assert result.exit_code == 0, result.output
        docs[jobs] = [json.loads(line) for line in (tmp_path / "out" / f"j{jobs}.jsonl").read_text().splitlines()]
        # -j 2: the first two images are solved here (first uses, then one timed); the workers wrote the rest
        assert len(written) == (len(images) if jobs == "1" else 2)

    def untimed(value):
        if isinstance(value, dict):
            return {k: untimed(v) for k, v in value.items() if k != "time_ms"}
        return [untimed(v) for v in value] if isinstance(value, list) else value

    assert [untimed(d) for d in docs["2"]] == [untimed(d) for d in docs["1"]]
    assert [d["image"]["path"] for d in docs["2"]] == [os.path.join("..", p) for p in images]
