"""startrack centroid: detect stars in images and measure their sub-pixel positions."""
import math

import click

from startrack.cli.options import (
    Command,
    FiniteFloat,
    Int,
    RegistryChoice,
    calibration_frame_options,
    calibration_from_options,
    centroid_methods,
    handle_errors,
    jobs_option,
    load_camera_file,
    output_option,
    quiet_option,
    resume_option,
)


@click.command("centroid", cls=Command, exclusive=[("threshold_sigma", "threshold_dn")],
               ordered=[("min_pixels", "max_pixels")], short_help="Detect and centroid stars in images -> frame documents.")
@click.argument("inputs", nargs=-1, metavar="IMAGE...")
@click.option("--method", "-m", type=RegistryChoice(centroid_methods), default="gauss", show_default=True,
              help="com: centre of mass (paper 000 Eq. 1); iwc: iterative weighted; quine: Gaussian "
                   "interpolation (paper 003 Eqs. 4-6); gauss: 2-D Gaussian least squares.")
@click.option("--threshold-sigma", type=FiniteFloat(0, 1000, min_open=True), default=5.0, show_default=True,
              help="Detection threshold in units of the local background noise.")
@click.option("--threshold-dn", type=FiniteFloat(0, min_open=True), default=None,
              help="Fixed threshold in DN above the background instead.")
@click.option("--background", type=click.Choice(["mesh", "global"]), default="mesh", show_default=True,
              help="mesh: a background per tile, interpolated; global: one level for the image.")
@click.option("--mesh-px", type=Int(4, 100_000), default=64, show_default=True, help="Background mesh tile size.")
@click.option("--matched-filter", is_flag=True, help="Detect on a Gaussian-filtered image (fainter stars).")
@click.option("--filter-sigma-px", type=FiniteFloat(0.1, 50), default=1.0, show_default=True,
              help="Sigma of the --matched-filter Gaussian.")
@click.option("--min-pixels", type=Int(1, 10_000_000), default=3, show_default=True,
              help="Smallest blob (pixels above the threshold) kept as a star.")
@click.option("--max-pixels", type=Int(1, 100_000_000), default=5000, show_default=True,
              help="Largest blob kept as a star.")
@click.option("--max-elongation", type=FiniteFloat(1, 1000), default=2.5, show_default=True,
              help="Blobs more elongated than this are flagged as trails, not stars.")
@click.option("--no-deblend", is_flag=True, help="Do not split touching stars.")
@click.option("--max-stars", type=Int(1, 100_000), default=None, help="Keep the N brightest (paper 000's adaptive selection).")
@click.option("--psf-sigma-px", type=FiniteFloat(0, 50, min_open=True), default=None, help="PSF sigma (default: measured per star).")
@click.option("--gain-e-per-dn", type=FiniteFloat(0, min_open=True), default=None,
              help="Gain, for photon noise in the fit's weights, SNR and uncertainties (default: the render "
                   "section's sensor gain when the input is a rendered frame's document).")
@click.option("--saturation-dn", type=FiniteFloat(0, min_open=True), default=None, help="Saturation level (default: the file type's maximum).")
@click.option("--camera", "camera_file", type=click.Path(dir_okay=False), default=None,
              help="Camera JSON to attach to every frame.")
@click.option("--windows-from", type=click.Choice(["stars", "truth"]), default=None,
              help="Windowed mode: centroid only around the input document's stars or truth positions.")
@click.option("--window-px", type=Int(1, 1000), default=8, show_default=True, help="Window half-size for --windows-from.")
@click.option("--plot", type=click.Path(dir_okay=False), default=None,
              help="Annotated PNG of the detections (numbered per image when several).")
