"""startrack solve: photographs in, attitudes out (centroid -> identify -> attitude)."""
from dataclasses import dataclass

import click

from startrack.cli.options import (
    Command,
    FiniteFloat,
    Int,
    NoTimeNotice,
    NumberList,
    OutputPath,
    apparent_from_options,
    apparent_options,
    calibration_frame_options,
    handle_errors,
    load_camera_file,
    output_option,
    parity_option,
    quiet_option,
    resume_option,
)


def output_for(template: str | None, image_path: str, total: int, suffix: str) -> str | None:
    """Where an image's output goes, named after the image.

    ``{name}`` in ``template`` is replaced by the image's file name without its
    extension; a template that is a directory (or ends with ``/``) receives
    ``NAME<suffix>``; with one image the template is the file; with several,
    ``sky.wcs.fits`` becomes ``sky.wcs-NAME.fits``.  The directory is created.
    """
    import os

    if not template:
        return None
    name = os.path.splitext(os.path.basename(image_path))[0]
    if "{name}" in template:
        path = template.replace("{name}", name)
    elif template.endswith(("/", os.sep)) or os.path.isdir(template):
        path = os.path.join(template, name + suffix)
    elif total <= 1:
        path = template
    else:
        root, ext = os.path.splitext(template)
        path = f"{root}-{name}{ext}"
    parent = os.path.dirname(path)
    if parent:
        os.makedirs(parent, exist_ok=True)
    return path


def _write_matches(path, doc):
    """The matched stars of a solved image as CSV: catalog id, RA/Dec, x/y, magnitude, residual."""
    import csv

    from startrack.formats.atomic import atomic_path

    # this process's catalog of the solve's ids (gaia's when the deep index identified it), loaded once
    cat = _databases().named_catalog(_catalog_of(doc))
    rows = cat.rows_by_id()
    resid = {(r["star"], r["id"]): r["residual_arcsec"] for r in doc["attitude"].get("residuals", [])}
    with atomic_path(path, suffix=".csv") as tmp, open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["catalog_id", "ra_deg", "dec_deg", "mag", "x_px", "y_px", "residual_arcsec", "used"])
        for m in doc["identification"]["matches"]:
            r = rows.get(int(m["id"]))
            s = doc["stars"][m["star"]]
            res = resid.get((m["star"], m["id"]))
            w.writerow([m["id"], f"{cat.ra[r]:.7f}" if r is not None else "", f"{cat.dec[r]:.7f}" if r is not None
                        else "", f"{cat.mag[r]:.3f}" if r is not None else "", f"{s['x']:.3f}", f"{s['y']:.3f}",
                        f"{res:.3f}" if res is not None else "", int(res is not None)])


def _cluster_progress(quiet):
    """A progress line on stderr for cluster batches (done, failed, in flight, images per second), once a second."""
    import time

    last = [0.0]

    def show(state):
        now = time.perf_counter()
        if quiet or (now - last[0] < 1.0 and state.done < state.total):
            return
        last[0] = now
        click.echo(f"solve: {state.line('images')}", err=True)

    return show


def _databases(catalog: str | None = None):
    """The databases of this process (the CLI's, or a -j worker's) for ``--catalog``: loaded once, kept for the
    next image."""
    from startrack.cluster import worker_cache
    from startrack.solve import BandDatabases

    cache = worker_cache()
    key = "band_databases" if catalog in (None, "hipparcos") else f"band_databases-{catalog}"
    if key not in cache:
        if key == "band_databases":
            cache[key] = BandDatabases()
        else:
            from startrack.catalog import load_catalog

            cache[key] = BandDatabases(load_catalog(catalog))
    return cache[key]


def _catalog_of(doc):
    """The catalog name of a solved frame's ids (``solve.catalog``), ``None`` for the shipped one."""
    name = (doc.get("solve") or {}).get("catalog")
    return None if name in (None, "hipparcos") else name


