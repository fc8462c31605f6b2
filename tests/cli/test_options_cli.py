"""The command-line vocabulary (issue 13), option validation (issue 17), verbose and "did you mean" (issue 20).

Usage errors are decided while click parses the options, before any command body
runs, so the big parametrised table runs through the real entry point
``startrack.cli.main.main`` in this process (milliseconds a case); a sample of it
also runs in subprocesses through ``run_cli``, as a user would.
"""
import io
import json
import math
import re
import sys
from contextlib import redirect_stderr, redirect_stdout
from types import SimpleNamespace

import pytest
from conftest import assert_refused, run_cli

# (command, arguments, the option(s) the message must name).  Required options
# are given (files need not exist: nothing is read when the options are refused).
ID = ("identify", "-", "-d", "db.h5")
TR = ("track", "-d", "db.h5")
EV = ("evaluate", "-d", "db.h5", "--fov-deg", "20", "--size", "1024x1024")
SO = ("solve", "sky.tiff")
CE = ("centroid", "sky.tiff")
RE = ("render", "--stars-only", "--fov-deg", "20")
BAD = [
    # issue 17's audit list
    (ID, ["--max-false-probability", "nan"], ["--max-false-probability"]),
    (("attitude",), ["--gate", "nan"], ["--gate"]),
    (ID, ["--sigma-px", "-1"], ["--sigma-px"]),
    (ID, ["--sigma-px", "nan"], ["--sigma-px"]),
    (("attitude",), ["--sigma-px", "-1"], ["--sigma-px"]),
    (("attitude",), ["--sigma-px", "nan"], ["--sigma-px"]),
    (ID, ["--tolerance-arcsec", "-1"], ["--tolerance-arcsec"]),
    (ID, ["--tolerance-arcsec", "nan"], ["--tolerance-arcsec"]),
    (ID, ["--tolerance-arcsec", "inf"], ["--tolerance-arcsec"]),
    (ID, ["--tolerance-arcsec", "36000"], ["--tolerance-arcsec"]),
    (SO, ["--timeout-s", "nan"], ["--timeout-s"]),
    (SO, ["--timeout-s", "-1"], ["--timeout-s"]),
    (SO, ["--fov-tolerance", "nan"], ["--fov-tolerance"]),
    (CE, ["--psf-sigma-px", "-1"], ["--psf-sigma-px"]),
    (CE, ["--saturation-dn", "-1"], ["--saturation-dn"]),
    (CE, ["--gain-e-per-dn", "0"], ["--gain-e-per-dn"]),
    (EV, ["--drop-fraction", "1.5"], ["--drop-fraction"]),
    (EV, ["--min-stars", "10", "--max-stars", "3"], ["--min-stars", "--max-stars"]),
    (EV, ["--sigma-px", "0.1,,0.2"], ["--sigma-px"]),
    (SO, ["--camera", "cam.json", "--fov-deg", "11"], ["--camera", "--fov-deg"]),
    # and more
    (ID, ["--max-false-probability", "0"], ["--max-false-probability"]),
    (ID, ["--max-false-probability", "2"], ["--max-false-probability"]),
    (ID, ["--max-stars", "2"], ["--max-stars"]),
    (ID, ["--max-stars", "ten"], ["--max-stars"]),
    (ID, ["--algorithm", "nope"], ["--algorithm"]),
    (("attitude",), ["--gate", "-1"], ["--gate"]),
    (("attitude",), ["--gate", "inf"], ["--gate"]),
    (("attitude",), ["--sigma-floor-px", "-0.1"], ["--sigma-floor-px"]),
    (("attitude",), ["--epoch", "nan"], ["--epoch"]),
    (("attitude",), ["--method", "nope"], ["--method"]),
    (SO, ["--timeout-s", "0"], ["--timeout-s"]),
    (SO, ["--timeout-s", "inf"], ["--timeout-s"]),
    (SO, ["--fov-tolerance", "-0.1"], ["--fov-tolerance"]),
    (SO, ["--fov-deg", "0"], ["--fov-deg"]),
    (SO, ["--fov-deg", "nan"], ["--fov-deg"]),
    (SO, ["--fov-deg", "90"], ["--fov-deg"]),
    (SO, ["--jobs", "0"], ["--jobs"]),
    (SO, ["--epoch", "inf"], ["--epoch"]),
    (CE, ["--psf-sigma-px", "nan"], ["--psf-sigma-px"]),
    (CE, ["--threshold-sigma", "nan"], ["--threshold-sigma"]),
    (CE, ["--threshold-sigma", "0"], ["--threshold-sigma"]),
    (CE, ["--threshold-sigma", "3", "--threshold-dn", "100"], ["--threshold-sigma", "--threshold-dn"]),
    (CE, ["--mesh-px", "0"], ["--mesh-px"]),
    (CE, ["--max-elongation", "0.5"], ["--max-elongation"]),
    (CE, ["--min-pixels", "10", "--max-pixels", "3"], ["--min-pixels", "--max-pixels"]),
    (CE, ["--window-px", "0"], ["--window-px"]),
    (CE, ["--max-stars", "0"], ["--max-stars"]),
    (CE, ["--method", "nope"], ["--method"]),
    (CE, ["--filter-sigma-px", "inf"], ["--filter-sigma-px"]),
    (EV, ["--drop-fraction", "1"], ["--drop-fraction"]),
    (EV, ["--sigma-px", "nan"], ["--sigma-px"]),
    (EV, ["--sigma-px", "0.1,-0.2"], ["--sigma-px"]),
    (EV, ["--false-stars", "1.5"], ["--false-stars"]),
    (EV, ["--focal-error-pct", "0,inf"], ["--focal-error-pct"]),
    (EV, ["--mag-noise", ","], ["--mag-noise"]),
    (EV, ["--count", "0"], ["--count"]),
    (EV, ["--jobs", "0"], ["--jobs"]),
    (EV, ["-a", "pyramid,nope"], ["--algorithm"]),
    (EV, ["-a", "pyramid,,voting"], ["--algorithm"]),
    (EV, ["--sigma-px", "0.1", "--sigma-arcsec", "1"], ["--sigma-px", "--sigma-arcsec"]),
    (EV, ["--tolerance-arcsec", "nan"], ["--tolerance-arcsec"]),
    (EV, ["--sigma-hint-px", "0"], ["--sigma-hint-px"]),
    (EV, ["--mag-max", "nan"], ["--mag-max"]),
    (("render", "--fov-deg", "nan"), [], ["--fov-deg"]),
    (("render", "--fov-deg", "0"), [], ["--fov-deg"]),
    (("render", "--fov-deg", "20", "--camera", "cam.json"), [], ["--camera", "--fov-deg"]),
    (RE, ["--exposure-ms", "0"], ["--exposure-ms"]),
    (RE, ["--psf-sigma-px", "nan"], ["--psf-sigma-px"]),
    (RE, ["--quaternion", "1,0,0"], ["--quaternion"]),
    (RE, ["--quaternion", "0.5,0.5,0.5,0.6"], ["--quaternion"]),
    (RE, ["--rate-deg-s", "1,,2"], ["--rate-deg-s"]),
    (RE, ["--frames", "0"], ["--frames"]),
    (RE, ["--count", "0"], ["--count"]),
    (RE, ["-n", "-3"], ["--count"]),
    (RE, ["--drop-fraction", "1"], ["--drop-fraction"]),
    (RE, ["--prnu", "-0.1"], ["--prnu"]),
    (RE, ["--dec", "91"], ["--dec"]),
    (RE, ["--ra", "inf"], ["--ra"]),
    (RE, ["--mag-max", "nan"], ["--mag-max"]),
    (RE, ["--sigma-px", "-1"], ["--sigma-px"]),
    (RE, ["--sigma-px", "0.1", "--sigma-arcsec", "1"], ["--sigma-px", "--sigma-arcsec"]),
    (RE, ["--frame-interval-s", "0"], ["--frame-interval-s"]),
    (RE, ["--hot-pixels", "-1"], ["--hot-pixels"]),
    (RE, ["--seed", "-1"], ["--seed"]),
    (("catalog-filter",), ["--merge-arcsec", "nan"], ["--merge-arcsec"]),
    (("catalog-filter",), ["--uniform", "0"], ["--uniform"]),
    (("catalog-filter",), ["--cell-deg", "0"], ["--cell-deg"]),
    (("catalog-filter",), ["--epoch", "nan"], ["--epoch"]),
    (("catalog-filter",), ["--mag-min", "6", "--mag-max", "3"], ["--mag-min", "--mag-max"]),
    (("catalog-stats",), ["-n", "0"], ["--count"]),
    (("catalog-stats",), ["--fov-deg", "-1"], ["--fov-deg"]),
    (("catalog-stats",), ["--k1", "nan"], ["--k1"]),
    (("catalog-stats",), ["--focal-length-mm", "0"], ["--focal-length-mm"]),
    (("catalog-stats",), ["--pixel-pitch-um", "-6"], ["--pixel-pitch-um"]),
    (("catalog-stats", "--fov-deg", "10"), ["--size", "0x100"], ["--size"]),
    (("catalog-stats", "--fov-deg", "10"), ["--size", "100"], ["--size"]),
    (("catalog-stats", "--fov-deg", "10"), ["--size", "1e9x10"], ["--size"]),
    (("build-kvector", "-o", "db.h5"), ["--margin-deg", "-1"], ["--margin-deg"]),
    (("build-kvector", "-o", "db.h5"), ["--fov-deg", "inf"], ["--fov-deg"]),
    (("build-kvector", "-o", "db.h5"), ["--mag-max", "nan"], ["--mag-max"]),
    (("build-kvector", "-o", "db.h5"), ["--mag-min", "6", "--mag-max", "5"], ["--mag-min", "--mag-max"]),
    (("build-triangles", "-o", "db.h5"), ["--max-separation-deg", "nan"], ["--max-separation-deg"]),
    (("build-triangles", "-o", "db.h5"), ["--mag-min", "7", "--mag-max", "6"], ["--mag-min", "--mag-max"]),
    (("build-labels", "-o", "db.h5"), ["--fov-deg", "0"], ["--fov-deg"]),
    (("build-labels", "-o", "db.h5", "--fov-deg", "20"), ["--step-deg", "0"], ["--step-deg"]),
    (("build-labels", "-o", "db.h5", "--fov-deg", "20"), ["--group-size", "6", "--stars-per-field", "5"],
     ["--group-size", "--stars-per-field"]),
    (("build-labels", "-o", "db.h5", "--fov-deg", "20"), ["--scale-digits", "0"], ["--scale-digits"]),
    (TR, ["--sigma-px", "-1"], ["--sigma-px"]),
    (TR, ["--window-px", "0"], ["--window-px"]),
    (TR, ["--max-gap-s", "nan"], ["--max-gap-s"]),
    (TR, ["--initial-quaternion", "1,0,0,0.5"], ["--initial-quaternion"]),
    (TR, ["--rate-prior", "1,2"], ["--rate-prior"]),
    (TR, ["--rate-prior", "1,nan,2"], ["--rate-prior"]),
    (TR, ["--frame-interval-s", "0"], ["--frame-interval-s"]),
    (TR, ["--exposure-ms", "nan"], ["--exposure-ms"]),
    (TR, ["-a", "labelling"], ["--algorithm"]),
    (("plot", "-o", "x.png"), ["--mag-max", "nan"], ["--mag-max"]),
    (("calibrate", "-o", "lens.json"), ["--fit", "focal_length_px,zz"], ["--fit"]),
]
CASES = [pytest.param(cmd, extra, needles, id=" ".join((cmd[0], *extra))) for cmd, extra, needles in BAD]


