"""startrack.fitsfast against astropy.io.fits: the same pixels and header values for the files it reads, None (astropy
reads them) for the others, and a FITS solve process that never imports astropy.io.fits."""
import os

import numpy as np
import pytest
from astropy.io import fits
from conftest import solve_in_a_process

from startrack import fitsfast
from startrack.imageio import read_image

HEADER = {"DATE-OBS": "2019-07-29T20:47:26.5", "TIME-OBS": "20:47:26", "MJD-OBS": 58693.866, "EXPTIME": 0.25,
          "OBJECT": "it's a test  ", "GAIN": 2, "FLIP": True, "FOCUS": -1.5e-3}


def _frame(dtype, shape=(48, 64), seed=0):
    rng = np.random.default_rng(seed)
    if np.dtype(dtype).kind == "f":
        return rng.normal(100.0, 20.0, shape).astype(dtype)
    info = np.iinfo(dtype)
    return rng.integers(info.min, info.max, shape, dtype=dtype, endpoint=True)


def _write(path, data, header=None, extension=False, **kw):
    hdr = fits.Header()
    for k, v in (header or {}).items():
        hdr[k] = v
    if extension:
        fits.HDUList([fits.PrimaryHDU(header=hdr), fits.ImageHDU(data)]).writeto(path, **kw)
    else:
        fits.PrimaryHDU(data, header=hdr).writeto(path, **kw)
    return path


@pytest.mark.parametrize("dtype", [np.uint8, np.int16, np.uint16, np.int32, np.uint32, np.int64, np.float32,
                                   np.float64])
@pytest.mark.parametrize("extension", [False, True])
def test_plain_images_are_astropys(tmp_path, dtype, extension):
    data = _frame(dtype)
    path = _write(str(tmp_path / "a.fits"), data, HEADER, extension)
    got = fitsfast.read_image(path)
    assert got is not None
    with fits.open(path) as hdul:
        want = hdul[1 if extension else 0].data
        assert got[0].dtype == want.dtype.newbyteorder("=") and got[0].shape == want.shape
        assert np.array_equal(got[0], want, equal_nan=True)
    assert got[0].dtype.isnative
    assert np.array_equal(read_image(path)[0], read_image_with_astropy(path)[0])


def read_image_with_astropy(path):
    """What read_image gave before: the file through astropy, then the same pixel handling."""
    with fits.open(path) as hdul:
        hdu = next(h for h in hdul if h.data is not None)
        data = hdu.data
    from startrack.imageio import _fits_pixels

    return _fits_pixels(np.asarray(data))


def test_a_cube_and_the_limit_are_read_as_before(tmp_path):
    cube = _frame(np.uint16, (3, 40, 50))
    path = _write(str(tmp_path / "c.fits"), cube)
    img, meta = read_image(path)
    assert img.shape == (40, 50) and np.allclose(img, cube.mean(axis=0))
    before = read_image_with_astropy(path)
    assert np.array_equal(img, before[0]) and (meta["bit_depth"], meta["saturation"]) == (before[1], before[3])
    from startrack.errors import BadInputError

    with pytest.raises(BadInputError, match="more than the limit"):
        read_image(path, max_pixels=100)


@pytest.mark.parametrize("case", ["scaled", "blank", "groups", "compressed", "table", "one_axis", "truncated",
                                  "continue", "not_fits"])
def test_other_files_are_left_to_astropy(tmp_path, case):
    path = str(tmp_path / f"{case}.fits")
    data = _frame(np.int16)
    if case == "scaled":
        hdu = fits.PrimaryHDU(data)
        hdu.header["BSCALE"] = 2.0
        hdu.header["BZERO"] = 10.0
        hdu.writeto(path)
    elif case == "blank":
        hdu = fits.PrimaryHDU(data)
        hdu.header["BLANK"] = -32768
        hdu.writeto(path)
    elif case == "groups":
        cards = ["SIMPLE  = T", "BITPIX  = -32", "NAXIS   = 3", "NAXIS1  = 0", "NAXIS2  = 3", "NAXIS3  = 4",
                 "GROUPS  = T", "PCOUNT  = 0", "GCOUNT  = 1", "END"]
        head = "".join(c[:8].ljust(8) + c[8:].ljust(72) if "=" in c else c.ljust(80) for c in cards)
        with open(path, "wb") as fh:
            fh.write(head.ljust(2880).encode() + np.zeros(12, dtype=">f4").tobytes().ljust(2880, b"\0"))
    elif case == "compressed":
        fits.HDUList([fits.PrimaryHDU(), fits.CompImageHDU(data)]).writeto(path)
    elif case == "table":
        fits.HDUList([fits.PrimaryHDU(), fits.BinTableHDU.from_columns(
            [fits.Column(name="x", format="E", array=np.arange(3.0))])]).writeto(path)
    elif case == "one_axis":
        fits.PrimaryHDU(np.arange(10, dtype=np.int16)).writeto(path)
    elif case == "truncated":
        _write(path, data)
        with open(path, "r+b") as fh:
            fh.truncate(2880 + 100)
    elif case == "continue":
        hdu = fits.PrimaryHDU(data)
        hdu.header["LONGSTR"] = "x" * 150
        hdu.writeto(path)
    else:
        with open(path, "wb") as fh:
            fh.write(b"not a FITS file at all" * 200)
    assert fitsfast.read_image(path) is None
    if case in ("scaled", "blank", "compressed"):
        # astropy reads them: read_image's answer is astropy's.
        img, _ = read_image(path)
        with fits.open(path) as hdul:
            want = next(h for h in hdul if h.data is not None and h.data.ndim >= 2).data
        assert np.allclose(img, want.astype(np.float32), equal_nan=True)


