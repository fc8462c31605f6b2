"""startrack.tifffast against OpenCV: the same pixels for the plain TIFF files it reads (grey, 8 or 16 bits, not
compressed, in strips, either byte order), None (OpenCV reads them) for the others, and a solve process of a plain
TIFF that never imports cv2."""
import os
import struct

import cv2
import numpy as np
import pytest
from conftest import solve_in_a_process

from startrack import tifffast
from startrack.errors import BadInputError
from startrack.imageio import _read_cv2, read_image

REAL = os.path.join(os.path.dirname(__file__), "data", "real")


def _frame(dtype, shape=(23, 37), seed=0):
    info = np.iinfo(dtype)
    return np.random.default_rng(seed).integers(info.min, info.max, shape, dtype=dtype, endpoint=True)


def _opencv(path):
    return cv2.imread(path, cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)


def _tiff(path, data, order="<", rows_per_strip=None, reverse_strips=False, extra=(), photometric=1, pages=1,
          offsets_type=4):
    """A baseline TIFF file written by hand: ``data`` (2-D uint8/uint16) in strips of ``rows_per_strip`` rows
    (stored last strip first with ``reverse_strips``), the directory's entries plus ``extra`` (tag, type, value)
    entries, ``pages`` images (each the same pixels plus its page number)."""
    h, w = data.shape
    bits = data.dtype.itemsize * 8
    rows = rows_per_strip or h
    n_strips = -(-h // rows)
    codes = {3: "H", 4: "I"}
    out = bytearray(b"II*\0" if order == "<" else b"MM\0*")
    out += b"\0\0\0\0"          # the first directory's offset, set below
    link = 4
    for page in range(pages):
        img = (data + page).astype(data.dtype.newbyteorder(order))
        strips = [img[k * rows:(k + 1) * rows].tobytes() for k in range(n_strips)]
        where = [0] * n_strips
        for k in (reversed(range(n_strips)) if reverse_strips else range(n_strips)):
            where[k] = len(out)
            out += strips[k]
        arrays = {}
        entries = [(256, 4, [w]), (257, 4, [h]), (258, 3, [bits]), (259, 3, [1]), (262, 3, [photometric]),
                   (273, offsets_type, where), (277, 3, [1]), (278, 4, [rows]),
                   (279, 4, [len(s) for s in strips])] + [(t, k, [v]) for t, k, v in extra]
        entries.sort()
        for tag, kind, values in entries:
            if len(values) * struct.calcsize(codes[kind]) > 4:       # the values out of line, before the directory
                arrays[tag] = len(out)
                out += struct.pack(f"{order}{len(values)}{codes[kind]}", *values)
        if len(out) % 2:
            out += b"\0"
        struct.pack_into(order + "I", out, link, len(out))
        out += struct.pack(order + "H", len(entries))
        for tag, kind, values in entries:
            if tag in arrays:
                field = struct.pack(order + "I", arrays[tag])
            else:
                field = struct.pack(f"{order}{len(values)}{codes[kind]}", *values).ljust(4, b"\0")
            out += struct.pack(order + "HHI", tag, kind, len(values)) + field
        link = len(out)
        out += b"\0\0\0\0"
    with open(path, "wb") as fh:
        fh.write(bytes(out))
    return path


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("shape", [(23, 37), (1, 1), (64, 3), (300, 257)])
def test_opencvs_own_uncompressed_tiffs(tmp_path, dtype, shape):
    data = _frame(dtype, shape)
    path = str(tmp_path / "cv.tif")
    assert cv2.imwrite(path, data, [cv2.IMWRITE_TIFF_COMPRESSION, 1])
    got = tifffast.read_image(path)
    assert got is not None
    pixels, bits = got
    assert bits == 8 * np.dtype(dtype).itemsize and pixels.dtype == dtype and pixels.dtype.isnative
    assert np.array_equal(pixels, _opencv(path)) and np.array_equal(pixels, data)


@pytest.mark.parametrize("order", ["<", ">"])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("layout", [dict(), dict(rows_per_strip=5), dict(rows_per_strip=4, reverse_strips=True),
                                    dict(rows_per_strip=7, offsets_type=3), dict(pages=3),
                                    dict(extra=[(284, 3, 1), (339, 3, 1), (266, 3, 1), (274, 3, 1)])])
def test_hand_made_layouts_are_opencvs(tmp_path, order, dtype, layout):
    """Either byte order; strips of any rows (the last one short), out of order in the file, with SHORT offsets; the
    first of several pages; the baseline values written out."""
    data = _frame(dtype, (23, 37), seed=len(layout))
    path = _tiff(str(tmp_path / "h.tif"), data, order=order, **layout)
    want = _opencv(path)
    assert want is not None and np.array_equal(want, data)
    pixels, bits = tifffast.read_image(path)
    assert pixels.dtype.isnative and pixels.dtype == want.dtype and np.array_equal(pixels, want)


def test_other_tiffs_go_to_opencv(tmp_path):
    """None for what this reader does not follow: OpenCV decodes it (or names what is wrong)."""
    grey = _frame(np.uint16)
    cases = {
        "lzw": lambda p: cv2.imwrite(p, grey),          # OpenCV's default compression
        "colour": lambda p: cv2.imwrite(p, np.dstack([grey] * 3), [cv2.IMWRITE_TIFF_COMPRESSION, 1]),
        "float": lambda p: cv2.imwrite(p, grey.astype(np.float32), [cv2.IMWRITE_TIFF_COMPRESSION, 1]),
        "white-is-zero": lambda p: _tiff(p, grey, photometric=0),
        "signed": lambda p: _tiff(p, grey, extra=[(339, 3, 2)]),
        "planar": lambda p: _tiff(p, grey, extra=[(284, 3, 2)]),
        "extra-samples": lambda p: _tiff(p, grey, extra=[(338, 3, 0)]),
        "tiled": lambda p: _tiff(p, grey, extra=[(322, 3, 16)]),
        "turned": lambda p: _tiff(p, grey, extra=[(274, 3, 3)]),        # OpenCV turns it: its first row is the bottom
    }
    for name, write in cases.items():
        path = str(tmp_path / f"{name}.tif")
        write(path)
        assert tifffast.read_image(path) is None, name
        try:
            want = _read_cv2(path, 10**9)
        except BadInputError as exc:           # OpenCV's pixels that read_image refuses (signed): refused as before
            with pytest.raises(BadInputError, match=str(exc).split(":")[-1].strip()[:20]):
                read_image(path)
            continue
        assert np.array_equal(read_image(path)[0], want[0]), name


def test_a_strip_beyond_the_file_is_opencvs_to_refuse(tmp_path):
    """A directory whose strip runs past the end of the file (a file cut short, a broken writer): None here, and
    read_image's refusal is OpenCV's, as before."""
    path = _tiff(str(tmp_path / "cut.tif"), _frame(np.uint16, (40, 40)))
    whole = bytearray(open(path, "rb").read())
    at = struct.unpack_from("<I", whole, 4)[0]
    for k in range(struct.unpack_from("<H", whole, at)[0]):
        entry = at + 2 + 12 * k
        if struct.unpack_from("<H", whole, entry)[0] == 273:
            struct.pack_into("<I", whole, entry + 8, len(whole) - 100)      # the strip's last 3,100 bytes are missing
    with open(path, "wb") as fh:
        fh.write(bytes(whole))
    assert tifffast.read_image(path) is None
    got = _opencv(path)
    if got is None:
        with pytest.raises(BadInputError):
            read_image(path)
    else:       # OpenCV's libtiff may hand back what it read: read_image gives OpenCV's pixels, as before
        assert np.array_equal(read_image(path, whole_dn=True)[0], got)


def test_read_image_is_the_opencv_reads_answer(tmp_path):
    """read_image of a plain TIFF file: the same pixels, bit depth, channels and saturation as through OpenCV, as
    whole DN or float32."""
    for dtype in (np.uint8, np.uint16):
        path = _tiff(str(tmp_path / f"r{np.dtype(dtype).itemsize}.tif"), _frame(dtype), order=">",
                     rows_per_strip=6)
        for whole in (False, True):
            img, meta = read_image(path, whole_dn=whole)
            want = _read_cv2(path, 10**9, whole)
            assert img.dtype == want[0].dtype and np.array_equal(img, want[0])
            assert (meta["bit_depth"], meta["channels"], meta["saturation"]) == want[1:]


def test_the_esa_images_are_read_as_opencv_reads_them():
    names = sorted(n for n in os.listdir(REAL) if n.endswith(".tiff"))
    assert len(names) == 8, "tests/data/real holds the ESA images"
    for name in names:
        path = os.path.join(REAL, name)
        pixels, bits = tifffast.read_image(path)
        assert bits == 16 and np.array_equal(pixels, _opencv(path))


def test_a_plain_tiff_solve_process_does_not_import_cv2(tmp_path):
    """An ESA image (a plain 16-bit TIFF): read and solved without OpenCV's ~17 ms import."""
    path = os.path.join(REAL, "2019-07-29T204726_Alt40_Azi135_Try1.tiff")
    modules, doc = solve_in_a_process(path, tmp_path / "f.json", "--no-aberration")
    assert "cv2" not in modules
    assert doc["solve"]["status"] == "ok" and doc["image"]["bit_depth"] == 16


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_startracks_own_tiffs_are_plain(tmp_path, dtype):
    """write_image (render's frames) writes TIFF files not compressed: this module reads them, OpenCV's pixels."""
    from startrack.imageio import write_image

    data = _frame(dtype, (48, 64), seed=3)
    for name in ("a.tif", "b.TIFF"):
        path = str(tmp_path / name)
        write_image(path, data)
        pixels, bits = tifffast.read_image(path)
        assert np.array_equal(pixels, data) and np.array_equal(pixels, _opencv(path))
        assert os.path.getsize(path) >= data.nbytes


@pytest.mark.parametrize("mode", ["L", "I;16", "I;16B"])
def test_pillows_tiffs_are_opencvs(tmp_path, mode):
    """Another writer's plain TIFF files (Pillow: 8-bit, 16-bit in either byte order, its own strips): OpenCV's
    pixels; its compressed ones go to OpenCV."""
    from PIL import Image

    dtype = np.uint8 if mode == "L" else np.uint16
    data = _frame(dtype, (301, 517), seed=5)
    if mode == "I;16B":
        image = Image.frombuffer(mode, (517, 301), data.astype(">u2").tobytes(), "raw", mode, 0, 1)
    else:
        image = Image.fromarray(data)
    for compression in (None, "tiff_lzw", "packbits"):
        path = str(tmp_path / f"pil-{compression}.tif")
        image.save(path, compression=compression) if compression else image.save(path)
        got = tifffast.read_image(path)
        assert (got is None) == (compression is not None)
        assert np.array_equal(read_image(path, whole_dn=True)[0], data) and np.array_equal(_opencv(path), data)
        if got is not None:
            assert np.array_equal(got[0], data)


def test_nothing_larger_than_the_file_or_the_limit_is_allocated(tmp_path, monkeypatch):
    """A directory (after the pixels, beyond the header read that checks the size) that claims more pixels than the
    file holds, or more than the image size limit: None here, before any allocation; read_image then refuses the file
    as it did through OpenCV."""
    path = _tiff(str(tmp_path / "big.tif"), _frame(np.uint16, (200, 200)))
    whole = bytearray(open(path, "rb").read())
    at = struct.unpack_from("<I", whole, 4)[0]
    assert at > 1 << 16         # beyond the 64 KB header read: no size check before the decoders
    for k in range(struct.unpack_from("<H", whole, at)[0]):
        entry = at + 2 + 12 * k
        tag = struct.unpack_from("<H", whole, entry)[0]
        if tag in (256, 257):                          # 100,000 x 100,000 pixels: 20 GB of uint16
            struct.pack_into("<I", whole, entry + 8, 100_000)
        if tag in (278, 279):
            struct.pack_into("<I", whole, entry + 8, 100_000 if tag == 278 else 2 * 100_000 ** 2 % 2**32)
    with open(path, "wb") as fh:
        fh.write(bytes(whole))
    allocated = []
    real_empty = np.empty
    monkeypatch.setattr(np, "empty", lambda shape, *a, **k: allocated.append(shape) or real_empty(shape, *a, **k))
    assert tifffast.read_image(path) is None and not allocated
    monkeypatch.undo()
    with pytest.raises(BadInputError):
        read_image(path)
    small = _tiff(str(tmp_path / "small.tif"), _frame(np.uint16, (40, 40)))
    assert tifffast.read_image(small, max_pixels=1599) is None and tifffast.read_image(small, max_pixels=1600)
    with pytest.raises(BadInputError, match="more than the limit of 1599"):
        read_image(small, max_pixels=1599)
