"""Apparent places: frame times, the Earth's velocity, stellar aberration (startrack.apparent)."""
import datetime as dt
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from startrack import apparent as ap
from startrack.errors import BadInputError

UTC = dt.timezone.utc
MAS = math.pi / 180 / 3.6e6


def _angle(a, b):
    """Angle between unit vectors (rad), accurate near zero."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


def _unit(rng, n):
    u = rng.normal(size=(n, 3))
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def test_perpendicular_aberration_is_asin_beta_toward_the_apex():
    # 30 km/s perpendicular to the star: the relativistic displacement is asin(v/c) (cos theta' = beta).
    state = ap.velocity_state([0.0, 30.0, 0.0])
    u = np.array([[1.0, 0.0, 0.0]])
    moved = ap.aberrate(u, state, deflection=False)
    shift = _angle(moved, u)[0]
    assert shift == pytest.approx(math.asin(30.0 / ap.C_KM_S), rel=1e-6)
    assert math.degrees(shift) * 3600 == pytest.approx(20.64, abs=0.01)
    # Toward the apex (+y), and in the plane of the star and the velocity.
    assert moved[0, 1] > 0 and abs(moved[0, 2]) < 1e-15


@settings(max_examples=60, deadline=None)
@given(st.floats(-1, 1), st.floats(0, 2 * math.pi), st.floats(0.1, 40.0))
def test_relativistic_formula_and_apex(cz, phi, speed):
    # tan(theta'/2) = sqrt((1 - beta) / (1 + beta)) tan(theta/2), theta from the apex: the special-relativistic
    # aberration (cos theta' = (cos theta + beta) / (1 + beta cos theta); e.g. Explanatory Supplement 3rd ed.
    # Eq. 7.38), in its well-conditioned half-angle form; the star moves toward the apex.
    s = math.sqrt(max(0.0, 1 - cz * cz))
    u = np.array([s * math.cos(phi), s * math.sin(phi), cz])
    apex = np.array([0.0, 0.0, 1.0])
    state = ap.velocity_state(apex * speed)
    moved = ap.aberrate(u, state, deflection=False)
    beta = speed / ap.C_KM_S
    theta = math.atan2(s, cz)
    expected = 2 * math.atan(math.sqrt((1 - beta) / (1 + beta)) * math.tan(theta / 2))
    # erfa.ab adds the Sun's potential term (< 1 microarcsecond at 1 au).
    assert _angle(moved, apex) == pytest.approx(expected, abs=1e-11)
    assert _angle(moved, apex) <= theta + 1e-15


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31), st.floats(0, 40.0))
def test_unaberrate_inverts(seed, speed):
    rng = np.random.default_rng(seed)
    v = _unit(rng, 1)[0] * speed
    state = ap.velocity_state(v, _unit(rng, 1)[0], 0.98)
    u = _unit(rng, 50)
    back = ap.unaberrate(ap.aberrate(u, state), state)
    assert np.max(_angle(back, u)) < 1e-14


def test_agrees_with_astropy_gcrs_of_a_star_at_infinity():
    from astropy import units
    from astropy.coordinates import GCRS, CartesianRepresentation, SkyCoord
    from astropy.time import Time

    rng = np.random.default_rng(7)
    u = _unit(rng, 500)
    ra = np.degrees(np.arctan2(u[:, 1], u[:, 0]))
    dec = np.degrees(np.arcsin(u[:, 2]))
    stars = SkyCoord(ra=ra * units.deg, dec=dec * units.deg, frame="icrs")
    for when, v_sc in ((dt.datetime(2026, 3, 20, 6, tzinfo=UTC), None),
                       (dt.datetime(2026, 9, 22, 18, 30, tzinfo=UTC), np.array([3.1, -6.2, 2.4]))):
        state = ap.observer_state(when, v_sc)
        ours = ap.aberrate(u, state)
        extra = {} if v_sc is None else {"obsgeovel": CartesianRepresentation(v_sc * units.km / units.s)}
        g = stars.transform_to(GCRS(obstime=Time(when), **extra)).cartesian.xyz.value.T
        g /= np.linalg.norm(g, axis=1, keepdims=True)
        assert np.max(_angle(ours, g)) < 1.0 * MAS
        # And the effect itself is there: up to ~20.5" (+ LEO).
        assert np.max(_angle(ours, u)) > 15 / 206265


def test_earth_velocity_is_the_orbital_one():
    # About 29.8 km/s, perpendicular to the Sun direction within the orbit's eccentricity (~1 deg).
    for month in (1, 4, 7, 10):
        t = dt.datetime(2026, month, 5, tzinfo=UTC)
        state = ap.observer_state(t)
        speed = np.linalg.norm(state.earth_km_s)
        assert 29.2 < speed < 30.4
        cosang = state.earth_km_s @ state.sun_to_observer / speed
        assert abs(cosang) < math.sin(math.radians(1.5))


def test_apparent_scale_matches_aberrated_separations():
    state = ap.velocity_state([20.0, -15.0, 10.0])
    rng = np.random.default_rng(3)
    for b in _unit(rng, 5):
        # Two stars 5 deg apart around b.
        perp = np.cross(b, [0.3, 0.5, 0.8])
        perp /= np.linalg.norm(perp)
        d = math.radians(2.5)
        p, q = b * math.cos(d) + perp * math.sin(d), b * math.cos(d) - perp * math.sin(d)
        pa, qa = ap.aberrate(np.array([p, q]), state, deflection=False)
        ratio = _angle(pa, qa) / _angle(p, q)
        assert ratio == pytest.approx(ap.apparent_scale(b, state), abs=2e-7)


def test_frame_time_sources_in_order():
    given_time = dt.datetime(2026, 1, 2, 3, 4, 5, tzinfo=UTC)
    doc = {"image": {"time": "2026-12-05T10:00:00Z"}}
    assert ap.frame_time(doc, explicit=given_time) == ap.FrameTime(given_time, "given")
    assert ap.frame_time(doc).source == "image.time"
    assert ap.frame_time(doc).time == dt.datetime(2026, 12, 5, 10, tzinfo=UTC)
    header = {"DATE-OBS": "2019-07-29T20:47:26"}
    assert ap.frame_time({}, fits_header=header) == ap.FrameTime(dt.datetime(2019, 7, 29, 20, 47, 26, tzinfo=UTC),
                                                                 "FITS DATE-OBS")
    mjd = ap.frame_time({}, fits_header={"MJD-OBS": 61000.25})
    assert mjd.source == "FITS MJD-OBS" and mjd.time == dt.datetime(2025, 11, 21, 6, tzinfo=UTC)  # MJD 60000 = 2023-02-25
    exif = ap.frame_time({}, exif_datetime="2019:07:29 22:47:26", utc_offset_hours=2)
    assert exif == ap.FrameTime(dt.datetime(2019, 7, 29, 20, 47, 26, tzinfo=UTC), "EXIF DateTimeOriginal")
    # EXIF has no zone: without an offset the time is unknown.
    assert not ap.frame_time({}, exif_datetime="2019:07:29 22:47:26").known
    assert ap.frame_time({}) == ap.FrameTime(None, None)


def test_velocity_input_is_checked():
    assert ap.parse_velocity("1,2,3", "--velocity-km-s").tolist() == [1, 2, 3]
    for bad in ("1,2", "a,b,c", "1,2,nan", "1e5,0,0"):
        with pytest.raises(BadInputError):
            ap.parse_velocity(bad, "--velocity-km-s")
    with pytest.raises(BadInputError, match="observer.velocity_km_s"):
        ap.frame_velocity({"observer": {"velocity_km_s": [1, 2]}}, source="f.jsonl:1")
    v, source = ap.frame_velocity({"observer": {"velocity_km_s": [1, 2, 3]}})
    assert source == "observer.velocity_km_s" and v.tolist() == [1, 2, 3]


@pytest.mark.parametrize("k1", [0.0, -0.05])
def test_astrometric_attitude_maps_pixels_to_astrometric_directions(k1):
    # The WCS's pinhole (rotation + scaled focal length) against the exact map: pixel -> true camera
    # direction -> apparent ICRS -> aberration removed, over the whole image, for 35 km/s.  What a
    # pinhole leaves is the aberration's second-order term in the field angle, below (v/c) theta^2
    # (0.4" at this image's corner); a wrong scale would leave (v/c) theta, five times more.
    from startrack.camera import Camera
    from startrack.rotations import quaternion_to_dcm, random_quaternions

    rng = np.random.default_rng(11)
    cam = Camera(1024, 768, 3000.0, 511.5, 383.5, k1, 0.0)
    for q in random_quaternions(5, rng):
        dcm = quaternion_to_dcm(q)
        state = ap.velocity_state(_unit(rng, 1)[0] * 35.0, _unit(rng, 1)[0], 1.0)
        a_astro, cam_astro = ap.astrometric_attitude(dcm, cam, state)
        # (the first-order scale holds for these lenses: not fitted)
        assert cam_astro.focal_length_px == cam.focal_length_px * ap.apparent_scale(dcm[2], state)
        x, y = rng.uniform(-0.5, 1023.5, 200), rng.uniform(-0.5, 767.5, 200)
        exact = ap.unaberrate(np.asarray(cam.pixels_to_vectors(x, y)) @ dcm, state)
        model = np.asarray(cam_astro.pixels_to_vectors(x, y)) @ a_astro
        corner = math.hypot(512, 384) / cam.focal_length_px
        assert np.max(_angle(exact, model)) < 35.0 / ap.C_KM_S * corner ** 2
        # ... and the true attitude alone would be off by the aberration itself.
        plain = np.asarray(cam.pixels_to_vectors(x, y)) @ dcm
        assert np.max(_angle(exact, plain)) > 5 / 206265


def test_astrometric_attitude_of_a_fitted_fisheye_that_folds_in_its_corners():
    # A blind solve's camera of a 100 deg field (stereographic, its polynomial fitted on the stars): it folds
    # beyond them, in the image's corners, where it maps no direction.  The map to astrometric directions is made
    # of the pixels it maps (the grid's NaN rows made the SVD raise LinAlgError), and its focal scale is fitted:
    # over the mapped field it is within the second-order bound, where the pinhole's first-order scale
    # (apparent_scale) is not, for this lens.
    from startrack.camera import Camera
    from startrack.rotations import quaternion_to_dcm, random_quaternions

    cam = Camera.from_dict({"width": 1280, "height": 960, "focal_length_px": 821.3842055430567,
                            "cx": 638.281503283044, "cy": 483.86762147838846, "projection": "stereographic",
                            "distortion": {"k1": 0.12937215237171976, "k2": -1.007495147742464,
                                           "k3": 1.7511498196382722, "k4": -1.1576045610520365}})
    corners = np.asarray(cam.pixels_to_vectors(np.array([-0.5, 1279.5, -0.5, 1279.5]),
                                               np.array([-0.5, -0.5, 959.5, 959.5])))
    assert not np.isfinite(corners).any()
    rng = np.random.default_rng(5)
    worse = 0
    for q in random_quaternions(3, rng):
        dcm = quaternion_to_dcm(q)
        state = ap.velocity_state(_unit(rng, 1)[0] * 35.0, _unit(rng, 1)[0], 1.0)
        a_astro, cam_astro = ap.astrometric_attitude(dcm, cam, state)
        assert np.all(np.isfinite(a_astro)) and np.allclose(a_astro @ a_astro.T, np.eye(3), atol=1e-12)
        x, y = rng.uniform(-0.5, 1279.5, 2000), rng.uniform(-0.5, 959.5, 2000)
        v = np.asarray(cam.pixels_to_vectors(x, y))
        model_b = np.asarray(cam_astro.pixels_to_vectors(x, y))
        # (away from the fold, where the map's radial derivative goes to 0 and any scale moves a direction far:
        # the pixels mapped at focal lengths 0.1 % either side)
        ok = np.isfinite(v).all(axis=1) & np.isfinite(model_b).all(axis=1)
        for s in (0.999, 1.001):
            ok &= np.isfinite(np.asarray(cam.with_focal_length(cam.focal_length_px * s).pixels_to_vectors(x, y))).all(1)
        assert ok.mean() > 0.85
        exact = ap.unaberrate(v[ok] @ dcm, state)
        theta = np.arccos(np.clip(v[ok][:, 2], -1.0, 1.0)).max()
        bound = 35.0 / ap.C_KM_S * theta ** 2
        assert np.max(_angle(exact, model_b[ok] @ a_astro)) < bound
        # The first-order scale with its best rotation, on the same pixels.
        first = np.asarray(cam.with_focal_length(cam.focal_length_px * ap.apparent_scale(dcm[2], state))
                           .pixels_to_vectors(x[ok], y[ok]))
        u, _, vt = np.linalg.svd(first.T @ exact)
        rot = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt))]) @ vt
        worse += np.max(_angle(exact, first @ rot)) > bound
    assert worse >= 2


def test_parallax_agrees_with_astropy_gcrs_of_near_stars():
    """Stars at finite distance (issue 39: "parallax for the stars that have one"): the apparent place with the
    parallax agrees with astropy's ICRS -> GCRS of a star with that distance within 1 mas; without the parallax
    term alpha Centauri's place is off by up to its 0.75"."""
    from astropy import units
    from astropy.coordinates import GCRS, SkyCoord
    from astropy.time import Time

    rng = np.random.default_rng(39)
    u = _unit(rng, 200)
    plx = rng.uniform(50.0, 800.0, len(u))                 # mas: 1.25 to 20 pc
    ra = np.degrees(np.arctan2(u[:, 1], u[:, 0]))
    dec = np.degrees(np.arcsin(u[:, 2]))
    stars = SkyCoord(ra=ra * units.deg, dec=dec * units.deg, distance=(1000.0 / plx) * units.pc, frame="icrs")
    worst_without = 0.0
    for when in (dt.datetime(2026, 3, 20, 6, tzinfo=UTC), dt.datetime(2026, 6, 21, 18, tzinfo=UTC)):
        state = ap.observer_state(when)
        assert 0.97 < np.linalg.norm(state.position_au) < 1.03
        g = stars.transform_to(GCRS(obstime=Time(when))).cartesian.xyz.value.T
        g /= np.linalg.norm(g, axis=1, keepdims=True)
        assert np.max(_angle(ap.aberrate(u, state, parallax_mas=plx), g)) < 1.0 * MAS
        worst_without = max(worst_without, float(np.max(_angle(ap.aberrate(u, state), g))))
        # One star at a time (the attitude's per-star call) is the same.
        np.testing.assert_allclose(ap.aberrate(u[3], state, parallax_mas=plx[3]), ap.aberrate(u, state, parallax_mas=plx)[3],
                                   atol=1e-15)
    assert worst_without > 0.5 / 206265