@calibration_frame_options
@output_option("Frame documents (JSON Lines).")
@jobs_option
@resume_option
@quiet_option
@handle_errors
def command(inputs, method, threshold_sigma, threshold_dn, background, mesh_px, matched_filter, filter_sigma_px,
            min_pixels, max_pixels, max_elongation, no_deblend, max_stars, psf_sigma_px, gain_e_per_dn, saturation_dn,
            camera_file, windows_from, window_px, plot, bias, dark, flat, output, jobs, resume, quiet):
    """Find the stars in each image: one frame document per image on stdout.

    IMAGE may be PNG, JPEG, TIFF or FITS (8/12/16-bit; colour becomes
    luminance), or '-' (the default) to read frame documents naming images
    (image.path) on stdin, e.g. from `startrack render`.  Each document gets
    `image` and `stars` (brightest first: x, y, flux, peak, npix, snr,
    sigma_px, fwhm_px, saturated) and a `centroid` section with the settings,
    the background, the time and the rejected detections (hot pixels,
    trails).  An image with no stars gets an empty list and a reason.

    \b
    Example (a real 16-bit night-sky photo, 20 brightest stars, a picture):
      startrack centroid sky.tiff --max-stars 20 --plot sky-stars.png > sky.json
    \b
    Example (the pipeline from rendered frames):
      startrack render --fov-deg 20 --size 1024x1024 --seed 1 -o sky.png | startrack centroid | jq '.stars | length'
    """
    import os

    from startrack.centroid import CentroidOptions, centroid_windows, find_stars
    from startrack.cli.batch import StreamNames, run_frames
    from startrack.errors import BadInputError
    from startrack.formats.frame import FRAME_FORMAT, FrameRecord, read_frame_image, read_frames
    from startrack.imageio import check_plot_output

    options = CentroidOptions(method, threshold_sigma, threshold_dn, background, mesh_px, matched_filter,
                              filter_sigma_px, min_pixels, max_pixels, max_elongation, 0.7, not no_deblend, max_stars,
                              psf_sigma_px, gain_e_per_dn, saturation_dn)
    camera_doc = load_camera_file(camera_file).to_dict() if camera_file else None
    calibration = calibration_from_options(bias, dark, flat)
    check_plot_output(plot)
    plot_names = StreamNames(plot)
    names = list(inputs) or ["-"]
    if sum(n == "-" for n in names) > 1:
        raise BadInputError("IMAGE", None, "standard input ('-') can be read only once")

    def records():
        """One record per input: image files become minimal documents; documents stream in."""
        for name in names:
            if name == "-" or name.lower().endswith((".json", ".jsonl", ".ndjson")):
                yield from read_frames(name)
            else:
                yield FrameRecord(name, {"format": FRAME_FORMAT, "image": {"path": name}})

    n_stars = [0]

    def process(doc, source, index, total):  # noqa: ARG001 - the caller's signature
        # An 8- or 16-bit frame stays as decoded (find_stars takes it so; issue 41), unless it is calibrated.
        image, meta = read_frame_image(doc, source, "no image to centroid", whole_dn=calibration is None)
        path = doc["image"]["path"]
        out = doc
        out["format"] = FRAME_FORMAT
        height, width = image.shape
        out["image"] = {**out["image"], "path": path, "width": width, "height": height,
                        "bit_depth": meta["bit_depth"]}
        if calibration is not None:
            image, meta["saturation"] = calibration.apply(image, meta["saturation"], path)
            out["image"]["calibration"] = calibration.record()
        if camera_doc is not None:
            out["camera"] = camera_doc
        if windows_from:
            prior = (doc.get("truth") or {}).get("stars", []) if windows_from == "truth" else doc.get("stars", [])
            if not prior:
                raise BadInputError(source, windows_from, "has no positions for --windows-from")
            field = "truth.stars" if windows_from == "truth" else "stars"
            if not isinstance(prior, list):
                raise BadInputError(source, field, "must be a list of stars")
            for i, p in enumerate(prior):
                for axis in ("x", "y"):
                    v = p.get(axis) if isinstance(p, dict) else None
                    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                        raise BadInputError(source, f"{field}[{i}].{axis}", "must be a finite number (a position "
                                                                             "for --windows-from)")
            found = centroid_windows(image, [(p["x"], p["y"]) for p in prior], window_px,
                                     _with_render_gain(options, doc), saturation=meta["saturation"])
            stars = [dict(f, prior=i) for i, f in enumerate(found) if f is not None]
            stars.sort(key=lambda s: -s["flux"])
            out["stars"] = stars[:max_stars] if max_stars else stars
            out["centroid"] = {"method": method, "mode": "windows", "windows": len(prior),
                               "found": len(stars), "window_px": window_px}
        else:
            result = find_stars(image, _with_render_gain(options, doc), saturation=meta["saturation"], source=path)
            out["stars"] = result.stars
            out["centroid"] = result.section()
        n_stars[0] += len(out["stars"])
        if plot:
            from startrack.plot import annotate_stars

            annotate_stars(plot_names(index), image.astype("float32", copy=False), out["stars"],
                           out["centroid"].get("rejected"),
                           title=f"{os.path.basename(path)}: {len(out['stars'])} stars ({method})")
        return out

    run_frames(names[0] if len(names) == 1 else "-", output, "centroid", process, quiet, "centroid",
               jobs=jobs, resume=resume, records=records(), unit="image",
               note=lambda: f"{n_stars[0]} stars")


def _with_render_gain(options, doc):
    """The options with the gain of the document's ``render`` section when --gain-e-per-dn was not given.

    A rendered frame says which sensor made it; with its gain each star's shot
    noise enters the weighted fit, its covariance and its SNR.  The read noise
    needs no reading: it is part of the background noise centroid measures.
    """
    from dataclasses import replace

    if options.gain_e_per_dn is not None:
        return options
    render = doc.get("render") if isinstance(doc.get("render"), dict) else {}
    params = render.get("params") if isinstance(render.get("params"), dict) else {}
    sensor = params.get("sensor") if isinstance(params.get("sensor"), dict) else {}
    gain = sensor.get("gain_e_per_dn")
    if isinstance(gain, (int, float)) and not isinstance(gain, bool) and math.isfinite(gain) and gain > 0:
        return replace(options, gain_e_per_dn=float(gain))
    return options
