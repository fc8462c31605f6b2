"""docs/formats.md against what the commands write, both ways (issue 20).

The commands run at small sizes: render (an image and a star list), centroid (also windowed and
a batch with a missing image), build-kvector, identify, attitude --wcs, track, solve (with every
output file), evaluate --json and --accuracy, catalog-stats --json and plot --kind track (its
standard output).  Their JSON is walked key by key against the field tables of docs/formats.md:
each table is marked ``<!-- fields: PATH -->`` (PATH as ``attitude``, ``stars[]``,
``truth.stars[]``, ``evaluate --json.rows[]``; the generated tables of the typed records carry
the same marks).  An object is checked (and walked into) when its path has a table; a list of
objects when ``PATH[]`` has one.

* Every key written must be in its table.
* Every field of a table must be written by one of the runs, or, for the fields that only
  rare conditions produce (a sign flip of a tracking rate, a blended double, another
  algorithm's details), be written by the package's source (the name as a string or keyword).
"""
import json
import os
import re

import pytest
from conftest import ROOT, run_cli

DOC = os.path.join(ROOT, "docs", "formats.md")
MARK = re.compile(r"<!--\s*fields:\s*(.+?)\s*-->")
EVERY = "(every section)"


# ---------------------------------------------------------------------------------------------
# The documented fields
# ---------------------------------------------------------------------------------------------

def documented_fields(text):
    """PATH -> list of field names (``MODE``-like upper-case words are wildcards) from the marked tables."""
    tables = {}
    lines = text.splitlines()
    for i, line in enumerate(lines):
        m = MARK.search(line)
        if not m:
            continue
        fields = tables.setdefault(m.group(1), [])
        rows = []
        for row in lines[i + 1:]:
            if not row.startswith("|"):
                break
            rows.append(row)
        assert len(rows) >= 3, f"the mark {line!r} is not followed by a table"
        for row in rows[2:]:             # the header and the |---| line
            first = row.strip("|").split("|")[0]
            names = re.findall(r"`([^`]+)`", first)
            assert names, f"{m.group(1)}: a row without a field name: {row!r}"
            fields.extend(names)
    return tables


def _pattern(name):
    return re.compile("^" + "".join(r"[\w-]+" if re.fullmatch(r"[A-Z]{3,}", part) else re.escape(part)
                                    for part in re.split(r"([A-Z]{3,})", name)) + "$")


class Checker:
    """Walks outputs against the tables; collects undocumented keys and the documented fields seen."""

    def __init__(self, tables):
        self.tables = tables
        self.sections = [f for f in tables.get("frame", [])]
        self.undocumented = set()
        self.seen = set()

    def fields(self, path):
        names = list(self.tables[path])
        if path in self.sections:
            names += self.tables.get(EVERY, [])
        return names

    def walk(self, value, path):
        if isinstance(value, dict) and path in self.tables:
            names = self.fields(path)
            for key, sub in value.items():
                hit = next((n for n in names if _pattern(n).match(key)), None)
                if hit is None:
                    self.undocumented.add(f"{path}: {key}")
                else:
                    self.seen.add((EVERY if hit not in self.tables[path] else path, hit))
                self.walk(sub, key if path == "frame" else f"{path}.{key}")
        elif isinstance(value, list) and f"{path}[]" in self.tables:
            for item in value:
                self.walk(item, f"{path}[]")

    def never_written(self, source):
        """Documented fields no run wrote and no source line writes."""
        missing = []
        for path, names in self.tables.items():
            for n in names:
                if (path, n) in self.seen:
                    continue
                static = max(re.split(r"[A-Z]{3,}", n), key=len).strip("_")
                if not re.search(rf"[\"']{re.escape(static)}[\"'_]|\b{re.escape(static)}=|[\"']{re.escape(static)}",
                                 source):
                    missing.append(f"{path}: {n}")
        return missing


def _package_source():
    parts = []
    for base, _, files in os.walk(os.path.join(ROOT, "startrack")):
        for f in files:
            if f.endswith(".py"):
                with open(os.path.join(base, f), encoding="utf-8") as fh:
                    parts.append(fh.read())
    return "\n".join(parts)


# ---------------------------------------------------------------------------------------------
# The runs
# ---------------------------------------------------------------------------------------------

def _docs(text):
    text = text.strip()
    if not text:
        return []
    try:
        return [json.loads(text)]
    except json.JSONDecodeError:
        return [json.loads(line) for line in text.splitlines() if line.strip()]


