"""The shipped constellation stick figures: the table is right, shipped, and drawn where the stars are."""
import os

import numpy as np
import pytest


def load_figures(path=None):
    from startrack.constellations import load_figures

    return load_figures(path)

#: Stars a figure borrows from a neighbour, as every drawing does (the table's header names them).
BORROWED = {("Peg", 677), ("Aur", 25428)}
#: The 88 IAU abbreviations.
IAU = set("""And Ant Aps Aqr Aql Ara Ari Aur Boo Cae Cam Cnc CVn CMa CMi Cap Car Cas Cen Cep Cet Cha Cir Col Com CrA CrB
Crv Crt Cru Cyg Del Dor Dra Equ Eri For Gem Gru Her Hor Hya Hyi Ind Lac Leo LMi Lep Lib Lup Lyn Lyr Men Mic Mon Mus Nor
Oct Oph Ori Pav Peg Per Phe Pic Psc PsA Pup Pyx Ret Sge Sgr Sco Scl Sct Ser Sex Tau Tel Tri TrA Tuc UMa UMi Vel Vir Vol
Vul""".split())


def test_the_table_is_a_package_file_with_its_provenance_and_licence():
    from startrack.constellations import FIGURES_PATH

    # in the package directory (a wheel ships every file under startrack/), not beside the repository
    assert os.path.dirname(FIGURES_PATH) == os.path.join(os.path.dirname(os.path.abspath(
        __import__("startrack").__file__)), "data")
    head = open(FIGURES_PATH, encoding="utf-8").read(3000)
    assert "Provenance" in head and "public domain" in head and "CC0" in head


def test_every_figure_star_is_bright_in_the_catalog_and_inside_its_constellation(catalog):
    """Each HIP number is a catalog star brighter than Hp 5.1 lying within the IAU boundary of its figure's
    constellation (astropy's get_constellation), except the borrowed stars; no segment spans more than 25 deg."""
    import astropy.units as u
    from astropy.coordinates import SkyCoord, get_constellation

    figures = load_figures()
    assert len(figures) >= 40 and len({f.abbr for f in figures}) == len(figures)
    rows = catalog.rows_by_id()
    vec = catalog.vectors()
    wrong = []
    for fig in figures:
        assert fig.abbr in IAU, fig.abbr
        ids = sorted(fig.stars())
        assert all(h in rows for h in ids), [h for h in ids if h not in rows]
        k = np.array([rows[h] for h in ids])
        assert np.all(catalog.mag[k] < 5.1), (fig.abbr, catalog.mag[k].max())
        where = get_constellation(SkyCoord(catalog.ra[k] * u.deg, catalog.dec[k] * u.deg), short_name=True)
        wrong += [(fig.abbr, h, c) for h, c in zip(ids, where) if c != fig.abbr and (fig.abbr, h) not in BORROWED]
        for a, b in fig.segments():
            assert np.degrees(np.arccos(np.clip(vec[rows[a]] @ vec[rows[b]], -1, 1))) < 25, (fig.abbr, a, b)
    assert not wrong, wrong


def test_a_malformed_table_is_named_with_its_line(tmp_path):
    from startrack.errors import BadInputError

    bad = tmp_path / "t.txt"
    bad.write_text("# ok\nOri Orion 27989 26727\nCyg Cygnus 102098 x1\n")
    with pytest.raises(BadInputError, match=r"t\.txt:3.*'102098 x1'"):
        load_figures(str(bad))


def test_segments_land_on_the_stars_they_join(catalog):
    """Orion seen from its centre: the belt's polyline starts and ends at Alnitak's and Alnilam's projected
    pixels, and a figure behind the camera draws nothing."""
    from startrack.camera import Camera
    from startrack.constellations import figure_segments_in_image
    from startrack.rotations import radec_roll_to_dcm

    cam = Camera.from_fov(30, 1200, 900)
    a = radec_roll_to_dcm(84.0, 0.0, 20.0)
    drawn = {f.abbr: (lines, where) for f, lines, where in figure_segments_in_image(load_figures(), catalog, a, cam)}
    assert "Ori" in drawn and "UMa" not in drawn and "Cru" not in drawn
    rows = catalog.rows_by_id()
    px = {h: np.array(cam.vectors_to_pixels(a @ catalog.vectors()[rows[h]])) for h in (26727, 26311, 25930)}
    lines, where = drawn["Ori"]
    starts = {tuple(np.round(line[0], 6)) for line in lines} | {tuple(np.round(line[-1], 6)) for line in lines}
    for h in px:
        assert any(np.hypot(*(np.array(s) - px[h])) < 1e-6 for s in starts), h
    assert cam.in_image(*where)


def test_the_overlay_draws_lines_and_names_only_on_request(tmp_path):
    """annotate_solution(constellations=True) draws Orion's figure in its colour along Betelgeuse-Alnitak
    (main: no such parameter); without it, that colour is nowhere in the picture."""
    import cv2

    from startrack.camera import Camera
    from startrack.catalog import load_catalog
    from startrack.plot import MARKERS, annotate_solution
    from startrack.rotations import dcm_to_quaternion, radec_roll_to_dcm

    cam = Camera.from_fov(30, 800, 600)
    a = radec_roll_to_dcm(84.0, 2.0, 0.0)
    doc = {"camera": cam.to_dict(), "stars": [], "identification": {"status": "failed"},
           "attitude": {"status": "ok", "quaternion": dcm_to_quaternion(a).tolist(), "ra": 84.0, "dec": 2.0,
                        "roll": 0.0}}
    image = np.random.default_rng(1).normal(100, 3, (600, 800)).astype(np.float32)
    colour = np.array(MARKERS["constellation"][0])
    cat = load_catalog()
    rows = cat.rows_by_id()
    x, y = cam.vectors_to_pixels(np.array([a @ cat.vectors()[rows[h]] for h in (27989, 26727)]))
    for flag in (True, False):
        path = tmp_path / f"o-{flag}.png"
        annotate_solution(str(path), image, doc, cat, mag_limit=3.0, constellations=flag)
        pic = cv2.imread(str(path))[:600]
        lit = np.all(np.abs(pic.astype(int) - colour) <= 30, axis=2)
        # points along the line from the shoulder to the belt, away from the star markers at its ends
        on_line = [lit[int(round(y[0] + t * (y[1] - y[0]))) - 1: int(round(y[0] + t * (y[1] - y[0]))) + 2,
                       int(round(x[0] + t * (x[1] - x[0]))) - 1: int(round(x[0] + t * (x[1] - x[0]))) + 2].any()
                   for t in np.linspace(0.2, 0.8, 13)]
        if flag:
            assert sum(on_line) >= 9, on_line      # a predicted-star square or the name may cover a few
        else:
            assert not lit.any()