def run_main(*args):
    """``startrack ARGS`` through the real entry point, in this process: (returncode, stdout, stderr)."""
    from startrack.cli.main import main

    out, err = io.StringIO(), io.StringIO()
    code = 0
    with redirect_stdout(out), redirect_stderr(err):
        try:
            main([str(a) for a in args])
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    return SimpleNamespace(returncode=code, stdout=out.getvalue(), stderr=err.getvalue())


@pytest.mark.parametrize("cmd, extra, needles", CASES)
def test_bad_option_refused(cmd, extra, needles):
    proc = run_main(*cmd, *extra)
    assert_refused(proc, *needles)


@pytest.mark.parametrize("i", [0, 1, 12, 17, 18, 19])
def test_bad_option_refused_through_the_process(i):
    """A sample of the table as a user meets it: a subprocess, exit 2, one line, nothing on stdout."""
    cmd, extra, needles = BAD[i]
    assert_refused(run_cli(*cmd, *extra), *needles)


def test_the_audit_list_is_in_the_table():
    spelled = {" ".join((c[0], *e)) for c, e, _ in BAD}
    for case in ["identify --max-false-probability nan", "attitude --gate nan", "identify --sigma-px -1",
                 "identify --sigma-px nan", "identify --tolerance-arcsec -1", "identify --tolerance-arcsec nan",
                 "identify --tolerance-arcsec inf", "identify --tolerance-arcsec 36000", "solve --timeout-s nan",
                 "solve --timeout-s -1", "solve --fov-tolerance nan", "centroid --psf-sigma-px -1",
                 "centroid --saturation-dn -1", "centroid --gain-e-per-dn 0", "evaluate --drop-fraction 1.5",
                 "evaluate --min-stars 10 --max-stars 3", "evaluate --sigma-px 0.1,,0.2",
                 "solve --camera cam.json --fov-deg 11"]:
        assert case in spelled, case