def _solved(run, jobs, scheduler, progress, base_dir=None):
    """``(index, frame document)`` of every task of ``run``, in order, with as many workers as pay off.

    On this machine, the first two images are solved here (the second one timed:
    the first pays this process's last first-use costs); workers then take the
    rest only when the time they save exceeds what they take to start, on CPUs
    other processes leave idle (:func:`startrack.cluster.pool_workers`; forked
    workers' start-up is measured, a spawned worker redoes this process's own,
    measured as its CPU time so far), so that ``-j N`` does not lose to ``-j 1``.
    """
    import logging
    import os
    import resource
    import time

    from startrack.cluster import idle_cpus, ordered_map, pool_workers, worker_startup_s

    if scheduler is not None or jobs <= 1 or len(run) <= 1:
        yield from ordered_map(_solve_one, run, jobs=max(1, min(jobs, len(run))), scheduler=scheduler,
                               progress=progress)
        return
    # The images this process solves before the pool starts are solved on one thread: find_stars' threads
    # (startrack.centroid reads STARTRACK_THREADS) would make forking the workers unsafe (cluster.fork_safe),
    # and the workers, one per CPU, each run single-threaded anyway.
    os.environ.setdefault("STARTRACK_THREADS", "1")
    ru = resource.getrusage(resource.RUSAGE_SELF)
    startup = ru.ru_utime + ru.ru_stime
    # The first image pays this process's remaining first-use costs (image readers' imports ...):
    # the second one is timed.
    head = min(2, len(run) - 1)
    task_s = 0.0
    t0 = time.perf_counter()
    for i, doc in ordered_map(_solve_one, run[:head], progress=progress):
        task_s = time.perf_counter() - t0
        yield i, doc
        t0 = time.perf_counter()
    rest = run[head:]
    # A pool's start-up is measured (forked workers) only when there is an idle CPU to give it.
    idle = idle_cpus()
    workers = pool_workers(jobs, len(rest), task_s, worker_startup_s(startup), idle=idle) \
        if min(jobs, len(rest), idle) > 1 else 1
    logging.getLogger(__name__).debug("-j %d: %d images left, %.3f s each: %d worker(s)", jobs, len(rest), task_s,
                                      workers)
    if workers == 1:
        for i, doc in ordered_map(_solve_one, rest, progress=progress):
            yield i + head, doc
        return
    # Workers write each document's line themselves (serialising is a fifth of an image's work here); this
    # process only writes them out in order.
    for i, doc in ordered_map(_solve_one_line, [(task, base_dir) for task in rest], jobs=workers, progress=progress):
        yield i + head, doc


def _calibration(frames):
    """This process's calibration frames of ``(bias, dark, flat)`` paths: read once, kept for the next image."""
    from startrack.calibration_frames import load_calibration_frames
    from startrack.cluster import worker_cache

    cache = worker_cache()
    key = ("calibration_frames", frames)
    if key not in cache:
        cache[key] = load_calibration_frames(*frames)
    return cache[key]


def _solve_one(args):
    """Worker: solve one image path; returns the frame document (never raises for a bad image)."""
    import dataclasses
    import time

    from startrack.apparent import frame_apparent, image_time_tags
    from startrack.errors import BadInputError
    from startrack.formats.frame import FRAME_FORMAT
    from startrack.formats.sections import to_frame
    from startrack.imageio import read_image
    from startrack.solve import solve_image

    path, (options, apparent, utc_offset, scale), camera_doc, outputs, frames = args
    t0 = time.perf_counter()
    doc = {"format": FRAME_FORMAT, "image": {"path": path}}
    try:
        # Whole DN as decoded (find_stars reads them as float32 holds them, without a copy), unless calibration
        # frames are subtracted from them.
        image, meta = read_image(path, whole_dn=frames is None)
        pixels, saturation = image, meta["saturation"]
        if frames is not None:
            calibration = _calibration(frames)
            pixels, saturation = calibration.apply(image, saturation, path)
            doc["image"]["calibration"] = calibration.record()
        header, exif = image_time_tags(path)
        setting = frame_apparent(doc, apparent, path, header, exif, utc_offset)
    except BadInputError as exc:
        doc["solve"] = {"status": "failed", "reason": str(exc), "bad_input": True}
        return doc
    if setting.time.known:
        from startrack.timeutil import format_time, julian_year

        doc["image"]["time"] = format_time(setting.time.time)
        if options.epoch is None:
            options = dataclasses.replace(options, epoch=julian_year(setting.time.time))
    options = dataclasses.replace(options, observer=setting.state, **fov_range_of_scale(scale, image.shape[1]))
    doc["image"].update(width=image.shape[1], height=image.shape[0], bit_depth=meta["bit_depth"])
    cam = None
    if camera_doc is not None:
        from startrack.camera import Camera

        cam = Camera.from_dict(camera_doc)
    result = solve_image(pixels, options=options, camera=cam, saturation=saturation,
                         databases=_databases(options.catalog))
    doc.update(to_frame(result))
    doc["solve"]["time_ms"] = round((time.perf_counter() - t0) * 1000, 3)
    if isinstance(doc.get("attitude"), dict):
        doc["attitude"]["apparent"] = setting.record()
    if doc["solve"]["status"] == "ok":
        try:
            _write_outputs(doc, image, path, outputs, result, meta["bit_depth"])
        except BadInputError as exc:
            # an output that cannot be written (disk full, /dev/full) is the command's error, not the image's
            return OutputFailure(exc.source, exc.field, exc.problem)
    return doc


