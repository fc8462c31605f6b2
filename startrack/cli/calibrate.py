"""startrack calibrate: focal length, principal point and distortion from identified frames."""
import click

from startrack.cli.options import Command, NameList, catalog_option, handle_errors, info, input_argument, quiet_option


@click.command("calibrate", cls=Command, short_help="Fit focal length, principal point and k1, k2 from solved frames.")
@input_argument
@click.option("--output", "-o", required=True, type=click.Path(dir_okay=False), help="Camera JSON to write.")
@click.option("--fit", type=NameList(lambda: ["auto", "focal_length_px", "cx", "cy", "k1", "k2", "k3", "k4"],
                                     as_text=True),
              default="auto", show_default=True,
              help="Parameters to fit (focal_length_px,cx,cy,k1,k2; a fisheye also k3,k4), or auto: all of them, then "
                   "those the data do not constrain (under 3 sigma from no distortion / the image centre) left out.")
@click.option("--projection", type=click.Choice(["auto", "pinhole", "equidistant", "equisolid", "stereographic",
                                                 "orthographic"]), default=None,
              help="The lens projection to fit (default: the frames' camera's); auto: each one the stars allow, "
                   "the one of least BIC (residual with a ln(n) penalty per parameter) kept.")
@catalog_option
@quiet_option
@handle_errors
def command(input, output, fit, projection, catalog, quiet):
    """Calibrate the camera from frames with identification and attitude (paper 000's ground calibration).

    A least-squares bundle adjustment over all frames: the camera intrinsics
    and a small attitude correction per frame.  By default (--fit auto) a
    parameter the data do not constrain (k2, k1, the principal point: under 3
    sigma from no distortion or the image centre) is left out and fixed at its
    default; every parameter's significance is reported.  Writes a startrack.camera/1
    JSON with the fitted values, their 1-sigma uncertainties, the residual RMS
    before and after, and the field of view with its uncertainty.

    \b
    Example (8 photos solved, then calibrated, then solved again with the calibrated camera):
      startrack solve photos/*.tiff > solved.jsonl
      startrack calibrate solved.jsonl -o lens.json
      startrack solve photos/*.tiff --camera lens.json > solved2.jsonl
    \b
    Example (an all-sky camera, rendered here: which projection, and its distortion):
      startrack render --projection equisolid --fov-deg 160 --size 640x640 --ra 30 --dec 50 --mag-max 5.5 \\
          --seed 1 -o allsky.png > allsky.json
      startrack solve allsky.png > allsky-solved.jsonl
      startrack calibrate allsky-solved.jsonl --projection auto -o allsky-lens.json
    """
    import json
    import math

    import numpy as np

    from startrack.calibrate import PARAMS, calibrate, calibrate_projection, calibrate_significant
    from startrack.camera import Camera
    from startrack.catalog import load_catalog
    from startrack.errors import BadInputError
    from startrack.formats.atomic import atomic_open, check_writable
    from startrack.formats.frame import read_frames, validate_attitude, validate_frame

    check_writable(output)
    base = load_catalog(catalog)
    frames = []
    camera = None
    for rec in read_frames(input):
        if rec.error is not None:
            raise rec.error
        doc = validate_frame(rec.doc, rec.source)
        att = doc.get("attitude") or {}
        ident = doc.get("identification") or {}
        if att.get("status") != "ok" or ident.get("status") != "ok":
            continue                    # unsolved frames carry nothing to calibrate from
        validate_frame(doc, rec.source, ("camera", "stars", "identification"))
        if "matches" not in ident:
            raise BadInputError(rec.source, "identification.matches", "is missing: an identified frame's matches are "
                                "what calibrate fits")
        if "mirrored" in (ident.get("parity"), (doc.get("solve") or {}).get("parity")):
            # Its camera is the un-mirrored one of flipped pixels: a principal point fitted from it would not be
            # the image's.
            raise BadInputError(rec.source, "identification.parity", "is mirrored: calibrate takes unmirrored "
                                "frames only (flip the images first)")
        dcm = validate_attitude(doc, rec.source)  # a zero quaternion is bad input, never skipped
        cam = Camera.from_dict(doc["camera"], rec.source)
        if camera is None:
            camera = cam
        elif (cam.width, cam.height) != (camera.width, camera.height):
            raise BadInputError(rec.source, "camera", "frames of different image sizes cannot share a calibration")
        ep = att.get("epoch", base.epoch)
        if isinstance(ep, bool) or not isinstance(ep, (int, float)) or not math.isfinite(ep):
            raise BadInputError(rec.source, "attitude.epoch", f"must be a decimal year, got {json.dumps(ep)[:40]}")
        ep = float(ep)
        # The matched stars at the frame's epoch (Catalog.positions_of: the whole catalog's numbers there, without
        # moving and keeping a copy of it for every epoch: 100 ms and 15.6 MB a frame of its own time).
        rows, vec, _ = base.positions_of([int(m["id"]) for m in ident.get("matches", [])],
                                         None if abs(ep - base.epoch) < 1e-9 else ep)
        xy, ref = [], []
        for m in ident.get("matches", []):
            k = rows.get(int(m["id"]))
            if k is None:
                continue
            s = doc["stars"][m["star"]]
            for axis, size in (("x", cam.width), ("y", cam.height)):
                if not -size <= s[axis] <= 2 * size:   # an absurd position would make the fit inf, not fail
                    raise BadInputError(rec.source, f"stars[{m['star']}].{axis}", f"{s[axis]:g} is far outside the "
                                        f"image (0..{size}); an identified star must be on it")
            xy.append((s["x"], s["y"]))
            ref.append(vec[k])
        frames.append((dcm, np.array(xy), np.array(ref)))
    if camera is None:
        raise BadInputError(input, "attitude", "no frame with a solved attitude to calibrate from")
    names = PARAMS if fit.strip() == "auto" else [p.strip() for p in fit.split(",") if p.strip()]
    if projection == "auto" or (projection is not None and projection != camera.projection):
        if fit.strip() != "auto":
            raise BadInputError("--projection", None, "a projection to fit needs --fit auto (its terms are chosen "
                                "by their significance)")
    try:
        if projection == "auto" or (projection is not None and projection != camera.projection):
            result = calibrate_projection(frames, camera, None if projection == "auto" else [projection])
        elif fit.strip() == "auto":
            result = calibrate_significant(frames, camera)
        else:
            result = calibrate(frames, camera, names)
    except BadInputError as exc:
        if exc.source != "frames":
            raise
        raise BadInputError(input, exc.field, exc.problem) from None     # the frames are the input file's
    doc = result.to_dict()
    with atomic_open(output, "w") as fh:
        json.dump(doc, fh, indent=1)
    c = doc["calibration"]
    info(quiet, f"calibrate: {result.n_frames} frame(s), {result.n_stars} stars; f = {result.camera.focal_length_px:.2f}"
                f" +- {result.sigma.get('focal_length_px', 0):.2f} px, FOV {c['fov_deg'][0]:.4f} x {c['fov_deg'][1]:.4f} deg; "
                f"residual RMS {c['rms_residual_before_arcsec']:.2f}\" -> {c['rms_residual_after_arcsec']:.2f}\" -> {output}")
    if not quiet:
        sig = c.get("significance_sigma", {})
        if result.projections:
            for name, row in result.projections.items():
                text = (f"BIC {row['bic']:.1f}, RMS {row['rms_px']:.3f} px" if "bic" in row else row["error"])
                click.echo(f"  {'*' if name == result.camera.projection else ' '} {name:14s} {text}", err=True)
        for name in PARAMS:
            if name in result.sigma:
                click.echo(f"  {name:16s} {getattr(result.camera, name):14.6g} +- {result.sigma[name]:.3g}"
                           + (f"  ({sig[name]:.1f} sigma)" if name in sig else ""), err=True)
            elif result.dropped and name in result.dropped:
                click.echo(f"  {name:16s} not fitted: {result.dropped[name]:.1f} sigma, not significant", err=True)