def _pillow_time_tag(path):
    from PIL import Image

    with Image.open(path) as img:
        exif = img.getexif()
        value = exif.get_ifd(0x8769).get(0x9003) or exif.get(0x0132)
    return value if isinstance(value, str) else None


@pytest.mark.parametrize("fmt", ["tiff", "jpeg", "png"])
@pytest.mark.parametrize("tags", [{}, {"dt": "2019:07:29 20:47:26"}, {"dto": "2021:01:02 03:04:05"},
                                  {"dt": "2019:07:29 20:47:26", "dto": "2021:01:02 03:04:05"},
                                  {"dt": "2019:07:29 20:47:26", "dto": ""}, {"dt": "abc"}])
def test_image_time_tags_read_directly_agree_with_pillow(tmp_path, fmt, tags):
    """The direct TIFF/JPEG/PNG tag reader gives what Pillow gives."""
    from PIL import Image

    exif = Image.Exif()
    if "dt" in tags:
        exif[0x0132] = tags["dt"]
    if "dto" in tags:
        exif.get_ifd(0x8769)[0x9003] = tags["dto"]
    img = Image.fromarray((np.arange(64 * 48) % 251).astype(np.uint8).reshape(48, 64))
    path = str(tmp_path / f"frame.{fmt}")
    img.save(path, exif=exif)
    want = _pillow_time_tag(path)
    if fmt == "jpeg" or "dto" not in tags:      # Pillow writes a TIFF or PNG EXIF directory, or not, by version
        assert want == (tags.get("dto") or tags.get("dt"))      # the oracle holds what was written
    found, got = ap._exif_datetime(path)
    assert found
    assert got == want
    assert ap.image_time_tags(path) == (None, want)


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    import struct
    import zlib

    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


