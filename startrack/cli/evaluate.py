"""startrack evaluate: Monte Carlo comparison of identification algorithms."""
import click

from startrack.cli.options import (
    CAMERA_EXCLUSIVE,
    Command,
    FiniteFloat,
    Int,
    NameList,
    NumberList,
    camera_from_options,
    camera_options,
    catalog_option,
    handle_errors,
    identify_algorithms,
    info,
    jobs_option,
    mag_options,
    output_option,
    quiet_option,
    retired_algorithms,
    seed_option,
)


def algorithm_options(func):
    """The algorithms' own settings, as ``identify`` offers them (each applies to the algorithms that have it)."""
    from startrack.cli.identify import _algorithm_options

    return _algorithm_options(func)


def algorithm_configs(settings, algorithms):
    """Algorithm name -> configuration from the generated options; an option none of ``algorithms`` has is an error."""
    from startrack.errors import BadInputError
    from startrack.identify import config_fields, make_config

    values = {a: {} for a in algorithms}
    for f in config_fields():
        v = settings.pop(f["name"], None)
        if v is None:
            continue
        takers = [a for a in algorithms if a in f["algorithms"]]
        if not takers:
            flag = "--" + f["name"].replace("_", "-")
            raise BadInputError(flag, None, f"is a setting of {', '.join(f['algorithms'])}, none of which is compared")
        for a in takers:
            values[a][f["name"]] = v
    return {a: make_config(a, v) for a, v in values.items() if v}


def _floats(text, name):
    from startrack.errors import BadInputError

    if isinstance(text, (tuple, list)):
        return [float(v) for v in text]
    try:
        return [float(v) for v in str(text).split(",") if v.strip()]
    except ValueError:
        raise BadInputError(name, None, f"expected comma-separated numbers, got {text!r}") from None


def _legacy_json_path(ctx, args):
    """``--json PATH`` (an output file before the vocabulary of issue 13) -> ``--json -o PATH``."""
    out = []
    i = 0
    while i < len(args):
        out.append(args[i])
        if args[i] == "--json" and i + 1 < len(args) and not args[i + 1].startswith("-"):
            click.echo(f"{ctx.command_path}: warning: --json PATH is deprecated, use --json -o PATH", err=True)
            out += ["-o", args[i + 1]]
            i += 1
        i += 1
    return out


@click.command("evaluate", cls=Command, rewrite=_legacy_json_path,
               exclusive=CAMERA_EXCLUSIVE + (("sigma_px", "sigma_arcsec"),), ordered=[("min_stars", "max_stars")],
               short_help="Monte Carlo comparison of identification algorithms (papers' tables).")
@click.option("--database", "-d", "databases", multiple=True, required=True, type=click.Path(dir_okay=False),
              help="Databases (kvector, labels, ...), repeat as needed; each algorithm takes its kind.")
@click.option("--algorithm", "-a", "algorithms", type=NameList(identify_algorithms, retired=retired_algorithms),
              default="pyramid,voting", show_default=True, help="Algorithms compared, comma-separated.")
@catalog_option
@camera_options
@mag_options(max_help="Faintest star in the simulated star lists (default: the databases').", with_min=False)
@click.option("--count", "-n", type=Int(1, 100_000_000), default=1000, show_default=True, help="Random attitudes per condition.")
@click.option("--sigma-px", type=NumberList(0, 100), default="0.1", show_default=True, help="Centroid noise values (px, 1 sigma), comma-separated.")
@click.option("--sigma-arcsec", type=NumberList(0, 3600), default=None, help="Centroid noise values in arcsec instead.")
@click.option("--false-stars", type=NumberList(0, 100_000, integer=True), default="0", show_default=True, help="False-star counts, comma-separated.")
@click.option("--mag-noise", type=NumberList(0, 10), default="0", show_default=True, help="Magnitude noise values.")
@click.option("--focal-error-pct", type=NumberList(-50, 50), default="0", show_default=True, help="Focal-length errors in percent.")
@click.option("--drop-fraction", type=NumberList(0, 1, max_open=True), default="0", show_default=True, help="Fractions of stars dropped.")
@click.option("--min-stars", type=Int(0, 100_000), default=0, show_default=True, help="Only frames with at least this many stars.")
@click.option("--min-catalog-stars", type=Int(0, 100_000), default=0, show_default=True,
              help="Only frames with at least this many catalog stars (false stars not counted).")
