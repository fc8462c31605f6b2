import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DATA = os.path.join(ROOT, "tests", "data")


def run_cli(*args, input=None, check=False, env=None, timeout=300):
    """Run the real ``startrack`` entry point in a subprocess."""
    full_env = dict(os.environ)
    full_env.pop("STARTRACK_DEBUG", None)
    if env:
        full_env.update(env)
    proc = subprocess.run([sys.executable, "-m", "startrack", *map(str, args)], input=input,
                          capture_output=True, text=True, env=full_env, timeout=timeout)
    if check and proc.returncode != 0:
        raise AssertionError(f"startrack {' '.join(map(str, args))} failed ({proc.returncode}):\n{proc.stderr}")
    return proc


def assert_refused(proc, *needles, stdout_empty=True):
    """Exit status 2, one line on stderr containing every needle, no traceback, nothing on stdout."""
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    lines = [l for l in proc.stderr.splitlines() if l.strip()]
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    for n in needles:
        assert n in lines[0], lines[0]
    if stdout_empty:
        assert proc.stdout == ""


@pytest.fixture(scope="session")
def solve_cache(tmp_path_factory):
    """One STARTRACK_CACHE for every test that runs `solve` (its databases are built once per session)."""
    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        # Shared by the workers of one run: databases are built once, under solve's build lock.
        path = base.parent / "solve-cache"
        path.mkdir(exist_ok=True)
        return {"STARTRACK_CACHE": str(path)}
    return {"STARTRACK_CACHE": str(tmp_path_factory.mktemp("solve-cache"))}


@pytest.fixture
def cli():
    return run_cli


@pytest.fixture(scope="session")
def catalog():
    from startrack.catalog import load_catalog

    return load_catalog()


def kvector_sensor(catalog, fov_deg, width, height, db_mag, star_mag):
    """``(camera, k-vector database to ``db_mag`` merged for the camera, catalog stars to ``star_mag``)``."""
    from startrack.camera import Camera
    from startrack.catalog import merge_radius_arcsec
    from startrack.kvector import build_kvector, max_separation_deg

    cam = Camera.from_fov(fov_deg, width, height)
    db = build_kvector(catalog.filter_magnitude(None, db_mag).merge_close(merge_radius_arcsec(cam)),
                       max_separation_deg(camera=cam))
    return cam, db, catalog.filter_magnitude(None, star_mag)


@pytest.fixture(scope="session")
def sensor15(catalog):
    """Issue 14's 15 deg 1280x960 sensor: database Hp <= 6 merged for it, stars to 5.5."""
    return kvector_sensor(catalog, 15, 1280, 960, 6.0, 5.5)


def png_pixels(path):
    """The BGR pixels of a PNG (uint8, rows x columns x 3)."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, f"{path} is not a readable PNG"
    return img


def colour_fraction(pixels, bgr, tol=40):
    """Fraction of ``pixels`` (any shape ending in 3) within ``tol`` of colour ``bgr`` on every channel."""
    import numpy as np

    px = np.asarray(pixels, dtype=np.int32).reshape(-1, 3)
    return float(np.mean(np.all(np.abs(px - np.asarray(bgr)) <= tol, axis=1)))


def ring(pixels, x, y, radius, n=72):
    """The pixels on a circle of ``radius`` px around image position ``(x, y)`` (x = column, y = row)."""
    import numpy as np

    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    cols = np.clip(np.round(x + radius * np.cos(t)).astype(int), 0, pixels.shape[1] - 1)
    rows = np.clip(np.round(y + radius * np.sin(t)).astype(int), 0, pixels.shape[0] - 1)
    return pixels[rows, cols]


def assert_identified_star_marked(png, doc):
    """The picture of a solved frame circles its first identified star in the "identified" colour
    (``plot.annotate_solution``), and does not paint that colour just anywhere."""
    from startrack.plot import MARKERS, _radius

    px = png_pixels(png)
    colour = MARKERS["identified"][0]
    scale = max(0.8, min(2.5, max(doc["image"]["width"], doc["image"]["height"]) / 1024.0))
    star = doc["stars"][doc["identification"]["matches"][0]["star"]]
    radius = int(round(_radius(star.get("flux")) * scale))
    on = max(colour_fraction(ring(px, star["x"], star["y"], r), colour, tol=60) for r in (radius - 1, radius, radius + 1))
    assert on > 0.5, on
    # ... and only there: twice as far out the ring is not the marker.
    assert colour_fraction(ring(px, star["x"], star["y"], 2 * radius + 4), colour, tol=60) < 0.5


# matplotlib's first colours (tab:blue, tab:orange, tab:green) in BGR
CHART_COLOURS = ((180, 119, 31), (14, 127, 255), (44, 160, 44))


def assert_chart_draws(png, colours, min_fraction=2e-4):
    """A matplotlib chart whose lines or points of each given colour cover some of the picture."""
    px = png_pixels(png)
    for bgr in colours:
        assert colour_fraction(px, bgr, tol=30) > min_fraction, (png, bgr)


def star_field(shape, n_stars, seed, sigma=1.3, margin=3, log_flux=(2.5, 4.5), clip=None):
    """``n_stars`` Gaussian stars (flux 10**U(log_flux)) at least ``margin`` px inside a frame of ``shape`` on a sloped
    background with noise 4 (float64); ``clip``: every pixel above it set to it."""
    import numpy as np

    rng = np.random.default_rng(seed)
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    img = 200.0 + 0.05 * xx + 0.03 * yy + rng.normal(0.0, 4.0, shape)
    for x0, y0, f in zip(rng.uniform(margin, w - margin, n_stars), rng.uniform(margin, h - margin, n_stars),
                         10 ** rng.uniform(*log_flux, n_stars)):
        img += f / (2 * np.pi * sigma**2) * np.exp(-((xx - x0) ** 2 + (yy - y0) ** 2) / (2 * sigma**2))
    return img if clip is None else np.minimum(img, clip)


def assert_same_record(got, want):
    """Two records of one dataclass field by field: the same types, arrays with the same dtype, shape and bytes,
    other values equal and written alike as JSON."""
    import dataclasses
    import json

    import numpy as np

    for f in dataclasses.fields(want):
        x, y = getattr(got, f.name), getattr(want, f.name)
        assert type(x) is type(y), f.name
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), f.name
        else:
            assert x == y and json.dumps(x, default=str) == json.dumps(y, default=str), f.name



def solve_in_a_process(path, out, *args):
    """``startrack solve PATH -q -o OUT ARGS`` in a fresh interpreter: ``(the modules it imported, the frame
    document)`` (exit status 0 asserted), for the tests that a solve imports no more than it needs."""
    import json
    import subprocess
    import sys

    code = ("import sys, json; from startrack.cli.main import main\n"
            "try:\n    main(['solve', sys.argv[1], '-q', '-o', sys.argv[2], *sys.argv[3:]])\n"
            "except SystemExit as e:\n    assert e.code in (0, None), e.code\n"
            "print(json.dumps(sorted(sys.modules)))")
    proc = subprocess.run([sys.executable, "-c", code, str(path), str(out), *args], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    with open(out) as fh:
        return set(json.loads(proc.stdout.splitlines()[-1])), json.loads(fh.read())