@pytest.fixture(scope="module")
def outputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("formats")
    p = lambda name: str(d / name)  # noqa: E731
    out = {"frame": []}

    def st(*args, input=None, ok=(0,)):
        proc = run_cli(*args, input=input, timeout=900)
        assert proc.returncode in ok, (args, proc.returncode, proc.stderr[-2000:])
        return proc.stdout

    cam20 = ("--fov-deg", "20", "--size", "1024x1024")
    render = st("render", "--fov-deg", "20", "--size", "640x640", "--ra", "83.8", "--dec", "-1.2", "--seed", "1",
                "--false-stars", "2", "--hot-pixels", "3", "--mag-max", "6", "-o", p("img.png"), "-q")
    with open(p("render.json"), "w") as fh:
        fh.write(render)
    stars = st("render", "--stars-only", "--count", "3", *cam20, "--mag-max", "5", "--false-stars", "1", "--seed", "1",
               "-q")
    cent = st("centroid", p("render.json"), "-q")
    windowed = st("centroid", p("render.json"), "--windows-from", "truth", "-q")
    with_missing = st("centroid", p("img.png"), p("missing.png"), "-q", ok=(2,))
    st("build-kvector", *cam20, "--mag-max", "5.0", "-o", p("db.h5"), "-q")
    ident = st("identify", "-d", p("db.h5"), "-q", input=cent)
    att = st("attitude", "--wcs", p("w.fits"), "-q", input=ident)
    seq = st("render", "--fov-deg", "12", "--size", "512x384", "--frames", "6", "--rate-deg-s", "0.3,-0.2,0.5",
             "--frame-interval-s", "0.1", "--blackout", "3:1", "--seed", "1", "-o", p("seq/frame.png"), "-q")
    st("build-kvector", "--fov-deg", "12", "--size", "512x384", "--mag-max", "6.0", "-o", p("db12.h5"), "-q")
    track = st("track", "-d", p("db12.h5"), "-q", input=seq, ok=(0, 1))
    with open(p("track.jsonl"), "w") as fh:
        fh.write(track)
    out["plot --kind track"] = _docs(st("plot", p("track.jsonl"), "--kind", "track", "-o", p("t.png"), "--json", "-q"))
    solve = st("solve", os.path.join(ROOT, "examples", "data", "sky.tiff"), "--wcs", p("s.wcs.fits"),
               "--plot", p("s.png"), "--fits-out", p("s.fits"), "--matches-out", p("s.csv"), "--corr-out",
               p("s.corr.fits"), "--axy-out", p("s.axy"), "--ra", "286", "--dec", "29", "--radius", "5",
               "--scale-low", "8", "--scale-high", "15", "--target-pixel", "1,2", "--target-radec", "286,29", "-q")
    st("evaluate", "-d", p("db.h5"), *cam20, "--mag-max", "5", "--count", "10", "-a", "pyramid,voting",
       "--false-stars", "0,1", "--seed", "1", "--json", "-o", p("ev.json"), "-q")
    st("evaluate", "-d", p("db.h5"), "--fov-deg", "20", "--size", "640x640", "--mag-max", "5", "--accuracy",
       "-n", "4", "--seed", "1", "--json", "-o", p("acc.json"), "-q")
    out["catalog-stats --json"] = _docs(st("catalog-stats", *cam20, "--mag-max", "5", "-n", "100", "--json"))
    for name, path in (("evaluate --json", "ev.json"), ("evaluate --accuracy", "acc.json")):
        with open(p(path)) as fh:
            out[name] = _docs(fh.read())
    for text in (render, stars, cent, windowed, with_missing, ident, att, seq, track, solve):
        out["frame"] += _docs(text)
    return out


# ---------------------------------------------------------------------------------------------
# The tests
# ---------------------------------------------------------------------------------------------

def test_every_written_field_is_documented_and_every_documented_field_written(outputs):
    with open(DOC, encoding="utf-8") as fh:
        tables = documented_fields(fh.read())
    for root in outputs:
        assert root in tables, f"docs/formats.md has no table for {root!r}"
    checker = Checker(tables)
    for root, docs in outputs.items():
        assert docs, root
        for doc in docs:
            checker.walk(doc, root)
    assert not checker.undocumented, "written but not in docs/formats.md:\n" + "\n".join(sorted(checker.undocumented))
    missing = checker.never_written(_package_source())
    assert not missing, "in docs/formats.md but never written:\n" + "\n".join(missing)
    n_fields = sum(len(v) for v in tables.values())
    print(f"formats.md: {len(tables)} tables, {n_fields} fields; {len(checker.seen)} seen in the outputs of "
          f"{sum(len(v) for v in outputs.values())} documents")
    # the runs reach the rare sections too
    for path in ("truth.stars[]", "stars[].streak", "centroid.rejected[]", "attitude.residuals[]", "track.stars[]",
                 "solve.principal_point", "solve.hint", "solve.targets[]", "evaluate --json.rows[]",
                 "evaluate --accuracy.accuracy"):
        assert any(p == path for p, _ in checker.seen), path
    assert (EVERY, "bad_input") in checker.seen


def test_the_checker_catches_drift_both_ways():
    text = ("<!-- fields: frame -->\n| field | | |\n|---|---|---|\n| `solve` | | |\n\n"
            "<!-- fields: solve -->\n| field | | |\n|---|---|---|\n| `fov_deg` | | |\n| `rms_MODE_arcsec` | | |\n"
            "| `never_anywhere_xyz` | | |\n\n<!-- fields: (every section) -->\n| f | |\n|---|---|\n| `status` | |\n")
    tables = documented_fields(text)
    assert tables["solve"] == ["fov_deg", "rms_MODE_arcsec", "never_anywhere_xyz"]
    checker = Checker(tables)
    checker.walk({"solve": {"status": "ok", "fov_deg": [1, 2], "rms_tracking_arcsec": 1.0, "undocumented_key": 1}},
                 "frame")
    assert checker.undocumented == {"solve: undocumented_key"}
    assert checker.never_written('x = {"fov_deg": 1}') == ["solve: never_anywhere_xyz"]