@dataclass(frozen=True)
class SolvedLine:
    """A worker's frame document, serialised there (:func:`startrack.formats.frame.frame_line`): ``line`` is
    written as it is; ``summary`` holds what the batch reads of the document (image, solve, attitude.apparent)."""

    summary: dict
    line: str


def _solve_one_line(args):
    """Worker: :func:`_solve_one`, its document serialised for a writer whose ``base_dir`` is given."""
    from startrack.formats.frame import frame_line

    task, base_dir = args
    doc = _solve_one(task)
    if not isinstance(doc, dict):
        return doc
    summary = {"image": doc.get("image"), "solve": doc["solve"]}
    attitude = doc.get("attitude")
    if isinstance(attitude, dict) and "apparent" in attitude:
        summary["attitude"] = {"apparent": attitude["apparent"]}
    return SolvedLine(summary, frame_line(doc, base_dir))


@dataclass(frozen=True)
class OutputFailure:
    """A worker's output file that could not be written: the batch stops with exit 2 naming it."""

    source: str
    field: str | None
    problem: str


def fov_range_of_scale(scale, width: int) -> dict:
    """``SolveOptions`` fields ``fov_min_deg``/``fov_max_deg`` of ``--scale-low/--scale-high/--scale-units`` for an
    image ``width`` pixels wide (``{}`` when neither is given).

    ``degwidth``: the image's width in degrees, the horizontal field; ``arcsecperpix``: the scale at the
    image centre, a pinhole's ``fov = 2 atan(width / 2 tan(scale))``.
    """
    import math

    low, high, units = scale
    out = {}
    for name, value in (("fov_min_deg", low), ("fov_max_deg", high)):
        if value is None:
            continue
        if units == "arcsecperpix":
            value = 2.0 * math.degrees(math.atan(width / 2.0 * math.tan(math.radians(value / 3600.0))))
        out[name] = value
    return out


def _stored_dtype(image, bit_depth):
    """The image as the file stored it (8 or 16 bits whole numbers), else float32 as read."""
    import numpy as np

    if bit_depth in (8, 16) and image.size:
        lo, hi = float(image.min()), float(image.max())
        if np.array_equal(image, np.round(image)):
            for dtype in (np.uint8, np.uint16, np.int16):
                info = np.iinfo(dtype)
                if (bit_depth == 16 or dtype is np.uint8) and info.min <= lo and hi <= info.max:
                    return image.astype(dtype)
    return image


