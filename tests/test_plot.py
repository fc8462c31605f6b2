"""Pictures people can read: the display stretch, one marker vocabulary with a legend, labels that stay
inside the frame without overlapping, markers where the stars are, and the proper names."""
import math

import numpy as np
import pytest

from startrack.plot import MARKERS, _Picture, annotate_solution, annotate_stars, stretch


def _sky(seed=1, shape=(480, 640), stars=((100.3, 200.7, 40000.0), (400.0, 300.0, 8000.0), (320.2, 60.5, 2000.0))):
    rng = np.random.default_rng(seed)
    img = rng.normal(1000.0, 20.0, shape)
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    for x, y, flux in stars:
        img += flux / (2 * math.pi * 1.2**2) * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 1.2**2))
    return img.astype(np.float32)


def test_stretch_keeps_the_sky_dark_and_the_stars_bright():
    img = _sky()
    out = stretch(img)
    assert out.dtype == np.uint8 and out.shape == img.shape
    # Sky noise: at 2 sigma above the sky the display is still black, so >= 95 % of the sky pixels are.
    assert np.mean(out[400:470, 10:200] == 0) > 0.95
    # Every star's peak stands out; the brightest is near white, none is clipped to a flat disc.
    assert out[201, 100] > 200 and out[300, 400] > 120 and out[60, 320] > 60
    assert np.sum(out == 255) <= 1e-4 * out.size     # only the top 0.005 % of pixels reach white


def _pixel(path, x, y):
    import cv2

    return cv2.imread(str(path))[int(round(y)), int(round(x))]


def _is(colour, kind, tol=40):
    return np.all(np.abs(colour.astype(int) - np.array(MARKERS[kind][0])) <= tol)


def test_markers_are_where_the_stars_are_and_the_legend_explains_them(tmp_path):
    import cv2

    from startrack.camera import Camera
    from startrack.rotations import radec_roll_to_dcm

    img = _sky()
    cam = Camera.from_fov(10.0, 640, 480)
    stars = [{"x": 100.3, "y": 200.7, "flux": 40000.0}, {"x": 400.0, "y": 300.0, "flux": 8000.0},
             {"x": 320.2, "y": 60.5, "flux": 2000.0}]
    a = radec_roll_to_dcm(83.8, -1.2, 30.0)
    from startrack.rotations import dcm_to_quaternion

    doc = {"camera": cam.to_dict(), "stars": stars,
           "identification": {"status": "ok", "algorithm": "pyramid", "matches": [{"star": 0, "id": 27989}]},
           "attitude": {"status": "ok", "quaternion": dcm_to_quaternion(a).tolist(), "ra": 83.8, "dec": -1.2,
                        "roll": 30.0, "sigma_cross_boresight_arcsec": 1.0, "sigma_roll_arcsec": 10.0}}
    path = tmp_path / "solved.png"
    annotate_solution(str(path), img, doc, mag_limit=5.0)
    pic = cv2.imread(str(path))
    assert pic.shape[1] == 640 and pic.shape[0] > 480       # the legend panel is below the image
    # The identified star's ring (radius from its flux) passes through the pixel right of its centroid.
    ring = [pic[201, x] for x in range(100 + 8, 100 + 20)]
    assert any(_is(c, "identified") for c in ring)
    # An unidentified detection is drawn "detected", not "identified".
    ring = [pic[300, x] for x in range(400 + 5, 400 + 18)]
    assert any(_is(c, "detected") for c in ring) and not any(_is(c, "identified") for c in ring)
    # The legend panel shows the identified and detected markers (and nothing is drawn there twice).
    panel = pic[480:]
    assert np.any(np.all(np.abs(panel.astype(int) - np.array(MARKERS["identified"][0])) <= 10, axis=2))
    assert np.any(np.all(np.abs(panel.astype(int) - np.array(MARKERS["detected"][0])) <= 10, axis=2))


