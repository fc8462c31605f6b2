"""Paper 003's Eq. 9 calibration carried frame to frame by `startrack identify` over a JSON Lines stream."""
import json

import pytest
from conftest import run_cli


def _k_in(text):
    k, in_k = (float(v) for v in text.split(":"))
    return k, in_k


@pytest.fixture(scope="module")
def stream(tmp_path_factory):
    """Paper 003's sensor: 20 x 20 deg, catalog to 5.0, 0.2 mag noise (so each frame's In_k differs), with a frame
    no database matches (its stars scattered) in the middle."""
    d = tmp_path_factory.mktemp("carry")
    db = d / "db.h5"
    run_cli("build-kvector", "--fov-deg", 20, "--size", "1024x1024", "--mag-max", 5.0, "-o", db, "-q", check=True)
    out = run_cli("render", "--stars-only", "--count", 7, "--fov-deg", 20, "--size", "1024x1024", "--mag-max", 5,
                  "--sigma-arcsec", 1.67, "--mag-noise", 0.2, "--max-stars", 10, "--seed", 11, "-q", check=True).stdout
    docs = [json.loads(line) for line in out.splitlines()]
    bad = docs[3]
    for i, s in enumerate(bad["stars"]):           # the same fluxes at positions of no real sky
        s["x"], s["y"] = 37.0 + 97.3 * i, 900.0 - 83.1 * i * (i % 3)
    bad.pop("truth", None)
    path = d / "set.jsonl"
    path.write_text("".join(json.dumps(doc) + "\n" for doc in docs))
    return db, path


def _identify(db, path, *extra):
    proc = run_cli("identify", "-d", db, "-a", "brightness", "-q", *extra, input=path.read_text())
    return [json.loads(line)["identification"] for line in proc.stdout.splitlines()], proc


def test_identified_frames_calibrate_the_next(stream):
    db, path = stream
    given = "3:13500"
    ids, proc = _identify(db, path, "--brightness-calibration", given, "--calibration-frames", 3)
    assert proc.returncode == 1                    # the scattered frame fails
    assert [i["status"] for i in ids] == ["ok", "ok", "ok", "failed", "ok", "ok", "ok"]
    assert ids[0]["calibration_source"] == "given" and ids[0]["calibration_used"] == given
    measured = {}                                   # frame -> its own (per-frame) In_k, restated at k = 3
    differs = 0
    for n, ident in enumerate(ids):
        if n > 0:
            # The oracle: the mean of the last (up to 3) identified frames' own measurements, computed here.
            last = sorted(measured)[-3:]
            k = 3.0
            expect = sum(measured[f] for f in last) / len(last)
            assert ident["calibration_source"] == "carried"
            assert ident["calibration_from_frame"] == last[-1] and ident["calibration_frames"] == len(last)
            k_used, in_used = _k_in(ident["calibration_used"])
            assert k_used == k and in_used == pytest.approx(expect, rel=1e-5)
        if ident["status"] == "ok":
            k, in_k = _k_in(ident["calibration"])
            measured[n] = in_k * 2.512 ** (k - 3.0)
            differs += abs(_k_in(ident["calibration_used"])[1] / measured[n] - 1) > 0.05
    assert ids[4]["calibration_from_frame"] == 2    # the failed frame 3 calibrates nothing
    assert differs >= 2                             # the carried In_k is not the frame's own estimate


def test_the_carried_calibration_is_the_one_searched_with(stream, tmp_path):
    """Frame 2 alone, given the calibration the stream carried to it, is searched the same way (mode, scope)."""
    db, path = stream
    ids, _ = _identify(db, path, "--calibration-frames", 10)
    assert ids[0]["calibration_source"] == "none" and ids[0]["calibration_used"] is None
    assert ids[0]["mode"] == "four-star"           # nothing to calibrate with yet: the four-star mode only
    frame2 = tmp_path / "f2.jsonl"
    frame2.write_text(path.read_text().splitlines()[2] + "\n")
    alone, _ = _identify(db, frame2, "--brightness-calibration", ids[2]["calibration_used"])
    assert alone[0]["calibration_source"] == "given"
    for key in ("mode", "scope", "scope_unnarrowed", "calibration"):
        assert alone[0][key] == ids[2][key], key
    off, _ = _identify(db, path, "--calibration-frames", 0)
    assert all("calibration_used" not in i for i in off) and off[2]["mode"] == "four-star"