def _write_outputs(doc, image, path, outputs, result, bit_depth=None):
    """The solved image's WCS, FITS, matched-star CSV, corr and axy tables and picture (each named by ``outputs``
    or None).

    The WCS (``attitude.wcs``, from :func:`startrack.solve.solve_image`) maps pixels to astrometric (catalog)
    positions, as astrometry.net's does, while the attitude is the camera's true orientation.
    """
    wcs_path, plot_path, fits_path, matches_path, corr_path, axy_path = outputs
    keywords = doc["attitude"]["wcs"]
    if wcs_path or fits_path:
        from astropy.io import fits

        from startrack.formats.atomic import atomic_path

        hdr = fits.Header()
        for key, value in keywords.items():
            hdr[key] = value

        if wcs_path:
            with atomic_path(wcs_path, suffix=".fits") as tmp:
                fits.PrimaryHDU(header=hdr).writeto(tmp, overwrite=True)
            doc["solve"]["wcs_path"] = wcs_path
        if fits_path:
            # The image itself with its WCS, like astrometry.net's new-image.fits, in the file's own type.
            full = hdr.copy()
            full["HISTORY"] = f"solved by startrack from {path}"
            with atomic_path(fits_path, suffix=".fits") as tmp:
                fits.PrimaryHDU(data=_stored_dtype(image, bit_depth), header=full).writeto(tmp, overwrite=True)
            doc["solve"]["fits_path"] = fits_path
    if corr_path or axy_path:
        from startrack.formats.fits_tables import write_axy, write_corr

        if corr_path:
            write_corr(corr_path, result)
            doc["solve"]["corr_path"] = corr_path
        if axy_path:
            write_axy(axy_path, result)
            doc["solve"]["axy_path"] = axy_path
    if matches_path:
        _write_matches(matches_path, doc)
        doc["solve"]["matches_path"] = matches_path
    if plot_path:
        from startrack.plot import annotate_solution

        annotate_solution(plot_path, image, doc, catalog=_databases().named_catalog(_catalog_of(doc)), mag_limit=7.0)
        doc["solve"]["plot_path"] = plot_path


@click.command("solve", cls=Command,
               exclusive=[("camera_file", "fov_deg"), ("camera_file", "scale_low"), ("camera_file", "scale_high"),
                          ("fov_deg", "scale_low"), ("fov_deg", "scale_high")],
               ordered=[("scale_low", "scale_high")],
               short_help="Solve photographs: centroid, identify and attitude in one go.")
@click.argument("images", nargs=-1, required=True, metavar="IMAGE...")
@click.option("--fov-deg", type=FiniteFloat(0, 90, min_open=True, max_open=True), default=None, help="Horizontal field of view hint (default: unknown).")
@click.option("--fov-tolerance", type=FiniteFloat(0, 1, max_open=True), default=0.1, show_default=True, help="Relative tolerance of the hint.")
@click.option("--scale-low", type=FiniteFloat(0, None, min_open=True), default=None,
              help="Smallest image scale searched, in --scale-units (as astrometry.net's).")
@click.option("--scale-high", type=FiniteFloat(0, None, min_open=True), default=None,
              help="Largest image scale searched, in --scale-units.")
@click.option("--scale-units", type=click.Choice(["degwidth", "arcsecperpix"]), default="degwidth",
              show_default=True, help="degwidth: the image's width in degrees; arcsecperpix: arcseconds per pixel "
                                      "at the image centre.")
@click.option("--ra", "hint_ra", type=FiniteFloat(0, 360, max_open=True), default=None,
              help="Right ascension (deg, ICRS) near the image's boresight; with --dec and --radius.")
@click.option("--dec", "hint_dec", type=FiniteFloat(-90, 90), default=None,
              help="Declination (deg) near the image's boresight; with --ra and --radius.")
@click.option("--radius", "hint_radius", type=FiniteFloat(0, 180, min_open=True), default=None,
              help="The boresight lies within this many degrees of --ra/--dec: patterns elsewhere are not tried, "
                   "and a solution outside is refused.")
@click.option("--target-pixel", "target_pixels", type=NumberList(length=2), multiple=True, metavar="X,Y",
              help="A pixel (0-based column, row) whose RA/Dec goes into solve.targets; repeatable.")
@click.option("--target-radec", type=NumberList(length=2), multiple=True, metavar="RA,DEC",
              help="A sky position (deg) whose pixel goes into solve.targets; repeatable.")
@click.option("--camera", "camera_file", type=click.Path(dir_okay=False), default=None,
              help="A calibrated camera JSON (then no field-of-view search).")
@click.option("--epoch", type=FiniteFloat(1000, 3000), default=None, help="Epoch of observation (decimal year) for proper motion.")
@apparent_options
@click.option("--utc-offset", type=FiniteFloat(-14, 14), default=None,
              help="Hours local time is ahead of UTC where a photo's EXIF DateTimeOriginal was taken (EXIF has no "
                   "zone; without it an EXIF time is not used).")
