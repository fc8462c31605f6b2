"""Fuzz (issue 17): frame documents, image headers and option values never give an internal error or a
traceback; exit status 0/1/2 means all ok / some frame failed / some input bad."""
import json
import math
import struct
import zlib

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import run_cli
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from startrack.errors import BadInputError
from startrack.formats.frame import MAX_JSON_DEPTH, read_frames, validate_frame

FRAME_CASES = 300
IMAGE_CASES = 150
STREAM_CASES = 4
OPTION_CASES = 40

json_scalars = st.one_of(st.none(), st.booleans(), st.integers(-10**12, 10**12),
                         st.floats(allow_nan=False, allow_infinity=False), st.text(max_size=8))
json_values = st.recursive(json_scalars, lambda inner: st.one_of(
    st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=6), inner, max_size=4)), max_leaves=20)

GOOD = {"format": "startrack.frame/1", "image": {"width": 1024, "height": 1024},
        "camera": {"width": 1024, "height": 1024, "focal_length_px": 2903.7, "cx": 511.5, "cy": 511.5},
        "stars": [{"x": 100.0 + 37 * i, "y": 200.0 + 23 * i, "flux": 1000.0 - i} for i in range(6)],
        "identification": {"status": "ok", "algorithm": "x", "matches": [{"star": 0, "id": 32349},
                                                                          {"star": 1, "id": 30438}]}}
FIELDS = [("format",), ("camera",), ("camera", "focal_length_px"), ("stars",), ("stars", 0), ("stars", 0, "x"),
          ("identification",), ("identification", "matches"), ("identification", "matches", 0, "id"),
          ("identification", "matches", 0, "star"), ("identification", "status"), ("image", "width")]


@st.composite
def mutated_frames(draw):
    """A good frame with a few fields replaced by arbitrary JSON (or deleted)."""
    doc = json.loads(json.dumps(GOOD))
    for _ in range(draw(st.integers(0, 3))):
        path = draw(st.sampled_from(FIELDS))
        node = doc
        for key in path[:-1]:
            node = node[key] if isinstance(node, dict) and key in node or isinstance(node, list) and (
                isinstance(key, int) and key < len(node)) else None
            if node is None:
                break
        if node is None or not isinstance(node, (dict, list)):
            continue
        if isinstance(node, dict) and draw(st.booleans()) and path[-1] in node:
            del node[path[-1]]
        elif isinstance(node, dict) or (isinstance(path[-1], int) and path[-1] < len(node)):
            node[path[-1]] = draw(json_values)
    return doc


lines = st.one_of(mutated_frames().map(json.dumps), json_values.map(json.dumps),
                  st.text(max_size=30).filter(lambda t: "\n" not in t and "\r" not in t),
                  st.integers(1, 3000).map(lambda n: "[" * n + "]" * n))


@settings(max_examples=FRAME_CASES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(lines, min_size=1, max_size=5))
def test_reading_and_validating_frames_only_ever_refuses(tmp_path_factory, text_lines):
    path = tmp_path_factory.mktemp("f") / "frames.jsonl"
    path.write_text("\n".join(text_lines) + "\n")
    for rec in read_frames(str(path)):
        if rec.error is not None:
            assert isinstance(rec.error, BadInputError) and "\n" not in str(rec.error)
            continue
        try:
            validate_frame(rec.doc, rec.source, ("stars", "camera", "identification"))
        except BadInputError as exc:
            assert "\n" not in str(exc) and rec.source in str(exc)


def _png(width, height, bit_depth, colour_type, body):
    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, bit_depth, colour_type, 0, 0,
                                                              0))
            + chunk(b"IDAT", zlib.compress(body)) + chunk(b"IEND", b""))


@settings(max_examples=IMAGE_CASES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(width=st.one_of(st.integers(0, 64), st.integers(0, 2**31 - 1)),
       height=st.one_of(st.integers(0, 64), st.integers(0, 2**31 - 1)),
       bit_depth=st.sampled_from([1, 2, 4, 8, 16, 3, 0]), colour_type=st.sampled_from([0, 2, 3, 4, 6, 5]),
       body=st.binary(max_size=2000), cut=st.integers(0, 200))
def test_image_headers_are_read_or_refused_in_one_line(tmp_path_factory, width, height, bit_depth, colour_type,
                                                       body, cut):
    from startrack.imageio import read_image

    data = _png(width, height, bit_depth, colour_type, body)
    if cut:
        data = data[:-cut]
    path = tmp_path_factory.mktemp("img") / "fuzz.png"
    path.write_bytes(data)
    limit = 10_000
    try:
        image, info = read_image(str(path), max_pixels=limit)
    except BadInputError as exc:
        assert "\n" not in str(exc) and "fuzz.png" in str(exc)
        return
    assert image.ndim == 2 and image.dtype == np.float32 and image.size <= limit
    assert info["bit_depth"] in (8, 16, 32) and info["saturation"] in (255.0, 65535.0) or info["bit_depth"] == 32


def _is_json(text):
    """A JSON value on its own that a frame reader takes (NaN and Infinity are not JSON; nesting at most
    MAX_JSON_DEPTH levels)."""
    def refuse(name):
        raise ValueError(name)
    try:
        value = json.loads(text, parse_constant=refuse)
    except (ValueError, RecursionError):
        return False
    stack = [(value, 1)]
    while stack:
        item, depth = stack.pop()
        if depth > MAX_JSON_DEPTH:
            return False
        if isinstance(item, (list, dict)):
            stack.extend((v, depth + 1) for v in (item.values() if isinstance(item, dict) else item)
                         if isinstance(v, (list, dict)))
    return True


def _expected_exit(docs, section):
    bad = any(d.get(section, {}).get("bad_input") for d in docs)
    failed = any(d.get(section, {}).get("status") == "failed" for d in docs)
    return 2 if bad else 1 if failed else 0


@settings(max_examples=STREAM_CASES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(lines, min_size=2, max_size=8))
def test_attitude_on_fuzzed_streams_is_honest(text_lines):
    """Many documents in one stream: one line out per line in, exit status from the statuses, no traceback."""
    text_lines = [line for line in text_lines if line.strip()]
    if len(text_lines) < 2:
        text_lines += [json.dumps(GOOD)] * 2
    proc = run_cli("attitude", input="\n".join(text_lines) + "\n")
    assert "Traceback" not in proc.stderr and "internal error" not in proc.stderr, proc.stderr
    docs = [json.loads(line) for line in proc.stdout.splitlines()]
    if not _is_json(text_lines[0]):
        if _is_json("\n".join(text_lines)):
            return                      # one (pretty-printed) document or array, not JSON Lines
        if not any(_is_json(line) for line in text_lines[1:]):
            # Neither JSON Lines nor one document (formats.md): the stream is unreadable.
            assert proc.returncode == 2 and docs == [] and len(proc.stderr.splitlines()) == 1, proc.stderr
            return
    assert len(docs) == len(text_lines)
    assert proc.returncode == _expected_exit(docs, "attitude"), (proc.returncode, proc.stderr)
    assert all(d["attitude"]["status"] in ("ok", "failed") for d in docs)
    for line in proc.stderr.splitlines():
        assert line.startswith(("startrack attitude:", "attitude:")), line


numbers = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-5, 5),
                    st.sampled_from([0, -1, 1e-300, 1e300, 1000000000]))


