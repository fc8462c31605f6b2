"""Issue 40 items 3, 4 and 7 through the real entry point: image.path relative to the document, pictures in
PDF/SVG, plot --kind track quiet on stdout, evaluate's JSON in the CLI's words, render --preview and
solve --retry-failed."""
import json
import os
import shutil

import numpy as np
import pytest

from tests.conftest import DATA, assert_refused, run_cli

SKY = os.path.abspath(os.path.join(DATA, "..", "..", "examples", "data", "sky.tiff"))


@pytest.fixture(scope="module")
def db20(tmp_path_factory):
    path = tmp_path_factory.mktemp("evalplot-db") / "db.h5"
    run_cli("build-kvector", "--fov-deg", "20", "--size", "640x640", "--mag-max", "5", "-o", path, "-q", check=True)
    return path


def _image_paths(path):
    return [json.loads(line)["image"]["path"] for line in open(path) if line.strip()]


def test_image_path_is_relative_to_the_documents_directory(db20, tmp_path, monkeypatch):
    """main: every writer kept image.path relative to where it ran, so a document written with -o /elsewhere/o.jsonl
    named a file that /elsewhere does not have, and `plot` run there failed.  Now render --documents, centroid,
    identify and attitude -o write it relative to the document's directory, and plot works from there."""
    work, elsewhere = tmp_path / "work", tmp_path / "elsewhere" / "deeper"
    work.mkdir()
    elsewhere.mkdir(parents=True)
    monkeypatch.chdir(work)
    run_cli("render", "--fov-deg", "20", "--size", "640x640", "--ra", "83.8", "--dec", "-1.2", "--seed", "1",
            "--mag-max", "5", "-o", "img.png", "--documents", elsewhere / "r.jsonl", "-q", check=True)
    run_cli("centroid", elsewhere / "r.jsonl", "-o", elsewhere / "c.jsonl", "-q", check=True)
    run_cli("identify", elsewhere / "c.jsonl", "-d", db20, "-o", elsewhere / "i.jsonl", "-q", check=True)
    run_cli("attitude", elsewhere / "i.jsonl", "-o", elsewhere / "a.jsonl", "-q", check=True)
    for name in ("r", "c", "i", "a"):
        (p,) = _image_paths(elsewhere / f"{name}.jsonl")
        assert p == os.path.join("..", "..", "work", "img.png"), (name, p)
    # standard output has no directory of its own: the path names the image from where the command ran
    out = run_cli("centroid", elsewhere / "r.jsonl", "-q", check=True).stdout
    assert os.path.samefile(json.loads(out)["image"]["path"], work / "img.png")
    monkeypatch.chdir(elsewhere)
    proc = run_cli("plot", "a.jsonl", "-o", "p.png", "-q")
    assert proc.returncode == 0, proc.stderr
    assert (elsewhere / "p.png").stat().st_size > 10_000
    # and from a third directory, through the document's own path
    monkeypatch.chdir(tmp_path)
    run_cli("plot", elsewhere / "a.jsonl", "-o", "q.svg", "-q", check=True)
    assert "<svg" in (tmp_path / "q.svg").read_text()[:500]


def _track_docs():
    from startrack.camera import Camera
    from startrack.rotations import dcm_to_quaternion, radec_roll_to_dcm

    cam = Camera.from_fov(12, 512, 384).to_dict()
    docs = []
    for k in range(4):
        q = dcm_to_quaternion(radec_roll_to_dcm(80.0 + 0.01 * k, 5.0, 0.0)).tolist()
        docs.append({"format": "startrack.frame/1", "frame": k, "camera": cam, "track": {"mode": "tracking"},
                     "attitude": {"status": "ok", "quaternion": q}, "truth": {"quaternion": q}})
    return "".join(json.dumps(d) + "\n" for d in docs)


def test_plot_track_prints_json_only_when_asked(tmp_path):
    """main: `plot --kind track` printed its statistics as JSON on stdout unasked.  Now stdout stays empty; --json
    prints them; --json with another kind is refused."""
    quiet = run_cli("plot", "--kind", "track", "-o", tmp_path / "t.png", input=_track_docs())
    assert quiet.returncode == 0, quiet.stderr
    assert quiet.stdout == "" and (tmp_path / "t.png").exists()
    asked = run_cli("plot", "--kind", "track", "-o", tmp_path / "t.pdf", "--json", "-q", input=_track_docs(),
                    check=True)
    assert json.loads(asked.stdout)["frames"] == 4
    assert (tmp_path / "t.pdf").read_bytes()[:5] == b"%PDF-"
    assert_refused(run_cli("plot", "--kind", "image", "--json", "-o", tmp_path / "x.png", input=_track_docs()),
                   "--json")
    assert_refused(run_cli("plot", "--kind", "track", "--constellations", "-o", tmp_path / "x.png",
                           input=_track_docs()), "--constellations")


