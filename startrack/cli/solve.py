"""startrack solve: photographs in, attitudes out (centroid -> identify -> attitude)."""
import click

from startrack.cli.options import handle_errors, info, load_camera_file, output_option, quiet_option


def _solve_one(args):
    """Worker: solve one image path; returns the frame document (never raises for a bad image)."""
    import time

    from startrack.errors import BadInputError
    from startrack.formats.frame import FRAME_FORMAT
    from startrack.imageio import read_image
    from startrack.solve import solve_image

    path, options, camera_doc, wcs_path, plot_path = args
    t0 = time.perf_counter()
    doc = {"format": FRAME_FORMAT, "image": {"path": path}}
    try:
        image, meta = read_image(path)
    except BadInputError as exc:
        doc["solve"] = {"status": "failed", "reason": str(exc), "bad_input": True}
        return doc
    doc["image"].update(width=image.shape[1], height=image.shape[0], bit_depth=meta["bit_depth"])
    cam = None
    if camera_doc is not None:
        from startrack.camera import Camera

        cam = Camera.from_dict(camera_doc)
    out = solve_image(image, options=options, camera=cam, saturation=meta["saturation"])
    doc.update(out)
    doc["solve"]["time_ms"] = round((time.perf_counter() - t0) * 1000, 3)
    if doc["solve"]["status"] == "ok":
        if wcs_path:
            import numpy as np
            from astropy.io import fits

            from startrack.attitude import wcs_header
            from startrack.camera import Camera
            from startrack.formats.atomic import atomic_path

            hdr = wcs_header(np.asarray(doc["attitude"]["dcm"]), Camera.from_dict(doc["camera"]))
            with atomic_path(wcs_path, suffix=".fits") as tmp:
                fits.PrimaryHDU(header=hdr).writeto(tmp, overwrite=True)
            doc["solve"]["wcs_path"] = wcs_path
        if plot_path:
            from startrack.plot import annotate_solution

            annotate_solution(plot_path, image, doc, mag_limit=7.0)
            doc["solve"]["plot_path"] = plot_path
    return doc


@click.command("solve", short_help="Solve photographs: centroid, identify and attitude in one go.")
@click.argument("images", nargs=-1, required=True, metavar="IMAGE...")
@click.option("--fov-deg", type=float, default=None, help="Horizontal field of view hint (default: unknown).")
@click.option("--fov-tolerance", type=float, default=0.1, show_default=True, help="Relative tolerance of the hint.")
@click.option("--camera", "camera_file", type=click.Path(dir_okay=False), default=None,
              help="A calibrated camera JSON (then no field-of-view search).")
@click.option("--epoch", type=float, default=None, help="Epoch of observation (decimal year) for proper motion.")
@click.option("--timeout-s", type=float, default=5.0, show_default=True,
              help="Give up on an image after this many seconds of search (building a cached database and "
                   "compiling kernels on first use do not count).")
@click.option("--jobs", "-j", type=int, default=1, show_default=True, help="Images solved in parallel.")
@click.option("--wcs", "wcs_path", type=click.Path(dir_okay=False), default=None,
              help="FITS WCS per image (numbered when several).")
@click.option("--plot", type=click.Path(dir_okay=False), default=None,
              help="Annotated picture per image (numbered when several).")
@output_option("Frame documents (JSON Lines).")
@quiet_option
@handle_errors
def command(images, fov_deg, fov_tolerance, camera_file, epoch, timeout_s, jobs, wcs_path, plot, output, quiet):
    """Solve night-sky photographs with no other input.

    Each image is centroided, identified and its attitude solved in one
    process.  The field of view may be unknown: paper 004's scale-free labels
    identify the brightest stars and measure the focal length, then the frame
    is matched in full.  Databases are built on first use from the shipped
    catalog and cached (in $STARTRACK_CACHE, else ~/.cache/startrack).  A
    frame document per image (JSON Lines) goes to stdout, with a `solve`
    section: status, fitted field of view, time.  Failures (not a star field,
    too few stars, timeout) are reported and the batch goes on.

    \b
    Example (a directory of photos, two processes, pictures and WCS files):
      startrack solve photos/*.tiff -j 2 --plot solved/sky.png --wcs solved/sky.wcs.fits > solved.jsonl
    \b
    Example (one photo with a known lens):
      startrack solve sky.tiff --fov-deg 11.4 | jq .attitude.ra,.attitude.dec,.attitude.roll
    """
    import os

    from startrack.errors import BadInputError
    from startrack.formats.atomic import check_writable
    from startrack.formats.frame import FrameWriter
    from startrack.progress import ProgressBar
    from startrack.render import numbered_path
    from startrack.solve import SolveOptions, band_database

    if jobs < 1:
        raise BadInputError("--jobs", None, f"must be at least 1, got {jobs}")
    if fov_deg is not None and not 0 < fov_deg < 90:
        raise BadInputError("--fov-deg", None, f"must be in (0, 90), got {fov_deg}")
    for p in (wcs_path, plot):
        if p:
            check_writable(p)
    camera_doc = None
    if camera_file:
        pass

        camera_doc = load_camera_file(camera_file).to_dict()
    options = SolveOptions(fov_deg=fov_deg, fov_tolerance=fov_tolerance, timeout_s=timeout_s, epoch=epoch)
    n = len(images)
    tasks = [(path, options, camera_doc, numbered_path(wcs_path, i, n) if wcs_path else None,
              numbered_path(plot, i, n) if plot else None) for i, path in enumerate(images)]
    # Build (or open) what the workers need once, before any of them starts.
    if camera_doc is None:
        from startrack.patterns import default_index
        from startrack.solve import _notice

        default_index(notice=_notice)
    else:
        from startrack.camera import Camera
        from startrack.solve import FOV_BANDS, _band_of

        b = _band_of(Camera.from_dict(camera_doc).fov_deg[0])
        for which in range(len(FOV_BANDS[b][2])):
            band_database(b, which=which)
    bar = ProgressBar("solve", quiet)
    n_ok = n_bad = 0
    with FrameWriter(output) as writer:
        if jobs > 1 and n > 1:
            import multiprocessing as mp

            with mp.get_context("spawn").Pool(jobs) as pool:
                results = pool.imap(_solve_one, tasks)
                for i, doc in enumerate(results):
                    n_ok += doc["solve"]["status"] == "ok"
                    n_bad += bool(doc["solve"].get("bad_input"))
                    writer.write(doc)
                    bar(i + 1, n)
        else:
            for i, task in enumerate(tasks):
                doc = _solve_one(task)
                if n == 1 and doc["solve"].get("bad_input"):
                    raise BadInputError(task[0], None, doc["solve"]["reason"].split(": ", 1)[-1])
                n_ok += doc["solve"]["status"] == "ok"
                n_bad += bool(doc["solve"].get("bad_input"))
                if doc["solve"]["status"] != "ok" and not quiet:
                    click.echo(f"startrack solve: {os.path.basename(task[0])}: {doc['solve']['reason']}", err=True)
                writer.write(doc)
                bar(i + 1, n)
    info(quiet, f"solve: {n_ok} of {n} image(s) solved" + (f", {n_bad} unreadable" if n_bad else ""))
    if n_bad:
        raise SystemExit(2)
    if n_ok < n:
        raise SystemExit(1)
