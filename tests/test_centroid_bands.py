"""find_stars on large frames, measured in bands of rows (issue 41): the same stars as the whole-frame path,
and a peak memory of ~2 bytes a pixel beyond the frame."""
import math
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import startrack.centroid as centroid
from startrack.camera import Camera
from startrack.centroid import CentroidOptions, find_stars
from startrack.render import Scene, Sensor, render_image


@pytest.fixture(scope="module")
def frame(catalog):
    """A 16-bit 1600 x 1200 frame of Orion: a sky three times brighter on one side, saturated stars, hot pixels."""
    from startrack.rotations import _radec_roll_to_dcm_rad

    cam = Camera.from_fov(16, 1600, 1200)
    a = _radec_roll_to_dcm_rad(math.radians(83.8), math.radians(-1.2), 0.2)
    sensor = Sensor(psf_sigma_px=1.3, hot_pixels=40, exposure_ms=1000.0)
    image, _ = render_image(catalog.filter_magnitude(None, 9.0), cam, a, sensor, Scene(gradient=3.0),
                            np.random.default_rng(7))
    return np.ascontiguousarray(image)


def _both(image, options, monkeypatch, band_rows):
    """find_stars on the whole frame, then in bands of about ``band_rows`` rows (forced on this small frame)."""
    monkeypatch.setattr(centroid, "_BAND_MIN_PIXELS", 10**12)
    whole = find_stars(image, options, saturation=65535.0)
    monkeypatch.setattr(centroid, "_BAND_MIN_PIXELS", 0)
    monkeypatch.setattr(centroid, "_BAND_BYTES", 4 * image.shape[1] * band_rows)
    assert centroid._banded(np.asarray(image), options)
    banded = find_stars(image, options, saturation=65535.0)
    return whole, banded


@pytest.mark.parametrize("opts", [{}, {"matched_filter": True, "threshold_sigma": 3.0}, {"max_stars": 40},
                                  {"matched_filter": True, "max_stars": 25, "gain_e_per_dn": 1.0},
                                  {"mesh_px": 48}, {"method": "com"}, {"method": "iwc", "matched_filter": True},
                                  {"method": "quine", "max_stars": 40}])
def test_bands_give_the_whole_frames_stars(frame, opts, monkeypatch):
    options = CentroidOptions(**opts)
    whole, banded = _both(frame, options, monkeypatch, 100)
    a, b = whole.stars, banded.stars
    assert len(a) == len(b) and len(a) >= (25 if opts.get("max_stars") == 25 else 40)
    assert any(s["saturated"] for s in a)
    # Stars across the bands' borders: the mask's bands are whole tile rows, the fits' bands start on one.
    cell = options.mesh_px
    assert options.max_stars or sum(min(s["y"] % cell, cell - s["y"] % cell) < 4 for s in a) >= 5
    for s, t in zip(a, b):          # the same order (brightest first, after the brightest-N cut)
        assert abs(s["x"] - t["x"]) < 1e-6 and abs(s["y"] - t["y"]) < 1e-6
        assert t["flux"] == pytest.approx(s["flux"], rel=1e-9)
        assert set(s) == set(t) and s["saturated"] == t["saturated"] and s["npix"] == t["npix"]
    assert [r["reason"] for r in whole.rejected] == [r["reason"] for r in banded.rejected]
    assert (whole.background_level, whole.background_sigma) == (banded.background_level, banded.background_sigma)


def test_bands_of_a_float_frame_and_a_blend(frame, monkeypatch):
    """A float32 frame (as read_image gives) and two touching stars deblended across a band's border."""
    image = frame.astype(np.float32)
    yy, xx = np.mgrid[0:15, 0:15]
    for (x, y) in ((400.3, 126.2), (404.3, 129.4)):     # 5.1 px apart, across row 128 (a multiple of 64)
        image[122:137, 395:410] += 9000.0 * np.exp(-((xx + 395 - x) ** 2 + (yy + 122 - y) ** 2) / (2 * 1.3**2))
    whole, banded = _both(image, CentroidOptions(), monkeypatch, 64)
    assert sum(bool(s.get("deblended")) and abs(s["y"] - 128) < 3 for s in whole.stars) == 2
    assert len(whole.stars) == len(banded.stars)
    for s, t in zip(whole.stars, banded.stars):
        assert abs(s["x"] - t["x"]) < 1e-6 and abs(s["y"] - t["y"]) < 1e-6 and s.get("deblended") == t.get("deblended")