@settings(max_examples=OPTION_CASES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(fov=numbers, size=st.one_of(st.sampled_from(["64x48", "0x10", "60000x60000", "axb", "10", "-5x5",
                                                    "100000x1"]), st.text(max_size=8)),
       count=st.integers(-2, 3), false_stars=st.one_of(st.integers(-3, 5), st.just(1000000000)),
       sigma=numbers)
def test_render_options_are_used_or_refused_in_one_line(fov, size, count, false_stars, sigma):
    from startrack.cli.main import cli

    args = ["render", "--stars-only", "--fov-deg", repr(float(fov)), "--size", size, "--count", str(count),
            "--false-stars", str(false_stars), "--sigma-px", repr(float(sigma)), "--seed", "1", "-q"]
    result = CliRunner().invoke(cli, args)
    out = result.output
    assert result.exit_code in (0, 2), (args, result.exit_code, out)
    assert "Traceback" not in out and "internal error" not in out, (args, out)
    if result.exit_code == 0:
        docs = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
        assert len(docs) == count and math.isfinite(fov) and fov > 0
    else:
        assert isinstance(result.exception, SystemExit)


def test_attitude_refuses_a_match_without_an_id_in_one_line():
    """Found by the stream fuzzer: a match without ``id`` was an internal error (KeyError)."""
    bad = json.loads(json.dumps(GOOD))
    bad["identification"] = {"status": "ok", "algorithm": "x", "matches": [{"star": 0}, {"star": 1, "id": 30438}]}
    proc = run_cli("attitude", input=json.dumps(GOOD) + "\n" + json.dumps(bad) + "\n")
    assert proc.returncode == 2, proc.stderr
    assert "<stdin>:2: identification.matches[0].id: must be an integer catalog id" in proc.stderr, proc.stderr
    assert "internal error" not in proc.stderr, proc.stderr
    docs = [json.loads(line) for line in proc.stdout.splitlines()]
    assert len(docs) == 2 and docs[1]["attitude"]["bad_input"] is True


def test_attitude_on_a_stream_of_no_json_is_one_error():
    """Found by the stream fuzzer: lines none of which is JSON are not JSON Lines: one error line, exit 2."""
    proc = run_cli("attitude", input="00\n00\n")
    assert proc.returncode == 2 and proc.stdout == "" and len(proc.stderr.splitlines()) == 1, proc.stderr


@pytest.mark.parametrize("memfd", [True, False])
def test_captured_stderr_catches_what_c_libraries_print(memfd, monkeypatch, capfd):
    """What is written to file descriptor 2 inside `captured_stderr` (as OpenCV's and libtiff's C code does) is
    caught, its first line without OpenCV's log prefix, and fd 2 is the terminal's again afterwards; in memory
    (memfd_create) or, without it, through a temporary file."""
    import os
    import sys

    from startrack.imageio import _scratch_file, captured_stderr

    if not memfd:
        monkeypatch.delattr(os, "memfd_create", raising=False)
    with _scratch_file() as scratch:
        # in memory where the system has memfd_create (every Linux this runs on), else a temporary file
        in_memory = os.readlink(f"/proc/self/fd/{scratch.fileno()}").startswith("/memfd:") \
            if sys.platform.startswith("linux") else False
    assert in_memory == (memfd and sys.platform.startswith("linux"))
    with captured_stderr() as cap:
        os.write(2, b"[ WARN:0@0.012] global grfmt_tiff.cpp:123 TIFFReadDirectory: Unknown field\nsecond line\n")
    assert cap.text.startswith("[ WARN:0@0.012]") and cap.text.endswith("second line\n")
    assert cap.first_line == "TIFFReadDirectory: Unknown field"
    os.write(2, b"after\n")
    assert capfd.readouterr().err == "after\n"