@click.option("--max-stars", type=Int(1, 100_000), default=None, help="At most the N brightest stars per frame (paper 003: 10).")
@click.option("--tolerance-arcsec", type=FiniteFloat(0, 600, min_open=True), default=None, help="Angle tolerance override for all algorithms.")
@click.option("--sigma-hint-px", type=FiniteFloat(0, 100, min_open=True), default=None,
              help="Centroid noise the algorithms assume (default: the simulated one).")
@seed_option
@jobs_option
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="Run on a Dask cluster ('local': a LocalCluster of -j workers; or tcp://HOST:8786): frames are "
                   "made and identified by the workers in chunks and reduced as they arrive.")
@click.option("--csv", "csv_path", type=click.Path(dir_okay=False), default=None, help="Write the rows as CSV.")
@click.option("--json", "as_json", is_flag=True,
              help="Write the rows as JSON (what `plot --kind evaluate` reads) instead of the text table.")
@output_option("The table, or with --json the rows as JSON; with a FILE the table is still printed on stdout.")
@click.option("--resume", is_flag=True,
              help="Go on from the checkpoint (-o FILE's FILE.partial.json, with --accuracy FILE.partial.jsonl) that "
                   "a run cut short left, with the same options; the frames are the same, so the rows are those of "
                   "an uninterrupted run (times aside).")
@click.option("--plot", type=click.Path(dir_okay=False), default=None,
              help="Chart (.png, .pdf or .svg): success with its 95 % interval, and time, against the condition.")
@click.option("--accuracy", is_flag=True,
              help="Instead: render --count images (stars to --mag-max + 1) and report the attitude error against "
                   "each frame's Cramér-Rao bound, per axis, and NEES (identification by the first database and "
                   "algorithm).")