def test_labels_stay_inside_the_frame_and_do_not_overlap():
    pic = _Picture(np.zeros((300, 400), dtype=np.float32))
    rng = np.random.default_rng(3)
    points = [(int(x), int(y)) for x, y in zip(rng.uniform(0, 400, 12), rng.uniform(0, 300, 12))]
    points += [(0, 0), (399, 299), (399, 0), (0, 299)]           # corners: labels must move inside
    boxes = [pic.label(f"HIP {100000 + i} Name", p, 6) for i, p in enumerate(points)]
    for b in boxes:
        assert b[0] >= 0 and b[1] >= 0 and b[2] <= 400 and b[3] <= 300, b
    overlaps = [(i, j) for i in range(len(boxes)) for j in range(i) if
                min(boxes[i][2], boxes[j][2]) > max(boxes[i][0], boxes[j][0]) and
                min(boxes[i][3], boxes[j][3]) > max(boxes[i][1], boxes[j][1])]
    # Sixteen labels on a small frame: the placement finds free spots for nearly all of them.
    assert len(overlaps) <= 1, overlaps


def test_drawn_labels_are_whole_at_the_edges():
    """The glyphs themselves (drawn above their box's baseline, with an outline) stay inside the image."""
    pic = _Picture(np.zeros((300, 400), dtype=np.float32))
    for p in [(0, 0), (399, 0), (0, 299), (399, 299), (200, 0)]:
        pic.label("HIP 95067 Albireo", p, 6)
    pic.draw_labels()
    lit = np.argwhere(pic.canvas[:pic.h, :pic.w].max(axis=2) > 60)
    assert len(lit) > 200
    assert lit[:, 0].min() >= 1 and lit[:, 1].min() >= 1, lit.min(axis=0)
    assert lit[:, 0].max() <= pic.h - 2 and lit[:, 1].max() <= pic.w - 2, lit.max(axis=0)


def test_centroid_picture_numbers_the_detections_and_marks_rejections(tmp_path):
    import cv2

    img = _sky()
    path = tmp_path / "c.png"
    annotate_stars(str(path), img, [{"x": 100.3, "y": 200.7, "flux": 40000.0}], rejected=[{"x": 500, "y": 100}])
    pic = cv2.imread(str(path))
    cross = pic[95:106, 495:506].reshape(-1, 3)
    assert any(_is(c, "rejected") for c in cross)
    panel = pic[480:]
    assert np.any(np.all(np.abs(panel.astype(int) - np.array(MARKERS["rejected"][0])) <= 10, axis=2))


@pytest.mark.parametrize("hip,name,dec", [
    (23875, "Cursa", -5.087), (21393, "Theemin", -30.562), (112122, "Tiaki", -46.885), (113881, "Scheat", 28.083),
    (113963, "Markab", 15.205), (1067, "Algenib", 15.184), (98036, "Alshain", 6.407), (97278, "Tarazed", 10.613),
    (78820, "Acrab", -19.806), (80112, "Alniyat", -25.593), (27989, "Betelgeuse", 7.407)])
def test_proper_names_sit_on_the_right_stars(catalog, hip, name, dec):
    """The IAU (WGSN) name and the declination it gives agree with the catalog row of that HIP number."""
    from startrack.names import PROPER_NAMES, star_label

    assert PROPER_NAMES[hip] == name and star_label(hip) == f"HIP {hip} {name}"
    row = catalog.rows_by_id()[hip]
    assert abs(float(catalog.dec[row]) - dec) < 0.05


def test_proper_names_are_unique_and_in_the_catalog(catalog):
    from startrack.names import PROPER_NAMES

    assert len(set(PROPER_NAMES.values())) == len(PROPER_NAMES)
    rows = catalog.rows_by_id()
    assert all(h in rows for h in PROPER_NAMES)
    assert "Navi" not in PROPER_NAMES.values()      # a nickname the WGSN did not adopt