def test_headers_are_astropys_values(tmp_path):
    path = _write(str(tmp_path / "h.fits"), _frame(np.uint16), HEADER)
    got = fitsfast.read_header(path)
    want = dict(fits.getheader(path))
    for key in HEADER:
        assert got[key] == want[key] and type(got[key]) is type(want[key]), key
    assert got["DATE-OBS"] == "2019-07-29T20:47:26.5" and got["OBJECT"] == "it's a test"
    assert {k: v for k, v in want.items() if k not in ("COMMENT", "HISTORY", "")} == got
    from startrack.apparent import fits_time, image_time_tags

    assert fits_time(image_time_tags(path)[0]) == fits_time(want)


def test_a_fits_solve_process_does_not_import_astropy_fits(tmp_path):
    """A plain 16-bit FITS frame with DATE-OBS: read, timed, solved, without astropy.io.fits' ~130 ms import."""
    real = os.path.join(os.path.dirname(__file__), "data", "real", "2019-07-29T204726_Alt40_Azi-135_Try1.tiff")
    assert os.path.exists(real), "tests/data/real holds the ESA images"
    img, _ = read_image(real)
    path = _write(str(tmp_path / "esa.fits"), img.astype(np.uint16), {"DATE-OBS": "2019-07-29T20:47:26"})
    modules, doc = solve_in_a_process(path, tmp_path / "f.json")
    assert "astropy.io.fits" not in modules
    assert doc["solve"]["status"] == "ok" and doc["image"]["time"].startswith("2019-07-29T20:47:26")


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int16, np.float32])
def test_whole_dn_fits_pixels_are_the_float_reads_values(tmp_path, dtype):
    """``read_image(whole_dn=True)`` gives an unsigned 8- or 16-bit FITS image as stored (native order), with the
    float read's values, bit depth and saturation; other types as float32, as before."""
    data = _frame(dtype)
    path = _write(str(tmp_path / "w.fits"), data)
    whole, meta_w = read_image(path, whole_dn=True)
    flt, meta_f = read_image(path)
    assert meta_w == meta_f and flt.dtype == np.float32
    if np.dtype(dtype).kind == "u":
        assert whole.dtype == dtype and whole.dtype.isnative and whole.flags.c_contiguous
    else:
        assert whole.dtype == np.float32
    assert np.array_equal(whole.astype(np.float32), flt)


def test_a_solve_reads_whole_dn_and_gives_the_float_reads_answer(monkeypatch):
    """solve_image of a 16-bit file hands find_stars the decoded uint16 pixels (no float copy of the frame), and
    answers as it does for the same pixels as float32."""
    real = os.path.join(os.path.dirname(__file__), "data", "real", "2019-07-29T204726_Alt60_Azi45_Try1.tiff")
    assert os.path.exists(real), "tests/data/real holds the ESA images"
    import startrack.centroid as centroid
    from startrack.solve import solve_image

    seen = []
    find = centroid.find_stars

    def spy(image, *args, **kw):
        seen.append(np.asarray(image).dtype)
        return find(image, *args, **kw)

    monkeypatch.setattr(centroid, "find_stars", spy)
    by_path = solve_image(real)
    img, meta = read_image(real)
    by_floats = solve_image(img, saturation=meta["saturation"])
    assert seen[0] == np.uint16 and seen[-1] == np.float32
    assert by_path.status == by_floats.status == "ok"
    assert by_path.identification.matches == by_floats.identification.matches
    assert np.array_equal(by_path.attitude.quaternion, by_floats.attitude.quaternion)