@quiet_option
@algorithm_options
@handle_errors
def command(databases, algorithms, catalog, camera_file, fov_deg, focal_length_mm, pixel_pitch_um, size, k1, k2,
            mag_max, count, sigma_px, sigma_arcsec, false_stars, mag_noise, focal_error_pct, drop_fraction,
            min_stars, min_catalog_stars, max_stars, tolerance_arcsec, sigma_hint_px, seed, jobs, scheduler, csv_path, as_json, output, plot,
            accuracy, quiet, resume, **settings):
    """Compare identification algorithms over random attitudes, as the papers do.

    Every combination of the comma-separated condition values is one row per
    algorithm: success rate and its Wilson 95 % interval, ID failures, bad
    matches and the interval of their rate, mean / median / 95th percentile
    time.  The progress bar counts frames and shows the time left.  Each condition uses the same attitudes (the same --seed)
    for every algorithm.  Bad matches are listed with the frame seed that
    reproduces them.

    \b
    Example (paper 003 Table 3's conditions, at 200 rather than the paper's 10,000 attitudes):
      startrack build-kvector --fov-deg 20 --mag-max 5.0 -o p003.h5
      startrack evaluate -d p003.h5 -a pyramid,voting --fov-deg 20 --size 1024x1024 --mag-max 5 \\
          --sigma-arcsec 1.667 --mag-noise 0.2 --max-stars 10 --false-stars 0,1 --count 200 --seed 1 -j 2
    \b
    Example (accuracy: error / Cramér-Rao bound per axis on paper 000's sensor, 100 rendered frames):
      startrack build-kvector --focal-length-mm 41.1 --pixel-pitch-um 6 --size 752x480 --mag-min 2.5 \\
          --mag-max 6.59 -o p000.h5
      startrack evaluate -d p000.h5 --focal-length-mm 41.1 --pixel-pitch-um 6 --size 752x480 --accuracy -n 100
    \b
    Example (robustness to focal-length error, with a chart):
      startrack evaluate -d p003.h5 --fov-deg 20 --size 1024x1024 --mag-max 5 --focal-error-pct 0,0.5,1,2 \\
          --count 50 --plot focal.png
    """
    from startrack.cli.options import require_stdout

    require_stdout()
    import json

    from startrack.catalog import load_catalog
    from startrack.errors import BadInputError
    from startrack.evaluate import conditions_grid, evaluate, summarise, with_intervals
    from startrack.formats.atomic import atomic_open, check_writable
    from startrack.identify import IdentifyParams
    from startrack.plot import plot_results
    from startrack.progress import ProgressBar

    cam = camera_from_options(camera_file, fov_deg, focal_length_mm, pixel_pitch_um, size, k1, k2,
                              default_size="1024x1024")
    if count < 1:
        raise BadInputError("--count", None, f"must be at least 1, got {count}")
    if jobs < 1:
        raise BadInputError("--jobs", None, f"must be at least 1, got {jobs}")
    if resume and output == "-":
        raise BadInputError("--resume", None, "needs -o FILE (its checkpoint is FILE.partial.json"
                                              + ("l)" if accuracy else ")"))
    for path in (csv_path, None if output == "-" else output, plot):
        if path:
            check_writable(path)
    from startrack.imageio import check_plot_output

    check_plot_output(plot)
    loaded = {}
    for path in databases:
        tag = _peek_format(path)
        kind = tag.split(".")[1].split("/")[0]
        if kind == "kvector":
            from startrack.kvector import check_database, load_kvector

            db = load_kvector(path)
            check_database(db, cam)
        elif kind == "labels":
            from startrack.labels import check_labels, load_labels

            db = load_labels(path)
            check_labels(db, cam)
        elif kind == "triangles":
            from startrack.triangles import check_triangles, load_triangles

            db = load_triangles(path)
            check_triangles(db, cam)
        else:
            raise BadInputError(path, "format", f"{tag!r} is not an identification database")
        loaded[kind] = db
    noise = _floats(sigma_px, "--sigma-px")
    in_arcsec = {}
    if sigma_arcsec is not None:
        noise = [v / cam.pixel_scale_arcsec for v in _floats(sigma_arcsec, "--sigma-arcsec")]
        in_arcsec = dict(zip(noise, _floats(sigma_arcsec, "--sigma-arcsec"), strict=True))
    if any(not v >= 0 for v in noise):
        raise BadInputError("--sigma-px", None, "must be >= 0")
    from startrack.render import MAX_FALSE_STARS

    n_false = [int(v) for v in _floats(false_stars, "--false-stars")]
    if any(not 0 <= v <= MAX_FALSE_STARS for v in n_false):
        raise BadInputError("--false-stars", None, f"each count must be in [0, {MAX_FALSE_STARS}], got {false_stars}")
    conds = conditions_grid(sigma_px=noise, false_stars=n_false,
                            mag_noise=_floats(mag_noise, "--mag-noise"),
                            focal_error_pct=_floats(focal_error_pct, "--focal-error-pct"),
                            drop_fraction=_floats(drop_fraction, "--drop-fraction"), min_stars=[min_stars],
                            max_stars=[max_stars], min_catalog_stars=[min_catalog_stars])
    if in_arcsec:
        import dataclasses

        conds = [dataclasses.replace(c, sigma_arcsec=in_arcsec[c.sigma_px]) for c in conds]
    algos = list(algorithms)
    configs = algorithm_configs(settings, algos)
    lim = mag_max
    if lim is None:
        lim = min(float(db.star_mag.max()) for db in loaded.values())
    cat = load_catalog(catalog, mag_max=lim).filter_magnitude(None, lim)
    import dataclasses
    import os

    import numpy as np

    checkpoint = f"{output}.partial.json" + ("l" if accuracy else "")
    if seed is None and not (resume and os.path.exists(checkpoint)):
        seed = int(np.random.SeedSequence().entropy % (2**31))
    if accuracy:
        _accuracy(cam, catalog, cat, lim, count, seed, databases[0], next(iter(loaded.values())), algos[0], max_stars,
                  None if output == "-" else output, quiet, resume)
        return
    # One step per identified frame (each algorithm's), so the bar moves within a condition and shows the
    # rate and the time left (tqdm's ETA), not a jump from 0 to 100 % at the end of each condition.
    bar = ProgressBar("evaluate", quiet, unit=" frame")
    saved = _Checkpoint(None if output == "-" else output, resume, seed, {
        "count": count, "camera": cam.to_dict(), "mag_limit": lim, "databases": [os.path.abspath(d) for d in databases],
        "catalog": catalog, "algorithms": algos, "conditions": [dataclasses.asdict(c) for c in conds],
        "tolerance_arcsec": tolerance_arcsec, "sigma_hint_px": sigma_hint_px,
        "settings": {a: dataclasses.asdict(c) for a, c in configs.items()}})
    seed = saved.seed
    rows = list(saved.rows)
    for ci, cond in enumerate(conds):
        if ci < saved.conditions_done:
            continue
        hint = sigma_hint_px if sigma_hint_px is not None else max(cond.sigma_px, 0.01)
        params = IdentifyParams(sigma_px=hint, tolerance_arcsec=tolerance_arcsec)
        done = len(rows)
        rows += evaluate(algos, [cond], count, loaded, cam, cat, seed, jobs, params, lim, scheduler=scheduler,
                         catalog_path=catalog, configs=configs, resume=saved.partial(ci),
                         checkpoint=saved.saver(ci, rows[:done]),
                         progress=lambda d, _t, k=done: bar(k * count + d, len(conds) * len(algos) * count))
    for r in rows:
        if r.get("double_frames"):
            info(quiet, f"unresolved doubles: {r['algorithm']} [{r['condition']}] {r['double_frames']} frames with one "
                        f"in view: {r['double_success']} identified, {r['double_bad']} wrong")
    for r in rows:
        for b in r["bad_seeds"]:
            info(quiet, f"bad match: {r['algorithm']} [{r['condition']}] frame seed {b['frame_seed']}: "
                        f"{b['wrong']}")
    from dataclasses import asdict

    rows = [with_intervals(r) for r in rows]        # rows of a checkpoint written before the intervals
    meta = {"seed": seed, "count": count, "camera": cam.to_dict(), "mag_max": lim,
            "databases": list(databases), "settings": {a: asdict(c) for a, c in configs.items()}}
    from startrack._version import __version__

    text = (json.dumps({"startrack_version": __version__, "params": meta, "rows": rows}, indent=1) if as_json
            else summarise(rows))
    if output != "-":
        with atomic_open(output, "w") as fh:
            fh.write(text + "\n")
    click.echo(text if output == "-" else summarise(rows))
    if csv_path:
        import csv

        keys = [k for k in rows[0] if k != "bad_seeds"]
        with atomic_open(csv_path, "w", newline="") as fh:
            fh.write(f"# startrack {__version__} evaluate; params: {json.dumps(meta)}\n")
            w = csv.DictWriter(fh, keys, extrasaction="ignore")
            w.writeheader()
            w.writerows(rows)
    saved.remove()
    if plot:
        # the conditions every point shares, in the title (the swept one is the x axis)
        plot_results(rows, plot, title=f"{cam.fov_deg[0]:.1f} x {cam.fov_deg[1]:.1f} deg field, {cam.width}x{cam.height} px, "
                                       f"stars to Hp {lim:g}")
        info(quiet, f"evaluate: chart -> {plot}")


