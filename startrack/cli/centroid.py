"""startrack centroid: detect stars in images and measure their sub-pixel positions."""
import click

from startrack.cli.options import handle_errors, info, load_camera_file, output_option, quiet_option


@click.command("centroid", short_help="Detect and centroid stars in images -> frame documents.")
@click.argument("inputs", nargs=-1, metavar="IMAGE...")
@click.option("--method", type=click.Choice(["com", "iwc", "quine", "gauss"]), default="gauss", show_default=True,
              help="com: centre of mass (paper 000 Eq. 1); iwc: iterative weighted; quine: Gaussian "
                   "interpolation (paper 003 Eqs. 4-6); gauss: 2-D Gaussian least squares.")
@click.option("--threshold-sigma", type=float, default=5.0, show_default=True,
              help="Detection threshold in units of the local background noise.")
@click.option("--threshold-dn", type=float, default=None, help="Fixed threshold in DN above the background instead.")
@click.option("--background", type=click.Choice(["mesh", "global"]), default="mesh", show_default=True)
@click.option("--mesh-px", type=int, default=64, show_default=True, help="Background mesh tile size.")
@click.option("--matched-filter", is_flag=True, help="Detect on a Gaussian-filtered image (fainter stars).")
@click.option("--filter-sigma-px", type=float, default=1.0, show_default=True)
@click.option("--min-pixels", type=int, default=3, show_default=True)
@click.option("--max-pixels", type=int, default=5000, show_default=True)
@click.option("--max-elongation", type=float, default=2.5, show_default=True,
              help="Blobs more elongated than this are flagged as trails, not stars.")
@click.option("--no-deblend", is_flag=True, help="Do not split touching stars.")
@click.option("--max-stars", type=int, default=None, help="Keep the N brightest (paper 000's adaptive selection).")
@click.option("--psf-sigma-px", type=float, default=None, help="PSF sigma (default: measured per star).")
@click.option("--gain-e-per-dn", type=float, default=None, help="Gain, for photon noise in SNR and uncertainties.")
@click.option("--saturation-dn", type=float, default=None, help="Saturation level (default: the file type's maximum).")
@click.option("--camera", "camera_file", type=click.Path(dir_okay=False), default=None,
              help="Camera JSON to attach to every frame.")
@click.option("--windows-from", type=click.Choice(["stars", "truth"]), default=None,
              help="Windowed mode: centroid only around the input document's stars or truth positions.")
@click.option("--window-px", type=int, default=8, show_default=True, help="Window half-size for --windows-from.")
@click.option("--plot", type=click.Path(dir_okay=False), default=None,
              help="Annotated PNG of the detections (numbered per image when several).")
@output_option("Frame documents (JSON Lines).")
@quiet_option
@handle_errors
def command(inputs, method, threshold_sigma, threshold_dn, background, mesh_px, matched_filter, filter_sigma_px,
            min_pixels, max_pixels, max_elongation, no_deblend, max_stars, psf_sigma_px, gain_e_per_dn, saturation_dn,
            camera_file, windows_from, window_px, plot, output, quiet):
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
    from startrack.errors import BadInputError
    from startrack.formats.frame import FRAME_FORMAT, FrameWriter, read_frames, validate_frame
    from startrack.imageio import read_image
    from startrack.progress import ProgressBar

    options = CentroidOptions(method, threshold_sigma, threshold_dn, background, mesh_px, matched_filter,
                              filter_sigma_px, min_pixels, max_pixels, max_elongation, 0.7, not no_deblend, max_stars,
                              psf_sigma_px, gain_e_per_dn, saturation_dn)
    camera_doc = None
    if camera_file:
        pass

        camera_doc = load_camera_file(camera_file).to_dict()
    if plot:
        from startrack.formats.atomic import check_writable

        check_writable(plot)

    def jobs():
        """(source label, frame document or None, image path) for every input."""
        names = list(inputs) or ["-"]
        for name in names:
            looks_like_doc = name == "-" or name.lower().endswith((".json", ".jsonl", ".ndjson"))
            if looks_like_doc:
                for rec in read_frames(name):
                    if rec.error is not None:
                        yield rec.source, None, None, rec.error
                        continue
                    try:
                        validate_frame(rec.doc, rec.source)
                        path = (rec.doc.get("image") or {}).get("path")
                        if not path:
                            raise BadInputError(rec.source, "image.path", "is missing: no image to centroid")
                        yield rec.source, rec.doc, path, None
                    except BadInputError as exc:
                        yield rec.source, rec.doc, None, exc
            else:
                yield name, None, name, None

    all_jobs = list(jobs())
    if len(all_jobs) == 1 and all_jobs[0][3] is not None:
        raise all_jobs[0][3]
    bar = ProgressBar("centroid", quiet)
    n_bad = 0
    n_stars = 0
    with FrameWriter(output) as writer:
        for index, (source, doc, path, error) in enumerate(all_jobs):
            out = dict(doc) if doc else {"format": FRAME_FORMAT}
            out["format"] = FRAME_FORMAT
            try:
                if error is not None:
                    raise error
                image, meta = read_image(path)
                if len(all_jobs) == 1 and doc is None:
                    pass
                height, width = image.shape
                out["image"] = {**(out.get("image") or {}), "path": path, "width": width, "height": height,
                                "bit_depth": meta["bit_depth"]}
                if camera_doc is not None:
                    out["camera"] = camera_doc
                if windows_from:
                    if windows_from == "truth":
                        prior = (doc or {}).get("truth", {}).get("stars", [])
                    else:
                        prior = (doc or {}).get("stars", [])
                    if not prior:
                        raise BadInputError(source, windows_from, "has no positions for --windows-from")
                    found = centroid_windows(image, [(p["x"], p["y"]) for p in prior], window_px, options,
                                             saturation=meta["saturation"])
                    stars = [dict(f, prior=i) for i, f in enumerate(found) if f is not None]
                    stars.sort(key=lambda s: -s["flux"])
                    out["stars"] = stars[:max_stars] if max_stars else stars
                    out["centroid"] = {"method": method, "mode": "windows", "windows": len(prior),
                                       "found": len(stars), "window_px": window_px}
                else:
                    result = find_stars(image, options, saturation=meta["saturation"], source=path)
                    out["stars"] = result.stars
                    out["centroid"] = result.section()
                n_stars += len(out["stars"])
                if plot:
                    from startrack.plot import annotate_stars
                    from startrack.render import numbered_path

                    annotate_stars(numbered_path(plot, index, len(all_jobs)), image, out["stars"],
                                   out["centroid"].get("rejected"), title=f"{os.path.basename(path)}: "
                                   f"{len(out['stars'])} stars ({method})")
            except BadInputError as exc:
                if len(all_jobs) == 1:
                    raise
                n_bad += 1
                info(quiet, f"startrack centroid: {exc}")
                out.setdefault("stars", [])
                out["centroid"] = {"status": "failed", "reason": str(exc)}
                if path and "image" not in out:
                    out["image"] = {"path": path}
            writer.write(out)
            bar(index + 1, len(all_jobs))
    info(quiet, f"centroid: {len(all_jobs)} image(s), {n_stars} stars"
                + (f"; {n_bad} could not be read (status failed in their documents)" if n_bad else ""))
    if n_bad:
        raise SystemExit(2)
