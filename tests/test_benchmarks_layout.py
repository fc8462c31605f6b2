"""benchmarks/ as a tool (issue 42): no import circle, every script says what it feeds, indexes and links hold.

Fast: nothing here runs a benchmark; the scripts are parsed, and imported once in a subprocess.
"""
from __future__ import annotations

import ast
import glob
import os
import re
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BENCH = os.path.join(ROOT, "benchmarks")
DIRS = [BENCH, os.path.join(BENCH, "studies"), os.path.join(BENCH, "peers")]
# What a script's first line must say: the figure it feeds, or that it is a study kept for what it showed.
SAYS = re.compile(r"\bfeeds\b|must-show|\bstudy\b|kept for the record", re.IGNORECASE)


def _modules():
    """``{module name: path}`` of every Python file of benchmarks/, benchmarks/studies/ and benchmarks/peers/."""
    out = {}
    for d in DIRS:
        for path in sorted(glob.glob(os.path.join(d, "*.py"))):
            name = os.path.splitext(os.path.basename(path))[0]
            if name == "__init__":
                continue
            assert name not in out, f"two benchmark modules named {name}: {out[name]} and {path}"
            out[name] = path
    return out


def _scripts():
    """The scripts whose first line must say what they feed: benchmarks/*.py|sh and benchmarks/studies/*.py."""
    paths = glob.glob(os.path.join(BENCH, "*.py")) + glob.glob(os.path.join(BENCH, "*.sh"))
    return sorted(paths + glob.glob(os.path.join(BENCH, "studies", "*.py")))


def _first_line(path):
    """The first line of a Python file's module docstring, or a shell script's first comment after the shebang."""
    with open(path, encoding="utf-8") as fh:
        text = fh.read()
    if path.endswith(".py"):
        doc = ast.get_docstring(ast.parse(text))
        return doc.strip().splitlines()[0] if doc else ""
    for line in text.splitlines():
        if line.startswith("#!") or not line.strip():
            continue
        return line.lstrip("# ").strip() if line.startswith("#") else ""
    return ""