def _peek_format(path):
    import os

    import h5py

    from startrack.errors import BadInputError

    if not os.path.exists(path):
        raise BadInputError(path, None, "no such file")
    from startrack.formats.hdf5 import corrupt_hdf5

    try:
        h5 = h5py.File(path, "r")
    except OSError:
        raise BadInputError(path, None, "is not an HDF5 file") from None
    with h5, corrupt_hdf5(path, "format"):
        tag = h5.attrs.get("format")
    if tag is None:
        raise BadInputError(path, "format", "is missing")
    tag = tag.decode() if isinstance(tag, bytes) else str(tag)
    if not tag.startswith("startrack."):
        raise BadInputError(path, "format", f"{tag!r} is not a startrack database")
    return tag


def _accuracy(cam, catalog_path, cat, lim, count, seed, db_path, db, algorithm, max_stars, json_path, quiet,
              resume=False):
    """``evaluate --accuracy``: startrack.accuracy.evaluate_accuracy on rendered frames, printed as a table.

    With ``-o FILE`` each frame's record goes to ``FILE.partial.jsonl`` as it ends (:class:`_AccuracyCheckpoint`),
    and ``--resume`` goes on from it.
    """
    import json
    import os

    from startrack.accuracy import evaluate_accuracy
    from startrack.catalog import load_catalog
    from startrack.errors import BadInputError, ParameterError
    from startrack.formats.atomic import atomic_open
    from startrack.identify import IdentifyParams, identify_stars
    from startrack.progress import ProgressBar

    params = IdentifyParams()

    def identify(stars):
        res = identify_stars(stars, cam, db, algorithm, params)
        return [(m.star, m.id) for m in res.matches] if res.status == "ok" else None

    render_cat = load_catalog(catalog_path).filter_magnitude(None, lim + 1.0)
    bar = ProgressBar("evaluate", quiet)
    saved = _AccuracyCheckpoint(json_path, resume, {
        "seed": seed, "count": count, "camera": cam.to_dict(), "catalog": catalog_path, "mag_limit": lim,
        "database": os.path.abspath(db_path), "algorithm": algorithm, "max_stars": max_stars})
    seed = saved.options["seed"]
    with saved:
        try:
            s = evaluate_accuracy(cam, cat, count, seed, render_catalog=render_cat, identify=identify,
                                  max_stars=max_stars, progress=bar, done=saved.records(), on_frame=saved.add)
        except ParameterError as exc:
            if exc.field != "done":
                raise
            raise BadInputError(saved.path, "frame", exc.problem) from None
    if not s.get("frames"):
        click.echo(f"no frame solved ({s['failed']} failed, {s['wrong']} wrong, {s['no_bound']} without 2 stars)")
        return
    click.echo(f"{s['frames']} frames solved, {s['failed']} failed, {s['far']} over 0.1 deg but within 5 sigma, "
               f"{s['wrong']} wrong, {s['no_bound']} with < 2 stars")
    click.echo(f"cross-boresight: RMS {s['rms_cross_arcsec']:.3f}\" / RMS bound {s['crb_cross_arcsec']:.3f}\" = "
               f"{s['ratio_cross']:.2f}  (normalised RMS {s['z_cross']:.2f})")
    click.echo(f"roll:            RMS {s['rms_roll_arcsec']:.2f}\" / RMS bound {s['crb_roll_arcsec']:.2f}\" = "
               f"{s['ratio_roll']:.2f}  (normalised RMS {s['z_roll']:.2f})")
    if "nees_mean" in s:
        lo, hi = s["nees_band"]
        click.echo(f"NEES mean {s['nees_mean']:.3f} (95 % band {lo:.3f} to {hi:.3f}); "
                   f"{100 * s['nees_in_95']:.1f} % of frames below the chi-square(3) 95 % point")
    if json_path:
        with atomic_open(json_path, "w") as fh:
            json.dump({"accuracy": s, "seed": seed, "count": count, "camera": cam.to_dict()}, fh, indent=1,
                      default=list)
    saved.remove()