def _commands():
    from startrack.cli.main import COMMANDS, cli

    return {name: cli.get_command(None, name) for name in COMMANDS}


def test_no_help_says_mag_limit():
    """One spelling of magnitude limits: --mag-max/--mag-min, in every command's help."""
    for name in _commands():
        proc = run_main(name, "--help")
        assert proc.returncode == 0, name
        assert "--mag-limit" not in proc.stdout, name
    assert "--mag-limit" not in run_main("--help").stdout


def test_vocabulary_is_one():
    """The same concept has the same flag (and short form) in every command that has it."""
    import click

    expect = {"mag_max": ("--mag-max",), "mag_min": ("--mag-min",), "algorithms": ("-a", "--algorithm"),
              "algorithm": ("-a", "--algorithm"), "method": ("-m", "--method"), "count": ("-n", "--count"),
              "samples": ("-n", "--count"),
              "database": ("-d", "--database"), "databases": ("-d", "--database"), "seed": ("--seed",),
              "jobs": ("-j", "--jobs"), "quiet": ("-q", "--quiet"), "output": ("-o", "--output"),
              "verbose": ("-v", "--verbose")}
    seen = set()
    for name, command in _commands().items():
        for p in command.params:
            if isinstance(p, click.Option) and p.name in expect:
                assert set(p.opts) == set(expect[p.name]), (name, p.name, p.opts)
                seen.add(p.name)
            if isinstance(p, click.Option) and "--json" in p.opts:
                assert p.is_flag, (name, "--json must be a flag everywhere")
            if isinstance(p, click.Option) and p.name == "sigma_px" and name in ("identify", "attitude"):
                assert p.default is None and "0.5" in p.help, name
    assert seen == set(expect)


