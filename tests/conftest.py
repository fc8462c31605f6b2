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