class _AccuracyCheckpoint:
    """``FILE.partial.jsonl`` beside ``evaluate --accuracy -o FILE``: a header line, then one line per frame done.

    The header holds the run's ``options`` (seed, count, camera, catalog, magnitude limit, database, algorithm,
    max_stars); each frame's record (``evaluate_accuracy``'s ``on_frame``) is appended and flushed as the frame
    ends, so a kill loses at most the frame under way (a last line cut short is dropped on resume).  Removed when
    the run ends.  ``--resume`` checks the header field by field against this run and goes on after the last
    frame written; without ``--resume`` a run starts afresh and overwrites it.
    """

    FORMAT = "startrack.evaluate-accuracy-checkpoint/1"

    def __init__(self, output, resume, options):
        import json
        import os

        from startrack.errors import BadInputError

        self.path = None if output is None else f"{output}.partial.jsonl"
        self.options = dict(options)
        self._fh = None
        self._resumed = False
        if not resume or self.path is None:
            return
        if not os.path.exists(self.path):
            raise BadInputError(self.path, None, "no such file: nothing to resume (run without --resume)")
        try:  # read directly: this file is written by this run, it is no input to protect
            with open(self.path, "rb") as fh:
                head = fh.readline()
            doc = json.loads(head)
        except (OSError, ValueError) as exc:
            raise BadInputError(self.path, None, f"cannot be read as a checkpoint ({exc})") from None
        if not isinstance(doc, dict) or doc.get("format") != self.FORMAT:
            raise BadInputError(self.path, "format", "is not an evaluate --accuracy checkpoint")
        mine = json.loads(json.dumps(self.options))
        for field, value in mine.items():
            if field == "seed" and value is None:   # --resume without --seed: the checkpoint's
                if not isinstance(doc.get("seed"), int):
                    raise BadInputError(self.path, "seed", f"is {doc.get('seed')!r}, not an integer")
                self.options["seed"] = doc["seed"]
                continue
            if doc.get(field) != value:
                raise BadInputError(self.path, field, f"is {json.dumps(doc.get(field))}, not this run's "
                                                      f"{json.dumps(value)}: give the same options, or run without "
                                                      "--resume")
        self._resumed = True

    def records(self):
        """The frames' records already in the file, one at a time (none without --resume)."""
        import json

        from startrack.errors import BadInputError

        if not self._resumed:
            return
        with open(self.path, "rb") as fh:
            fh.readline()
            for i, line in enumerate(fh, start=2):
                if not line.endswith(b"\n"):
                    return          # cut by a kill while written: that frame is done again
                try:
                    yield json.loads(line)
                except ValueError as exc:
                    raise BadInputError(self.path, f"line {i}", f"is not a frame record ({exc})") from None

    def __enter__(self):
        import json
        import os

        from startrack._version import __version__

        if self.path is None:
            return self
        if self._resumed:
            with open(self.path, "rb+") as fh:   # drop a last line cut short, then append after the whole ones
                end = fh.seek(0, os.SEEK_END)
                while end > 0:
                    start = max(0, end - 4096)
                    fh.seek(start)
                    cut = fh.read(end - start).rfind(b"\n")
                    if cut >= 0:
                        fh.truncate(start + cut + 1)
                        break
                    end = start
            self._fh = open(self.path, "a", encoding="utf-8")  # noqa: SIM115 (closed in __exit__)
        else:
            tmp = f"{self.path}.tmp{os.getpid()}"
            with open(tmp, "w", encoding="utf-8") as fh:
                fh.write(json.dumps({"format": self.FORMAT, "startrack_version": __version__, **self.options}) + "\n")
            os.replace(tmp, self.path)
            self._fh = open(self.path, "a", encoding="utf-8")  # noqa: SIM115 (closed in __exit__)
        return self

    def add(self, record):
        import json

        if self._fh is not None:
            self._fh.write(json.dumps(record) + "\n")
            self._fh.flush()

    def __exit__(self, *exc):
        if self._fh is not None:
            self._fh.close()
            self._fh = None
        return False

    def remove(self):
        import contextlib
        import os

        if self.path is not None:
            with contextlib.suppress(OSError):
                os.remove(self.path)