@click.option("--timeout-s", type=FiniteFloat(0, 86400, min_open=True), default=5.0, show_default=True,
              help="Give up on an image after this many seconds of search, in CPU time, so that a busy machine "
                   "solves what an idle one does (building a cached database and compiling kernels on first use "
                   "do not count).")
@click.option("--jobs", "-j", type=Int(1, 1024), default=1, show_default=True, help="Images solved in parallel.")
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="Solve on a Dask cluster: 'local' starts a LocalCluster of -j workers here; an address "
                   "(tcp://host:8786) uses a running `dask scheduler` and its workers, which must be able to read "
                   "the images (a shared filesystem).  Needs the [cluster] extra.")
@click.option("--wcs", "wcs_path", type=click.Path(), default=None,
              help="FITS WCS header per image (named after the image when several; {name} = image name).")
@click.option("--plot", type=click.Path(), default=None,
              help="Annotated picture per image (named after the image when several; {name} = image name).")
@click.option("--fits-out", type=click.Path(), default=None,
              help="The image with its WCS as FITS (like astrometry.net's new-image.fits); a directory, a file, "
                   "or a pattern with {name}.")
@click.option("--matches-out", type=click.Path(), default=None,
              help="Matched stars per image as CSV (catalog id, RA/Dec, x/y, residual); a directory, a file, or "
                   "a pattern with {name}.")
@click.option("--corr-out", type=OutputPath(), default=None,
              help="Matched stars per image as a FITS table with astrometry.net's corr.fits columns (field_x, "
                   "field_y, field_ra, field_dec, index_ra, index_dec, index_id, ...); a directory, a file, or a "
                   "pattern with {name}.")
@click.option("--axy-out", type=OutputPath(), default=None,
              help="Detected stars per image as a FITS table of astrometry.net's .axy columns (X, Y, FLUX); a "
                   "directory, a file, or a pattern with {name}.")
@click.option("--catalog", type=click.Choice(["hipparcos", "gaia"]), default=None,
              help="The star pattern index: gaia searches the Gaia DR3 index alone (fields from 0.8 deg, Gaia source "
                   "ids; the extra startrack[gaia]), hipparcos the shipped catalog's alone (fields from 1.5 deg). "
                   "Default: the Hipparcos index, then, when it finds nothing and the field may be under 3 deg, "
                   "the Gaia one (with the extra; first when --fov-deg is under 3).")
@parity_option
@click.option("--projection", type=click.Choice(["auto", "pinhole", "equidistant", "equisolid", "stereographic",
                                                 "orthographic"]), default="auto", show_default=True,
              help="The lens of a blind solve: auto tries a pinhole (fields to about 70 deg), then an all-sky or "
                   "fisheye frame (100-200 deg) with its projection and distortion fitted; pinhole: the first only; "
                   "a fisheye projection: the all-sky search with that projection.")
@calibration_frame_options
@output_option("Frame documents (JSON Lines).")
@resume_option
@click.option("--retry-failed", is_flag=True,
              help="With --resume: solve again the images whose document in the -o file failed; the file is "
                   "rewritten (atomically) without them and their new documents are appended.")
