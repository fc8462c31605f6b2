"""Every command line in README.md and in every `--help` runs, as written (issue 20).

The commands are extracted from the texts themselves, so an example that breaks
fails CI:

* `--help`: the indented lines under each "Example" heading of every command (and
  of `startrack --help`); the examples of one command run in order, in one fresh
  directory, so a later example may use what an earlier one made.
* README.md: every fenced ``sh`` block, in order, in one fresh directory (the
  ``python`` blocks run with this interpreter).  A block right after the comment
  ``<!-- not run by the tests: REASON -->`` is skipped, and counted.

Each block runs through ``bash`` with ``set -eo pipefail`` (a failing stage of a
pipe fails the block), with ``startrack`` on PATH resolving to this checkout.  A
comment line ``# -> TEXT`` claims output: every number in TEXT must be printed by
the commands before it (to the claim's decimals).  The directories hold the files
the texts name, prepared here: ``sky.tiff``/``cam.json`` (the ESA image and its
camera), ``a.tiff``/``b.tiff``, ``photos/`` and ``tests/data/real/`` (two ESA images, to keep the run
short), ``examples/data/``.  `jq` is needed by the examples that use it; without
it those blocks are skipped (and the reason says how many).

solve's cached databases and pattern index are shared by the tests (built once, or linked from the
user's cache): each test has its own ``STARTRACK_CACHE`` of links, so ``startrack cache clear``
never touches the user's cache.  ``STARTRACK_DOC_TIMES=FILE`` records each command's wall and CPU
seconds.
"""
import contextlib
import functools
import os
import re
import shutil
import subprocess
import sys

import pytest
from conftest import ROOT

SKIP_MARK = re.compile(r"<!--\s*not run by the tests:(.*?)-->", re.DOTALL)
CLAIM = re.compile(r"^\s*#\s*->\s*(.*)$")
NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?")


# ---------------------------------------------------------------------------------------------
# Extraction
# ---------------------------------------------------------------------------------------------

@functools.lru_cache(maxsize=None)
def help_text(*args):
    env = dict(os.environ, PYTHONPATH=ROOT, COLUMNS="100")
    return subprocess.run([sys.executable, "-m", "startrack", *args, "--help"], capture_output=True, text=True,
                          env=env, check=True).stdout


def help_examples(text):
    """The example blocks of one --help text: the indented lines under each 'Example' line."""
    blocks, current, indent = [], None, None
    for line in text.splitlines():
        stripped = line.strip()
        if re.match(r"^Examples?\b", stripped):
            if current:
                blocks.append("\n".join(current))
            current, indent = [], len(line) - len(line.lstrip()) + 1
            continue
        if current is None:
            continue
        if not stripped or len(line) - len(line.lstrip()) < indent:
            if current:
                blocks.append("\n".join(current))
            current = None
            continue
        current.append(line)
    if current:
        blocks.append("\n".join(current))
    return blocks


def readme_blocks(text):
    """(language, code, skip reason or None) of every fenced block of README.md."""
    out = []
    for m in re.finditer(r"```(\w*)\n(.*?)```", text, re.DOTALL):
        before = text[:m.start()].rstrip()
        skip = SKIP_MARK.search(before[-300:]) if before.endswith("-->") else None
        out.append((m.group(1), m.group(2), skip.group(1).strip() if skip else None))
    return out


def commands_in(block):
    """The startrack command lines of a shell block (continuations joined), for counting."""
    joined = re.sub(r"\\\n\s*", " ", block)
    n = 0
    for line in joined.splitlines():
        if line.strip().startswith("#"):
            continue
        n += len(re.findall(r"(?:^|[|;&(]\s*)startrack\s", line.strip()))
    return n


# ---------------------------------------------------------------------------------------------
# Running
# ---------------------------------------------------------------------------------------------

@pytest.fixture(scope="session")
def cache_seed(tmp_path_factory):
    """solve's cached databases and pattern index, shared by the tests of this module.

    Seeded with links to the files of the user's cache when there are any (else the first test that
    solves builds them, and the next ones reuse them); each test gets its own directory of links
    (:func:`_test_cache`), so `startrack cache clear` clears that, never the user's cache.
    """
    seed = tmp_path_factory.mktemp("cache-seed")
    from startrack.solve import cache_dir

    user = cache_dir()
    for name in os.listdir(user):
        src = os.path.join(user, name)
        if os.path.isfile(src) and not name.endswith(".lock") and ".part" not in name:
            os.symlink(src, seed / name)
    return seed