@pytest.mark.parametrize("where", ["after the pixels", "text chunk", "two eXIf chunks", "truncated"])
def test_png_time_tags_without_decoding_agree_with_pillow(tmp_path, where):
    """A PNG's eXIf chunk after its pixels (where Pillow decodes the image to reach it), one before and one after, an EXIF
    held in a text chunk (left to Pillow) and a truncated file (refused, Pillow decides): Pillow's answer."""
    import io

    from PIL import Image

    def exif_bytes(dto):
        exif = Image.Exif()
        exif[0x0132] = "2019:07:29 20:47:26"
        exif.get_ifd(0x8769)[0x9003] = dto
        return exif.tobytes()[6:]           # the TIFF structure (Exif.tobytes() starts with its Exif header)

    buf = io.BytesIO()
    Image.fromarray((np.arange(64 * 48) % 251).astype(np.uint8).reshape(48, 64)).save(buf, format="png")
    raw = buf.getvalue()
    end = raw.rindex(b"IEND") - 4           # the IEND chunk's length field
    if where == "after the pixels":
        data = raw[:end] + _png_chunk(b"eXIf", exif_bytes("2021:01:02 03:04:05")) + raw[end:]
    elif where == "two eXIf chunks":
        data = raw[:33] + _png_chunk(b"eXIf", exif_bytes("2001:01:01 01:01:01")) + raw[33:end] \
            + _png_chunk(b"eXIf", exif_bytes("2021:01:02 03:04:05")) + raw[end:]
    elif where == "text chunk":
        hexed = (b"Exif\0\0" + exif_bytes("2011:11:11 11:11:11")).hex().encode()
        data = raw[:33] + _png_chunk(b"tEXt", b"Raw profile type exif\0\nexif\n %d\n" % (len(hexed) // 2) + hexed
                                     + b"\n") + raw[33:]
    else:
        data = raw[:end - 20]
    path = tmp_path / "frame.png"
    path.write_bytes(data)
    if where == "truncated":
        with pytest.raises(ValueError):
            ap._exif_datetime(str(path))
        assert ap.image_time_tags(str(path)) == (None, None)
        return
    want = _pillow_time_tag(str(path))
    found, got = ap._exif_datetime(str(path))
    if where == "text chunk":
        assert not found and want == "2011:11:11 11:11:11"     # Pillow's to read
    else:
        assert found and got == want == ("2001:01:01 01:01:01" if where == "two eXIf chunks" else "2021:01:02 03:04:05")
    assert ap.image_time_tags(str(path)) == (None, want)


def test_image_time_tags_of_a_big_endian_tiff(tmp_path):
    """A Motorola-order TIFF whose EXIF directory holds DateTimeOriginal (written by hand)."""
    import struct

    text = b"2020:02:03 04:05:06\0"
    # header, IFD0 at 8: one entry (ExifIFD -> 26), next 0; EXIF IFD at 26: one entry (DateTimeOriginal -> 44)
    ifd0 = struct.pack(">H", 1) + struct.pack(">HHII", 0x8769, 4, 1, 26) + struct.pack(">I", 0)
    exif = struct.pack(">H", 1) + struct.pack(">HHII", 0x9003, 2, len(text), 44) + struct.pack(">I", 0)
    data = b"MM\0*" + struct.pack(">I", 8) + ifd0 + exif + text
    assert len(b"MM\0*" + struct.pack(">I", 8) + ifd0) == 26 and len(data) - len(text) == 44
    path = tmp_path / "be.tif"
    path.write_bytes(data)
    assert ap._exif_datetime(str(path)) == (True, "2020:02:03 04:05:06")
    path.write_bytes(data[:30])          # truncated: the reader refuses, Pillow decides
    with pytest.raises(ValueError):
        ap._exif_datetime(str(path))
    assert ap.image_time_tags(str(path)) == (None, None)