@quiet_option
@handle_errors
def command(images, fov_deg, fov_tolerance, scale_low, scale_high, scale_units, hint_ra, hint_dec, hint_radius,
            target_pixels, target_radec, camera_file, epoch, obs_time, velocity_km_s, no_aberration, utc_offset,
            timeout_s, jobs, scheduler, wcs_path, plot, fits_out, matches_out, corr_out, axy_out, catalog, parity,
            projection, bias, dark, flat, output, resume, retry_failed, quiet):
    """Solve night-sky photographs with no other input.

    Each image is centroided, identified and its attitude solved in one
    process.  The field of view may be unknown (about 2 to 70 degrees, and
    all-sky or fisheye frames of about 100 to 200 degrees: --projection): a
    scale-free index of 4-star patterns, built once from the shipped catalog
    and cached (in $STARTRACK_CACHE, else ~/.cache/startrack; see `startrack
    cache`), identifies the stars and measures the focal length (and, for
    fields over 25 degrees, the radial distortion k1).  A frame document per
    image (JSON Lines) goes to stdout, with a `solve` section: status, fitted
    field of view, the RA/Dec of the image centre (center_ra, center_dec) and
    of the principal point (astrometric, as the WCS), the image's parity (mirrored images are solved
    too: --parity), time.  The image's time (--time, FITS DATE-OBS / MJD-OBS, EXIF
    DateTimeOriginal with --utc-offset) and the camera's velocity give the catalog's apparent
    places (stellar aberration): attitude is the camera's true orientation, attitude.apparent
    records the setting.  An image that cannot be solved is reported on stderr and the batch
    goes on.  Exit status: 0 when every image was solved, 1 when any could not
    be, 2 when any could not be read.

    \b
    Example (a directory of photos, two processes; outputs named after each photo):
      startrack solve photos/*.tiff -j 2 --plot solved/ --fits-out solved/ --matches-out solved/ > solved.jsonl
    \b
    Example (on a Dask cluster: 'local' here, or tcp://HOST:8786 for a running `dask scheduler`;
    rerun with --resume after an interruption):
      startrack solve a.tiff b.tiff --scheduler local -j 2 -o solved.jsonl --resume
    \b
    Example (the same batch again: only the images that failed are solved again, their documents replaced):
      startrack solve a.tiff b.tiff -o solved.jsonl --resume --retry-failed
    \b
    Example (one photo with a field-of-view hint):
      startrack solve sky.tiff --fov-deg 11.4 | jq .solve.center_ra,.solve.center_dec
    \b
    Example (several photos, the WCS of each as sky.wcs-NAME.fits):
      startrack solve a.tiff b.tiff --wcs out/sky.wcs.fits > solved.jsonl
    \b
    Example (hints as astrometry.net's: near Vega, 8 to 15 degrees wide; the RA/Dec of a pixel, the pixel of
    a star, and astrometry.net's corr and axy tables):
      startrack solve sky.tiff --ra 280 --dec 30 --radius 10 --scale-low 8 --scale-high 15 \\
        --target-pixel 100,200 --target-radec 279.23,38.78 --corr-out sky.corr.fits --axy-out sky.axy > sky.json
    \b
    Example (an all-sky camera's frame, rendered here: the projection, focal length and distortion fitted, an
    ARC/ZEA/STG/SIN or ZPN WCS written):
      startrack render --projection equidistant --fov-deg 180 --size 640x640 --ra 80 --dec 40 --mag-max 5.5 \\
          --horizon random --seed 5 -o allsky.png > allsky.json
      startrack solve allsky.png --wcs allsky.wcs.fits | jq -c .camera
    """
    import os

    from startrack.cli.batch import BatchTally
    from startrack.cluster import TaskFailure
    from startrack.errors import BadInputError
    from startrack.formats.atomic import check_writable
    from startrack.formats.frame import FRAME_FORMAT, FrameWriter
    from startrack.progress import ProgressBar
    from startrack.solve import SolveOptions

    if jobs < 1:
        raise BadInputError("--jobs", None, f"must be at least 1, got {jobs}")
    if fov_deg is not None and not 0 < fov_deg < 90:
        raise BadInputError("--fov-deg", None, f"must be in (0, 90), got {fov_deg}")
    if resume and output == "-":
        raise BadInputError("--resume", None, "needs an output file (-o FILE) to resume into")
    if retry_failed and not resume:
        raise BadInputError("--retry-failed", None, "goes with --resume -o FILE: it solves again the failed images "
                                                     "of FILE")
    from startrack.imageio import check_plot_output

    for t in (plot,):
        if t and "{name}" not in t and not t.endswith(("/", os.sep)) and not os.path.isdir(t):
            check_plot_output(t)
    camera_doc = None
    if camera_file:
        camera_doc = load_camera_file(camera_file).to_dict()
    sky = (hint_ra, hint_dec, hint_radius)
    if any(v is not None for v in sky) and any(v is None for v in sky):
        missing = [flag for flag, v in zip(("--ra", "--dec", "--radius"), sky) if v is None]
        raise BadInputError(" ".join(missing), None, "is needed too: --ra, --dec and --radius go together")
    options = SolveOptions(fov_deg=fov_deg, fov_tolerance=fov_tolerance, timeout_s=timeout_s, epoch=epoch,
                           parity=parity, ra_deg=hint_ra, dec_deg=hint_dec, radius_deg=hint_radius,
                           target_pixels=tuple(target_pixels), target_radec=tuple(target_radec), catalog=catalog,
                           projection=projection)
    scale = (scale_low, scale_high, scale_units)
    frames = None
    if bias or dark or flat:
        # Checked here (a bad calibration file is bad usage: exit 2), then read once per worker.
        frames = (tuple(bias), tuple(dark), tuple(flat))
        _calibration(frames)
    n = len(images)
    apparent = (options, apparent_from_options(obs_time, velocity_km_s, no_aberration), utc_offset, scale)
    tasks = [(path, apparent, camera_doc, (output_for(wcs_path, path, n, ".wcs.fits"),
                                          output_for(plot, path, n, ".solved.png"),
                                          output_for(fits_out, path, n, ".new.fits"),
                                          output_for(matches_out, path, n, ".matches.csv"),
                                          output_for(corr_out, path, n, ".corr.fits"),
                                          output_for(axy_out, path, n, ".axy")), frames)
             for path in images]
    for outs in {p for t in tasks for p in t[3] if p}:
        check_writable(outs)
    # The output checked (--resume: this command's documents only) before the index is built or opened.
    writer = FrameWriter(output, resume=resume, section="solve", retry_failed=retry_failed)
    # Build (or open) what the workers need once, before any of them starts.
    if camera_doc is None:
        from startrack.solve import _process_index, index_plan

        # the first index of the search now; the deep one (narrow fields) is built when a frame first needs it
        _process_index(index_plan(options.fov_range(), catalog)[0][0])
    else:
        from startrack.camera import Camera
        from startrack.solve import FOV_BANDS, _band_of

        b = _band_of(Camera.from_dict(camera_doc).fov_deg[0])
        for which in range(len(FOV_BANDS[b][2])):
            _databases(catalog).band_database(b, which=which)
    no_time = NoTimeNotice("solve", NoTimeNotice.IMAGES)
    bar = ProgressBar("solve", quiet)
    tally = BatchTally("solve", quiet, "image")
    todo = [t for t in tasks if not writer.skip({"image": {"path": t[0]}})]
    tally.skipped = n - len(todo)
    if retry_failed:
        tally.notes.append(f"{len(writer.retried)} failed image(s) solved again (--retry-failed)")
    run, progress = todo, None
    if scheduler is not None and todo:
        from startrack.cluster import check_readable_on_workers

        # Workers open the files themselves, from their own working directory: absolute paths,
        # checked up front on every worker (the first unreadable one is named).
        check_readable_on_workers([t[0] for t in todo], scheduler, jobs)
        run = [(os.path.abspath(p), o, c, tuple(os.path.abspath(x) if x else x for x in outs),
                None if fr is None else tuple(tuple(os.path.abspath(x) for x in kind) for kind in fr))
               for p, o, c, outs, fr in todo]
        progress = _cluster_progress(quiet)
    with writer:
        # In input order; with -j N, workers share the pattern index through the page cache.
        for i, doc in _solved(run, jobs, scheduler, progress, writer.base_dir):
            line = None
            if isinstance(doc, SolvedLine):
                doc, line = doc.summary, doc.line
            if isinstance(doc, dict) and run is not todo:
                doc.setdefault("image", {})["path"] = todo[i][0]
            if isinstance(doc, OutputFailure):
                raise BadInputError(doc.source, doc.field, doc.problem)
            if isinstance(doc, TaskFailure):
                doc = {"format": FRAME_FORMAT, "image": {"path": todo[i][0]},
                       "solve": {"status": "failed", "reason": f"internal error: {doc.error}"}}
            no_time(((doc.get("attitude") or {}).get("apparent") or {}).get("aberration"))
            bad = bool(doc["solve"].get("bad_input"))
            if n == 1 and bad:
                raise BadInputError(todo[i][0], None, doc["solve"]["reason"].split(": ", 1)[-1])
            if doc["solve"]["status"] != "ok":
                reason, where = str(doc["solve"].get("reason")), str(todo[i][0])
                tally.error(reason if reason.startswith(where) else f"{where}: {reason}")
            if line is None:
                writer.write(doc)
            else:
                writer.write_line(line)
            tally.add(doc["solve"]["status"], bad=bad)
            bar(i + 1, len(todo))
    tally.finish()