@contextlib.contextmanager
def _test_cache(seed, tmp_path):
    """A cache directory for one test: links to the seed's files; what the test builds goes to the seed after it."""
    d = tmp_path / "cache"
    d.mkdir()
    for name in os.listdir(seed):
        os.symlink(os.path.realpath(seed / name), d / name)
    try:
        yield d
    finally:
        for name in os.listdir(d):
            p = d / name
            if p.is_file() and not p.is_symlink() and not name.endswith(".lock") and not (seed / name).exists():
                shutil.move(str(p), seed / name)


def _workdir(tmp_path, cache=None):
    """A directory with the files the texts name, and a PATH whose `startrack` is this checkout."""
    bindir = tmp_path / "bin"
    bindir.mkdir()
    wrapper = bindir / "startrack"
    times = os.environ.get("STARTRACK_DOC_TIMES")
    if times and shutil.which("time") == "/usr/bin/time":
        # Each command's wall and CPU seconds appended to that file (GNU time), to see where the time goes.
        wrapper.write_text(f'#!/bin/sh\nexec /usr/bin/time -a -o "{times}" -f "%e s wall %U+%S s cpu: %C" '
                           f'"{sys.executable}" -m startrack "$@"\n')
    else:
        wrapper.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m startrack "$@"\n')
    wrapper.chmod(0o755)
    if shutil.which("jq") is None:
        # The jq wheel (the test extra) stands in for the jq program.
        shim = bindir / "jq"
        shim.write_text(f'#!/bin/sh\nexec "{sys.executable}" "{os.path.join(ROOT, "tests", "jq_shim.py")}" "$@"\n')
        shim.chmod(0o755)
    work = tmp_path / "work"
    (work / "photos").mkdir(parents=True)
    (work / "tests" / "data" / "real").mkdir(parents=True)
    (work / "examples").mkdir()
    os.symlink(os.path.join(ROOT, "examples", "data"), work / "examples" / "data")
    shutil.copy(os.path.join(ROOT, "examples", "data", "sky.tiff"), work / "sky.tiff")
    shutil.copy(os.path.join(ROOT, "examples", "data", "camera.json"), work / "cam.json")
    real = os.path.join(ROOT, "tests", "data", "real")
    photos = sorted(f for f in os.listdir(real) if f.endswith(".tiff"))[:2]
    for f, alias in zip(photos, ("a.tiff", "b.tiff"), strict=True):
        os.symlink(os.path.join(real, f), work / alias)
        os.symlink(os.path.join(real, f), work / "photos" / f)
        os.symlink(os.path.join(real, f), work / "tests" / "data" / "real" / f)
    shutil.copy(os.path.join(real, "camera.json"), work / "tests" / "data" / "real" / "camera.json")
    env = dict(os.environ, PATH=f"{bindir}{os.pathsep}{os.environ.get('PATH', '')}", PYTHONPATH=ROOT)
    env.pop("STARTRACK_DEBUG", None)
    if cache is not None:
        env["STARTRACK_CACHE"] = str(cache)
    return work, env


def check_claims(block, printed):
    """Every number of every `# -> ...` line must have been printed (to the claim's decimals)."""
    got = [float(v) for v in NUMBER.findall(printed)]
    for line in block.splitlines():
        m = CLAIM.match(line)
        if not m:
            continue
        for text in NUMBER.findall(m.group(1)):
            want = float(text)
            decimals = len(text.split(".")[1]) if "." in text else 0
            tol = 0.5 * 10 ** -decimals + 1e-9
            assert any(abs(v - want) <= tol for v in got), f"claimed {text} ({m.group(1)!r}) not in output:\n{printed}"


def run_block(block, work, env, language="sh"):
    if language == "python":
        proc = subprocess.run([sys.executable, "-c", block], cwd=work, env=env, capture_output=True, text=True,
                              timeout=900)
    else:
        script = "set -eo pipefail\n" + block
        proc = subprocess.run(["bash", "-c", script], cwd=work, env=env, capture_output=True, text=True, check=False,
                              timeout=900)
    assert proc.returncode == 0, f"exit {proc.returncode} running:\n{block}\n--- stderr:\n{proc.stderr[-3000:]}"
    if language != "python":
        check_claims(block, proc.stdout)
    return proc