def test_evaluate_json_speaks_mag_max_with_intervals_and_charts_in_any_format(db20, tmp_path):
    """main: params said mag_limit where the option is --mag-max, rows had no intervals, --plot wrote PNG bytes
    whatever the name.  Now params.mag_max, the Wilson intervals, SVG/PDF charts, and a .jpg chart refused."""
    common = ("evaluate", "-d", db20, "-a", "pyramid", "--fov-deg", "20", "--size", "640x640", "--mag-max", "4.5",
              "--false-stars", "0,2", "--count", "30", "--seed", "2")
    proc = run_cli(*common, "--json", "-o", tmp_path / "e.json", "--plot", tmp_path / "e.svg", "-q", check=True)
    assert "success 95% CI" in proc.stdout
    doc = json.load(open(tmp_path / "e.json"))
    assert doc["params"]["mag_max"] == 4.5 and "mag_limit" not in doc["params"]
    for row in doc["rows"]:
        assert row["success_rate_low"] <= row["success_rate"] <= row["success_rate_high"]
        assert row["bad_rate_low"] <= row["bad_rate"] <= row["bad_rate_high"]
    assert "<svg" in (tmp_path / "e.svg").read_text()[:500]
    assert_refused(run_cli(*common, "--plot", tmp_path / "e.jpg"), "e.jpg", ".png, .pdf or .svg")
    # a document written before the rename (mag_limit, no intervals) still plots, its title from its params
    old = {**doc, "params": {k: v for k, v in doc["params"].items() if k != "mag_max"} | {"mag_limit": 4.5},
           "rows": [{k: v for k, v in r.items() if not k.endswith(("_low", "_high")) and k != "bad_rate"}
                    for r in doc["rows"]]}
    (tmp_path / "old.json").write_text(json.dumps(old))
    run_cli("plot", tmp_path / "old.json", "--kind", "evaluate", "-o", tmp_path / "old.svg", "-q", check=True)
    svg = (tmp_path / "old.svg").read_text()
    assert "stars to Hp 4.5" in svg and "20.0 x 20.0 deg field" in svg
    run_cli("plot", tmp_path / "old.json", "--kind", "evaluate", "-o", tmp_path / "old.pdf", "-q", check=True)
    assert (tmp_path / "old.pdf").read_bytes()[:5] == b"%PDF-"


def test_render_preview_is_an_8_bit_picture_people_can_see(tmp_path):
    """main: the demo's orion.png is the sensor's 16-bit frame, black in a viewer, and nothing else is written.
    Now --preview writes an 8-bit stretched PNG beside it: dark sky, stars near white; -o keeps 16 bits."""
    import cv2

    run_cli("render", "--fov-deg", "20", "--size", "512x512", "--ra", "83.8", "--dec", "-1.2", "--seed", "1",
            "-o", tmp_path / "o.png", "--preview", tmp_path / "o-preview.png", "-q", check=True)
    raw = cv2.imread(str(tmp_path / "o.png"), cv2.IMREAD_UNCHANGED)
    shown = cv2.imread(str(tmp_path / "o-preview.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and shown.dtype == np.uint8 and shown.shape == raw.shape
    # what a viewer shows of the 16-bit file: its top byte is dark almost everywhere
    assert np.percentile(raw >> 8, 99.9) < 40
    # the preview: sky dark, the brightest stars bright
    assert np.median(shown) < 30 and np.percentile(shown, 99.99) > 200
    assert_refused(run_cli("render", "--fov-deg", "20", "--size", "64x64", "-o", tmp_path / "a.png", "--preview",
                           tmp_path / "a.jpg"), "a.jpg", "8-bit PNG")
    # the preview is an output: written again over the last one, never taken for an input
    run_cli("render", "--fov-deg", "20", "--size", "64x64", "-o", tmp_path / "a.png", "--preview",
            tmp_path / "o-preview.png", "-q", check=True)
    assert cv2.imread(str(tmp_path / "o-preview.png"), cv2.IMREAD_UNCHANGED).shape == (64, 64)


def test_solve_retry_failed_solves_the_failed_images_again(solve_cache, tmp_path, monkeypatch):
    """main: `solve --resume` counted an image whose document failed as done and had no way to retry it.  Now
    --retry-failed solves it again, its new document replacing the failed one; the good one is not redone."""
    monkeypatch.chdir(tmp_path)
    shutil.copy(SKY, "a.tiff")
    (tmp_path / "b.tiff").write_text("not an image")
    env = {"STARTRACK_CACHE": str(solve_cache)}
    args = ("solve", "a.tiff", "b.tiff", "-o", "out.jsonl", "--fov-deg", "11.4", "--no-aberration")
    first = run_cli(*args, "-q", env=env)
    assert first.returncode == 2, first.stderr
    before = [json.loads(line) for line in open("out.jsonl")]
    assert [d["solve"]["status"] for d in before] == ["ok", "failed"]
    shutil.copy(SKY, "b.tiff")
    again = run_cli(*args, "--resume", env=env)
    assert again.returncode == 0 and "2 already in the output" in again.stderr        # what --resume alone does
    proc = run_cli(*args, "--resume", "--retry-failed", env=env)
    assert proc.returncode == 0, proc.stderr
    assert "1 failed image(s) solved again" in proc.stderr and "1 already in the output" in proc.stderr
    after = [json.loads(line) for line in open("out.jsonl")]
    assert [(d["image"]["path"], d["solve"]["status"]) for d in after] == [("a.tiff", "ok"), ("b.tiff", "ok")]
    assert after[0] == before[0]                                   # the good document untouched, not redone
    assert not [f for f in os.listdir(".") if f.startswith(".out.jsonl")]          # no temporary left
    assert_refused(run_cli(*args, "--retry-failed", env=env), "--retry-failed", "--resume")