def test_residual_at_is_the_passes_residual_to_the_bit():
    """The residual recomputed from the mesh (labelling, bands) equals subtract_background_rows' own."""
    from startrack._kernels.centroid import residual_rows, subtract_background_rows

    rng = np.random.default_rng(3)
    h, w, cell = 150, 211, 32
    img = rng.integers(0, 4000, (h, w)).astype(np.uint16)
    level = rng.uniform(100, 900, (-(-h // cell), -(-w // cell)))
    res = np.empty((h, w), dtype=np.float32)
    labels = np.zeros((h, w), dtype=np.uint16)
    subtract_background_rows(img.astype(np.float32), level, level * 0 + 50.0, float(cell), res, labels, 65535,
                             np.zeros(h, dtype=np.int64), 0, h, level, 3.0, 0.986, np.empty((0, 0)), 0)
    again = residual_rows(img, level, float(cell), 0, h, 0, w, np.empty((h, w), dtype=np.float32))
    assert np.array_equal(res.view(np.uint32), again.view(np.uint32))
    part = residual_rows(img, level, float(cell), 37, 101, 15, 190, np.empty((64, 175), dtype=np.float32))
    assert np.array_equal(part, res[37:101, 15:190])


_PEAK = textwrap.dedent("""
    import sys
    import numpy as np
    import startrack.centroid as centroid
    from startrack.centroid import CentroidOptions, find_stars

    def status(key):
        for line in open("/proc/self/status"):
            if line.startswith(key):
                return int(line.split()[1]) * 1024

    h, w = 4000, 5000
    rng = np.random.default_rng(1)
    image = np.empty((h, w), dtype=np.uint16)
    for r in range(0, h, 250):          # the frame, without a float copy of it
        image[r:r + 250] = rng.normal(1000.0, 10.0, (250, w)).astype(np.uint16)
    yy, xx = np.mgrid[0:11, 0:11]
    for x, y in rng.uniform(10, [w - 20, h - 20], (300, 2)):
        image[int(y):int(y) + 11, int(x):int(x) + 11] += (3000 * np.exp(-((xx - 5) ** 2 + (yy - 5) ** 2) / 2.9)
                                                          ).astype(np.uint16)
    options = CentroidOptions(matched_filter=sys.argv[1] == "deep")
    # The kernels first (compiled or loaded: numba's own memory is not the frame's), on a small frame in bands.
    saved, centroid._BAND_MIN_PIXELS = centroid._BAND_MIN_PIXELS, 0
    find_stars(image[:512, :768].copy(), options)
    centroid._BAND_MIN_PIXELS = saved
    try:
        open("/proc/self/clear_refs", "w").write("5")       # the peak RSS starts again from here
    except OSError:
        pass
    before = status("VmRSS:")
    result = find_stars(image, options)
    print(len(result.stars), before, status("VmHWM:"))
""")


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="reads the peak RSS from /proc")
@pytest.mark.parametrize("mode", ["plain", "deep"])
def test_peak_memory_of_a_large_frame_is_two_bytes_a_pixel(mode):
    """A 20 Mpx 16-bit frame (40 MB): find_stars' peak beyond the frame is at most 2.5 bytes a pixel plus 40 MB
    (the whole-frame path took a float copy, the residual and the labels: 10 bytes a pixel; 14 with the
    matched filter)."""
    out = subprocess.run([sys.executable, "-c", _PEAK, mode], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    n_stars, before, peak = (int(v) for v in out.stdout.split())
    assert n_stars >= 250
    assert peak - before <= 2.5 * 20_000_000 + 40_000_000, (peak - before) / 1e6


@pytest.mark.parametrize("bits", [8, 16])
def test_centroid_cli_keeps_whole_dn_frames_as_decoded(frame, bits, tmp_path):
    """read_image(whole_dn=True) gives the file's own values in its own type, and `startrack centroid` (which reads
    so) finds the stars find_stars finds on the float32 read."""
    import json

    from conftest import run_cli

    from startrack.imageio import read_image, write_image

    path = str(tmp_path / f"sky{bits}.png")
    write_image(path, frame if bits == 16 else (frame >> 8).astype(np.uint8))
    as_float, meta = read_image(path)
    as_read, meta2 = read_image(path, whole_dn=True)
    assert as_float.dtype == np.float32 and as_read.dtype == (np.uint16 if bits == 16 else np.uint8)
    assert np.array_equal(as_read, as_float) and meta == meta2
    want = find_stars(as_float, CentroidOptions(max_stars=30), saturation=meta["saturation"]).stars
    doc = json.loads(run_cli("centroid", path, "--max-stars", "30", "-q", check=True).stdout)
    assert [(s["x"], s["y"], s["flux"]) for s in doc["stars"]] == [(s["x"], s["y"], s["flux"]) for s in want]
    assert doc["image"]["bit_depth"] == bits


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("opts", [{}, {"matched_filter": True, "threshold_sigma": 3.0}, {"max_stars": 40},
                                  {"method": "com"}, {"background": "global"}, {"background": "tophat"}])
def test_whole_dn_frames_give_their_float_copys_stars(frame, bits, opts, monkeypatch):
    """An 8- or 16-bit frame is measured as it is, without a float copy (the whole-frame path since session 11):
    the kernels read whole DN as float32 holds them, so every number is the float32 copy's to the bit."""
    monkeypatch.setattr(centroid, "_BAND_MIN_PIXELS", 10**12)
    image = frame if bits == 16 else np.clip(frame // 64, 0, 255).astype(np.uint8)
    options = CentroidOptions(**opts)
    sat = float(np.iinfo(image.dtype).max)
    got = find_stars(image, options, saturation=sat)
    want = find_stars(image.astype(np.float32), options, saturation=sat)
    assert len(got.stars) >= 20
    assert got.stars == want.stars and got.rejected == want.rejected
    assert (got.background_level, got.background_sigma, got.reason) == \
        (want.background_level, want.background_sigma, want.reason)


def test_whole_dn_frames_are_not_copied_to_float(frame, monkeypatch):
    """The whole-frame path takes no float copy of an 8- or 16-bit frame (a 12 Mpx frame's copy is 48 MB and a
    third of its find_stars time): the kernels are handed the frame itself."""
    from startrack._kernels import centroid as kernels

    monkeypatch.setattr(centroid, "_BAND_MIN_PIXELS", 10**12)
    seen = []
    real = kernels.label_blobs_into

    def spy(residual, image, *args):
        seen.append(image)
        return real(residual, image, *args)

    monkeypatch.setattr(kernels, "label_blobs_into", spy)
    for image in (frame, np.clip(frame // 64, 0, 255).astype(np.uint8)):
        seen.clear()
        find_stars(image, CentroidOptions())
        assert len(seen) == 1 and seen[0] is image


def test_whole_dn_frames_take_no_frame_sized_float_copy(frame, monkeypatch):
    """Nothing in find_stars makes a float copy of an 8- or 16-bit frame on the whole-frame path, the background
    mesh's samples included (its strips of float32 were once made and dropped unread: 4 bytes a pixel and ~0.6 ms of
    a 1024 x 768 frame): the memory it takes beyond its reused buffers stays under a quarter of such a copy."""
    import tracemalloc

    monkeypatch.setattr(centroid, "_BAND_MIN_PIXELS", 10**12)
    for image in (frame, np.clip(frame // 64, 0, 255).astype(np.uint8)):
        find_stars(image, CentroidOptions())          # the thread's buffers for this shape, made once
        tracemalloc.start()
        try:
            find_stars(image, CentroidOptions())
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < image.size, (image.dtype, peak, 4 * image.size)