def _commands():
    from startrack.cli.main import COMMANDS

    return [""] + list(COMMANDS)




@pytest.mark.parametrize("name", _commands())
def test_help_examples_run(name, tmp_path, cache_seed):
    """`startrack NAME --help`: each example runs as written (exit status 0, printed claims hold)."""
    text = help_text(*([name] if name else []))
    blocks = help_examples(text)
    assert blocks, f"startrack {name} --help has no example"
    assert all(commands_in(b) for b in blocks), blocks
    with _test_cache(cache_seed, tmp_path) as cache:
        work, env = _workdir(tmp_path, cache)
        for block in blocks:
            run_block(block, work, env)


def test_readme_commands_run(tmp_path, cache_seed):
    with open(os.path.join(ROOT, "README.md"), encoding="utf-8") as fh:
        blocks = readme_blocks(fh.read())
    runnable = [(lang, code) for lang, code, skip in blocks if skip is None and lang in ("sh", "bash", "python")]
    skipped = [(lang, skip) for lang, code, skip in blocks if skip is not None]
    assert len(runnable) >= 4 and all(reason for _, reason in skipped)
    with _test_cache(cache_seed, tmp_path) as cache:
        work, env = _workdir(tmp_path, cache)
        for lang, code in runnable:
            run_block(code, work, env, "python" if lang == "python" else "sh")


# ---------------------------------------------------------------------------------------------
# The test can fail: the extraction finds the commands, and a broken example or claim is caught
# ---------------------------------------------------------------------------------------------

def test_extraction_and_failure_detection(tmp_path):
    text = ("Usage: x\n\n  Example (one):\n    startrack a --b 1 \\\n        | startrack c\n  \n"
            "  Example (two):\n    startrack d\n\nOptions:\n  --x\n")
    assert help_examples(text) == ["    startrack a --b 1 \\\n        | startrack c", "    startrack d"]
    assert commands_in(help_examples(text)[0]) == 2
    md = "a\n<!-- not run by the tests: it runs the suite -->\n```sh\nmake test\n```\n```sh\nstartrack x\n```\n"
    assert readme_blocks(md) == [("sh", "make test\n", "it runs the suite"), ("sh", "startrack x\n", None)]
    work, env = _workdir(tmp_path)
    with pytest.raises(AssertionError, match="exit 2"):
        run_block("startrack solve sky.tiff --fov-deg nan", work, env)
    with pytest.raises(AssertionError, match="exit 1"):
        run_block("startrack catalog-filter --mag-max 1 | false\n", work, env)
    with pytest.raises(AssertionError, match="claimed 3.15"):
        run_block("echo 3.14159\n# -> pi is 3.15\n", work, env)
    run_block("echo 3.14159\n# -> pi is 3.14\n", work, env)


def test_count_of_documented_commands():
    """The suite runs every startrack command line of README.md and of every --help (printed for the record)."""
    n_help = sum(commands_in(b) for name in _commands() for b in help_examples(help_text(*([name] if name else []))))
    with open(os.path.join(ROOT, "README.md"), encoding="utf-8") as fh:
        blocks = readme_blocks(fh.read())
    n_readme = sum(commands_in(code) for lang, code, skip in blocks if skip is None and lang != "python")
    n_python = sum(1 for lang, code, skip in blocks if skip is None and lang == "python")
    print(f"documented commands run: {n_help} in --help texts, {n_readme} in README.md sh blocks, "
          f"{n_python} README python block(s)")
    assert n_help >= 25 and n_readme >= 10


@pytest.mark.skipif(shutil.which("jq") is None, reason="compares the stand-in with the jq program")
@pytest.mark.parametrize("args", [["-c", ".a"], [".b"], ["-c", "[.a, .b.c]"], ["-r", ".s"], ["-c", "(.a * 2)"]])
def test_jq_stand_in_prints_what_jq_prints(args):
    """Where jq is installed (CI installs it), the stand-in used without it prints the same bytes."""
    text = '{"a": 1.5, "b": {"c": [1, 2]}, "s": "x y"}\n{"a": -3, "b": {"c": null}, "s": "z"}\n'
    real = subprocess.run(["jq", *args], input=text, capture_output=True, text=True, check=True).stdout
    shim = subprocess.run([sys.executable, os.path.join(ROOT, "tests", "jq_shim.py"), *args], input=text,
                          capture_output=True, text=True, check=True).stdout
    assert shim == real