class _Checkpoint:
    """``FILE.partial.json`` beside ``evaluate -o FILE``: the rows done and the tallies of the condition under way.

    Written (atomically, at most every few seconds and at the end of each condition) while the run goes
    on, removed when it ends; ``--resume`` goes on from it when it was written with the same options
    (its ``key``), else it is refused.  Without ``--resume`` a run starts afresh and overwrites it.
    """

    def __init__(self, output, resume, seed, options):
        import hashlib
        import json
        import os

        #: seconds between checkpoints (STARTRACK_CHECKPOINT_S, default 5)
        self.every_s = float(os.environ.get("STARTRACK_CHECKPOINT_S", "5"))

        from startrack.errors import BadInputError

        self.path = None if output is None else f"{output}.partial.json"
        self.key = hashlib.sha256(json.dumps(options, sort_keys=True, default=str).encode()).hexdigest()
        self.seed, self.rows, self.conditions_done, self._partial = seed, [], 0, None
        self._last = 0.0
        if not resume:
            return
        if not os.path.exists(self.path):
            raise BadInputError(self.path, None, "no such file: nothing to resume (run without --resume)")
        try:  # read directly: this file is rewritten by this run, it is no input to protect
            with open(self.path, encoding="utf-8") as fh:
                doc = json.load(fh)
        except (OSError, ValueError) as exc:
            raise BadInputError(self.path, None, f"cannot be read as a checkpoint ({exc})") from None
        if not isinstance(doc, dict) or doc.get("format") != "startrack.evaluate-checkpoint/1":
            raise BadInputError(self.path, "format", "is not an evaluate checkpoint")
        if doc.get("key") != self.key:
            raise BadInputError(self.path, "key", "was written by an evaluate run with other options: give the same "
                                                  "options, or run without --resume")
        if seed is not None and doc.get("seed") != seed:
            raise BadInputError(self.path, "seed", f"is {doc.get('seed')}, not --seed {seed}")
        try:
            self.seed, self.rows = int(doc["seed"]), list(doc["rows"])
            self.conditions_done = int(doc["conditions_done"])
            self._partial = doc.get("partial")
        except (KeyError, TypeError, ValueError) as exc:
            raise BadInputError(self.path, None, f"is damaged ({type(exc).__name__}: {exc})") from None

    def partial(self, condition: int):
        """The state ``evaluate(resume=...)`` takes for condition ``condition``, or None."""
        p = self._partial
        if p is not None and p.get("condition_index") == condition:
            return p["state"]
        return None

    def saver(self, condition: int, rows_before: list):
        if self.path is None:
            return None

        def save(state):
            import time

            end = state["tallies"] is None
            if not end and time.monotonic() - self._last < self.every_s:
                return
            self._last = time.monotonic()
            rows = rows_before + state["rows"]
            partial = None if end else {"condition_index": condition, "state": {**state, "rows": []}}
            self._write({"rows": rows, "conditions_done": condition + 1 if end else condition, "partial": partial})
        return save

    def _write(self, body):
        import json

        from startrack._version import __version__
        from startrack.formats.atomic import atomic_open

        doc = {"format": "startrack.evaluate-checkpoint/1", "startrack_version": __version__, "key": self.key,
               "seed": self.seed, **body}
        with atomic_open(self.path, "w") as fh:
            json.dump(doc, fh, allow_nan=True)

    def remove(self):
        import contextlib
        import os

        if self.path is not None:
            with contextlib.suppress(OSError):
                os.remove(self.path)