def test_choices_come_from_the_registries():
    from startrack.attitude import METHODS as ATT
    from startrack.centroid import METHODS as CEN
    from startrack.identify import algorithm_names, database_kind

    ALGORITHMS = algorithm_names()
    cmds = _commands()

    def opt(cmd, name):
        return next(p for p in cmds[cmd].params if p.name == name)

    assert list(opt("identify", "algorithm").type.choices) == list(ALGORITHMS)
    assert list(opt("track", "algorithm").type.choices) == [a for a in ALGORITHMS if database_kind(a) == "kvector"]
    assert list(opt("attitude", "method").type.choices) == list(ATT)
    assert list(opt("centroid", "method").type.choices) == list(CEN)
    help_text = run_main("identify", "--help").stdout
    assert "later versions" not in help_text
    for a in ALGORITHMS:
        assert a in help_text


def test_a_registered_algorithm_is_a_choice(monkeypatch):
    """Adding an algorithm to the registry adds it to the command line, with no second list to edit."""
    import importlib

    import startrack.identify as ident
    from startrack.identify.pyramid import PYRAMID

    registry = ident._registry()
    monkeypatch.setitem(registry, "toy", ident.Algorithm("toy", PYRAMID.search, PYRAMID.config, "kvector"))
    module = importlib.reload(importlib.import_module("startrack.cli.identify"))
    try:
        assert "toy" in next(p for p in module.command.params if p.name == "algorithm").type.choices
    finally:
        monkeypatch.undo()
        importlib.reload(module)


def test_deprecated_spelling_still_works_with_one_warning():
    new = run_cli("catalog-filter", "--mag-max", "1.0", "-q", check=True)
    old = run_cli("catalog-filter", "--mag-limit", "1.0", "-q", check=True)
    assert old.stdout == new.stdout and old.stdout.count("\n") > 5
    lines = old.stderr.splitlines()
    assert len(lines) == 1 and "--mag-limit is deprecated" in lines[0] and "--mag-max" in lines[0]


def test_deprecated_evaluate_json_path_is_rewritten():
    from startrack.cli.evaluate import _legacy_json_path

    ctx = SimpleNamespace(command_path="startrack evaluate")
    err = io.StringIO()
    with redirect_stderr(err):
        assert _legacy_json_path(ctx, ["--json", "rows.json", "-q"]) == ["--json", "-o", "rows.json", "-q"]
        assert _legacy_json_path(ctx, ["--json", "-q"]) == ["--json", "-q"]
    assert err.getvalue().count("deprecated") == 1