def _imports(path, names):
    """The benchmark modules ``path`` imports (at any depth: a function-level import makes a circle too)."""
    with open(path, encoding="utf-8") as fh:
        tree = ast.parse(fh.read())
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(a.name.split(".")[-1] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            parts = node.module.split(".")
            found.add(parts[-1])
            if parts[:2] in (["benchmarks", "peers"], ["benchmarks", "studies"]) or parts == ["benchmarks"]:
                found.update(a.name for a in node.names)
    return found & set(names)


def _cycle(graph):
    """One import circle of ``graph`` (a list of module names, first == last), or None."""
    state, stack = {}, []

    def visit(n):
        state[n] = "open"
        stack.append(n)
        for m in sorted(graph[n]):
            if state.get(m) == "open":
                return stack[stack.index(m):] + [m]
            if m not in state:
                found = visit(m)
                if found:
                    return found
        stack.pop()
        state[n] = "done"
        return None

    for n in sorted(graph):
        if n not in state:
            found = visit(n)
            if found:
                return found
    return None


def test_cycle_finder_finds_a_circle():
    # the oracle of the next test: it must see a circle through a function-level import, as run <-> track_bench was
    assert _cycle({"run": {"track_bench"}, "track_bench": {"common", "run"}, "common": set()}) == \
        ["run", "track_bench", "run"]
    assert _cycle({"run": {"track_bench", "common"}, "track_bench": {"common"}, "common": set()}) is None


def test_no_import_circle():
    mods = _modules()
    graph = {name: _imports(path, mods) - {name} for name, path in mods.items()}
    assert _cycle(graph) is None, f"import circle among benchmarks/: {' -> '.join(_cycle(graph))}"
    assert not graph.get("common", {"(no common.py)"}), f"common.py must import no benchmark module: {graph.get('common')}"


def test_every_module_imports_without_running():
    """Each benchmark module imports cleanly and importing it runs nothing (prints nothing)."""
    mods = _modules()
    code = ("import importlib, sys\n"
            f"sys.path[:0] = {DIRS!r}\n"
            f"for name in {sorted(mods)!r}:\n"
            "    importlib.import_module(name)\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env,
                          cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout == "", f"importing the benchmark modules printed (a script runs at import): {proc.stdout[:500]}"


@pytest.mark.parametrize("path", _scripts(), ids=lambda p: os.path.relpath(p, BENCH))
def test_first_line_says_what_it_feeds(path):
    line = _first_line(path)
    assert SAYS.search(line), (f"{os.path.relpath(path, ROOT)}: the first line must say which README or results figure "
                               f"it feeds ('Feeds ...', '... must-show ...') or that it is a study; it is {line!r}")
    if os.path.dirname(path).endswith("studies"):
        assert re.search(r"\bstudy\b|kept for the record", line, re.IGNORECASE), line
    for name in re.findall(r"results/[\w.-]+\.md", line):
        assert os.path.exists(os.path.join(BENCH, name)), f"{os.path.relpath(path, ROOT)} names {name}, not there"


def _md_links(path):
    with open(path, encoding="utf-8") as fh:
        text = fh.read()
    return set(re.findall(r"\]\(([^)#\s]+)", text)) | set(re.findall(r"`([\w./-]+\.(?:md|py|sh))`", text))


def test_results_index_lists_every_results_file():
    results = os.path.join(BENCH, "results")
    index = os.path.join(results, "README.md")
    links = _md_links(index)
    files = {os.path.basename(p) for p in glob.glob(os.path.join(results, "*.md"))} - {"README.md"}
    assert files, "no results files"
    assert not files - links, f"results files missing from results/README.md: {sorted(files - links)}"
    for link in links:
        if link.startswith("results-"):
            assert os.path.exists(os.path.join(results, link)), f"results/README.md links {link}, not there"


def test_studies_index_lists_every_study():
    studies = os.path.join(BENCH, "studies")
    links = _md_links(os.path.join(studies, "README.md"))
    files = {os.path.basename(p) for p in glob.glob(os.path.join(studies, "*.py"))}
    assert not files - links, f"studies missing from studies/README.md: {sorted(files - links)}"


def _texts():
    """The files whose mentions of benchmarks/... must resolve: README, docs, catalogs' README, benchmarks' own
    Markdown (results included) and scripts, the package's docstrings, the tests."""
    pats = ["README.md", "docs/*.md", "catalogs/README.md", "benchmarks/**/*.md", "benchmarks/**/*.py",
            "benchmarks/**/*.sh", "startrack/**/*.py", "tests/**/*.py"]
    out = []
    for p in pats:
        out += glob.glob(os.path.join(ROOT, p), recursive=True)
    return sorted(set(out))


def test_every_mention_of_a_benchmark_file_exists():
    missing = []
    for path in _texts():
        with open(path, encoding="utf-8") as fh:
            text = fh.read()
        # (a path after "COMMIT:" names a file of git history, as the indexes do for removed results)
        for name in set(re.findall(r"(?<![\w:/])benchmarks/[\w./-]*\w\.(?:py|sh|md)\b", text)):
            if not os.path.exists(os.path.join(ROOT, name)):
                missing.append(f"{os.path.relpath(path, ROOT)}: {name}")
        if not os.path.relpath(path, ROOT).startswith(("benchmarks/results/", "tests/")):
            # a results file named alone (README, docs, indexes) is one of results/
            for name in set(re.findall(r"(?<![\w:/-])(results-[\w.-]+\.md)", text)):
                if not os.path.exists(os.path.join(BENCH, "results", name)):
                    missing.append(f"{os.path.relpath(path, ROOT)}: {name}")
    assert not missing, "named but not there:\n" + "\n".join(sorted(missing))


def test_run_lists_its_sections():
    proc = subprocess.run([sys.executable, os.path.join(BENCH, "run.py"), "--list"], capture_output=True, text=True,
                          timeout=120, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    names = [line.split()[0] for line in lines]
    for section in ("render", "centroid", "databases", "identify", "identify-compare", "identify-speed", "attitude",
                    "track", "solve", "blind", "accuracy"):
        assert section in names, proc.stdout
    assert all(len(line.split(None, 1)) == 2 and len(line.split(None, 1)[1]) > 20 for line in lines), proc.stdout
    bad = subprocess.run([sys.executable, os.path.join(BENCH, "run.py"), "no-such-section"], capture_output=True,
                         text=True, timeout=120, cwd=ROOT)
    assert bad.returncode == 2 and "no-such-section" in bad.stderr