def test_library_parameter_names_become_flags():
    from startrack.cli.options import error_message
    from startrack.errors import BadInputError

    cmds = _commands()
    assert error_message(BadInputError("Camera.from_fov", "fov_deg", "must be positive, got -1"),
                         cmds["render"]) == "--fov-deg: must be positive, got -1"
    assert error_message(BadInputError("sigma_px", None, "must be positive, not with sigma_arcsec"),
                         cmds["render"]) == "--sigma-px: must be positive, not with --sigma-arcsec"
    # A parameter of another command is not turned into a flag this command lacks.
    assert error_message(BadInputError("x", "gate", "must be positive"), cmds["render"]) == "x: gate: must be positive"
    # A field of a file keeps its file name.
    assert error_message(BadInputError("f.json", "stars[0].sigma_px", "must be positive"),
                         cmds["identify"]) == "f.json: stars[0].sigma_px: must be positive"


def test_did_you_mean():
    proc = run_main("slove", "x.tiff")
    assert_refused(proc, "slove", "Did you mean 'solve'")
    proc = run_main("render", "--mag-mx", "3")
    assert_refused(proc, "--mag-mx", "--mag-max")
    assert_refused(run_main("frobnicate"), "No such command 'frobnicate'")


def test_verbose_logs_to_stderr_and_quiet_never_hides_errors():
    proc = run_cli("-v", "catalog-filter", "--mag-max", "1", "-q", check=True)
    assert re.search(r"INFO: startrack.cli: startrack catalog-filter .*mag_max=1\.0", proc.stderr), proc.stderr
    proc = run_cli("catalog-filter", "--mag-max", "1", "-q", "-v", check=True)
    assert "INFO" in proc.stderr
    assert run_cli("catalog-filter", "--mag-max", "1", "-q", check=True).stderr == ""
    assert_refused(run_cli("catalog-filter", "--mag-max", "nan", "-q"), "--mag-max")


def test_shell_completion_is_documented_and_works():
    assert "_STARTRACK_COMPLETE=bash_source" in run_main("--help").stdout
    proc = run_cli(env={"_STARTRACK_COMPLETE": "bash_complete", "COMP_WORDS": "startrack sol", "COMP_CWORD": "1"})
    assert proc.returncode == 0 and proc.stdout.splitlines() == ["plain,solve"], proc.stdout


def test_number_types():
    import click

    from startrack.cli.options import FiniteFloat, NumberList

    t = FiniteFloat(0, 1, min_open=True)
    assert t.convert("0.5", None, None) == 0.5
    for bad in ("nan", "inf", "-inf", "0", "1.0001", "", "x"):
        with pytest.raises(click.BadParameter):
            t.convert(bad, None, None)
    q = NumberList(-1, 1, length=4, unit=True, as_text=True)
    assert [float(v) for v in q.convert("0, 0, 0, 1", None, None).split(",")] == [0, 0, 0, 1]
    assert NumberList(integer=True, min=0).convert("0,2,4", None, None) == (0, 2, 4)
    assert math.isclose(sum(NumberList().convert("0.1,0.2", None, None)), 0.3)
    for bad in ("", ",", "1,", "1,,2", "1;2", "nan"):
        with pytest.raises(click.BadParameter):
            NumberList().convert(bad, None, None)


def test_evaluate_json_is_a_flag(tmp_path):
    """evaluate --json writes the rows as JSON to the main output (-o), like catalog-stats --json."""
    db = tmp_path / "db.h5"
    run_cli("build-kvector", "--fov-deg", "20", "--mag-max", "4", "-o", db, "-q", check=True)
    proc = run_cli("evaluate", "-d", db, "--fov-deg", "20", "--size", "512x512", "-a", "pyramid", "-n", "5",
                   "--seed", "1", "--json", "-q", check=True)
    doc = json.loads(proc.stdout)
    assert len(doc["rows"]) == 1 and doc["rows"][0]["algorithm"] == "pyramid"
    out = tmp_path / "rows.json"
    proc = run_cli("evaluate", "-d", db, "--fov-deg", "20", "--size", "512x512", "-a", "pyramid", "-n", "5",
                   "--seed", "1", "--json", "-o", out, "-q", check=True)
    def untimed(rows):
        return [{k: v for k, v in r.items() if not k.endswith("_ms")} for r in rows]

    assert untimed(json.loads(out.read_text())["rows"]) == untimed(doc["rows"])
    assert "pyramid" in proc.stdout and not proc.stdout.lstrip().startswith("{")


if __name__ == "__main__":
    sys.exit(pytest.main([__file__, "-q"]))
