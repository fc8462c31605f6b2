"""startrack attitude: Wahba solvers with uncertainty, residuals, outlier rejection and FITS WCS."""
import json

import click

from startrack.cli.options import (
    Command,
    FiniteFloat,
    NoTimeNotice,
    RegistryChoice,
    apparent_from_options,
    apparent_options,
    attitude_methods,
    catalog_option,
    handle_errors,
    input_argument,
    jobs_option,
    output_option,
    quiet_option,
    resume_option,
)


@click.command("attitude", cls=Command, short_help="Attitude (quaternion, RA/Dec/roll, covariance) from identified stars.")
@input_argument
@click.option("--method", "-m", type=RegistryChoice(attitude_methods),
              default="quest", show_default=True, help="Wahba solver.")
@catalog_option
@click.option("--epoch", type=FiniteFloat(1000, 3000), default=None,
              help="Epoch (decimal year) of the catalog positions; default: image.time, else the render's epoch.")
@apparent_options
@click.option("--sigma-px", type=FiniteFloat(0, 100, min_open=True), default=None,
              help="Centroid noise (1 sigma, px) of every star, instead of each star's own bound (default: from "
                   "flux, PSF and noise, else sigma_px, else 0.5).")
@click.option("--sigma-floor-px", type=FiniteFloat(0, 100), default=0.05, show_default=True,
              help="Smallest per-star centroid sigma (px): calibration and optics limit real images.")
@click.option("--unweighted", is_flag=True, help="Equal weights instead of 1 / sigma^2.")
@click.option("--merge-px", type=FiniteFloat(0, 100), default=2.0, show_default=True,
              help="A star's reference direction is the photocentre of the catalog stars closer than this many "
                   "pixels of the frame's camera (an unresolved double images as one; 0 = the star itself).")
@click.option("--gate", type=FiniteFloat(0, min_open=True), default=13.8, show_default=True,
              help="Chi-square gate (2 dof) on a star's residual; the worst star beyond it is dropped.")
@click.option("--wcs", "wcs_path", type=click.Path(dir_okay=False), default=None,
              help="Write a FITS WCS header (TAN, SIP with distortion); numbered when several frames.")
@output_option()
@jobs_option
@resume_option
@quiet_option
@handle_errors
def command(input, method, catalog, epoch, obs_time, velocity_km_s, no_aberration, sigma_px, sigma_floor_px, unweighted, merge_px, gate, wcs_path, output, jobs,
            resume, quiet):
    """Solve each frame's attitude from its identified stars: adds an `attitude` section.

    Camera-frame vectors come from the star positions and the camera (paper 000
    Eq. 13, distortion removed); ICRS vectors from the catalog by HIP id
    (Eq. 14), with proper motion applied to the frame's epoch, then moved to
    their apparent places for the frame (solar light deflection and stellar
    aberration for the Earth's barycentric velocity at the frame's time plus
    the camera's own, --velocity-km-s or observer.velocity_km_s): the
    attitude is the camera's true orientation in ICRS, while the WCS maps
    pixels to astrometric (catalog) positions.  The time and velocity used are
    in attitude.apparent.  A star with
    catalog companions closer than --merge-px pixels (an unresolved double,
    down to the catalog's faintest) is referred to their photocentre, where
    its centroid lies.  Written:
    status, method, quaternion (scalar last, ICRS -> camera), dcm, ra, dec,
    roll, euler123_deg (yaw, pitch, roll), the Wahba loss (Eq. 15), per-star
    residuals in arcsec, and the QUEST covariance as 1-sigma cross-boresight
    and roll errors in arcsec, beside the frame's Cramér-Rao bound
    (crb_cross_boresight_arcsec, crb_roll_arcsec) from each star's flux, PSF
    width and noise.  Each star is weighted by its own centroid covariance
    (the one centroid's fit reports, cov_px2, else its bound); stars whose
    fit failed its chi-square test (misfit; while 2 and half the stars
    remain) and stars failing the attitude's chi-square gate are dropped and
    listed.  The
    identification is checked, and the frame is "failed" with a reason_code
    when it does not hold up: fewer than 2 stars, a star or id used twice,
    stars too close together to fix the roll, or residuals too large for the
    centroid noise (a wrong identification, catalog or camera).

    \b
    Example (the whole pipeline on a real photo, with a WCS for DS9 or astropy):
      startrack build-kvector --camera cam.json --mag-max 6.5 -o esa.h5
      startrack centroid sky.tiff --camera cam.json | startrack identify -d esa.h5 \\
          | startrack attitude --wcs sky.wcs.fits | jq .attitude.ra,.attitude.dec,.attitude.roll
    """
    import math

    import numpy as np

    from startrack.accuracy import attitude_crb, misfits_to_drop, star_covariance, stars_crb_from_frame
    from startrack.attitude import estimate_attitude, wcs_header
    from startrack.camera import Camera
    from startrack.catalog import load_catalog, merge_radius_arcsec
    from startrack.cli.batch import StreamNames, run_frames
    from startrack.errors import BadInputError
    from startrack.timeutil import julian_year

    if wcs_path:
        from startrack.imageio import check_fits_output

        check_fits_output(wcs_path)
    from startrack.apparent import astrometric_attitude, frame_apparent

    apparent = apparent_from_options(obs_time, velocity_km_s, no_aberration)
    no_time = NoTimeNotice("attitude")
    base = load_catalog(catalog)
    wcs_names = StreamNames(wcs_path)

    def positions_at(ep, ids):
        """``(rows, vectors, catalog rows)`` of the matched stars at epoch ``ep`` (Catalog.positions_of: the
        numbers of the whole catalog moved there, without moving it; the catalog as it is at its own epoch)."""
        return base.positions_of(ids, None if abs(ep - base.epoch) < 1e-9 else ep)

    def photocentres_at(ep, cam, ids):
        """``{id: unit vector}`` of the matched stars that have unresolved companions at this camera's scale."""
        if not merge_px:
            return {}
        return base.photocentres_at(ids, merge_radius_arcsec(cam, merge_px),
                                    None if abs(ep - base.epoch) < 1e-9 else ep)

    def process(doc, source, index, total):  # noqa: ARG001 - the caller's signature
        ident = doc.get("identification")
        if not isinstance(ident, dict):
            raise BadInputError(source, "identification", "is missing: run startrack identify first")
        if "camera" not in doc:
            raise BadInputError(source, "camera", "is missing")
        cam = Camera.from_dict(doc["camera"], source)
        if ident.get("status") != "ok":
            doc["attitude"] = {"status": "failed", "method": method, "reason_code": "not_identified",
                               "reason": f"identification failed: {ident.get('reason', 'no reason given')}"}
            return doc
        stars = doc.get("stars") or []
        matches = ident.get("matches") or []
        if not isinstance(matches, list):
            raise BadInputError(source, "identification.matches", "must be a list")
        for i, m in enumerate(matches):
            if not isinstance(m, dict) or isinstance(m.get("star"), bool) or not isinstance(m.get("star"), int) \
                    or not 0 <= m["star"] < len(stars):
                raise BadInputError(source, f"identification.matches[{i}].star", "must index into stars")
            cid = m.get("id")
            if isinstance(cid, bool) or not isinstance(cid, int):
                raise BadInputError(source, f"identification.matches[{i}].id",
                                    f"must be an integer catalog id, got {json.dumps(cid)[:40]}")
        setting = frame_apparent(doc, apparent, source)
        no_time(setting.aberration)
        ep = epoch
        if ep is None and setting.time.known:
            ep = julian_year(setting.time.time)
        if ep is None and isinstance((doc.get("truth") or {}).get("epoch"), (int, float)):
            ep = float(doc["truth"]["epoch"])
        if ep is None:
            ep = base.epoch
        match_ids = [int(m["id"]) for m in matches]
        rows, vectors, cat_rows = positions_at(ep, match_ids)
        centres = photocentres_at(ep, cam, match_ids)
        gain = _frame_gain(doc)
        noise_frame = (doc.get("centroid") or {}).get("noise_dn")
        body, ref, sig, labels, bounds = [], [], [], [], []
        missing, misfits = [], []
        drop = misfits_to_drop([stars[m["star"]].get("misfit") is True and not sigma_px for m in matches])
        mirrored = ident.get("parity") == "mirrored"
        for m, dropped in zip(matches, drop):
            row = rows.get(int(m["id"]))
            if row is None:
                missing.append(m["id"])
                continue
            s = stars[m["star"]]
            x, y = s.get("x"), s.get("y")
            if not (isinstance(x, (int, float)) and isinstance(y, (int, float)) and math.isfinite(x)
                    and math.isfinite(y)):
                raise BadInputError(source, f"stars[{m['star']}].x", "must be a finite number")
            if dropped:
                # Its fit failed the chi-square test: a neighbour or a distorted image may bias it beyond its sigma.
                misfits.append({"star": int(m["star"]), "id": int(m["id"]),
                                "reason": "centroid fit chi-square "
                                          f"{s.get('fit_chi2', float('nan')):.1f} for {s.get('fit_dof', '?')} dof: "
                                          "not a single star's image"})
                continue
            if mirrored:
                x = 2.0 * cam.cx - x        # identified as the un-mirrored camera's stars (startrack.parity)
            body.append(cam.pixels_to_vectors(x, y))
            ref.append(setting.apparent(centres.get(int(m["id"]), vectors[row]), base.plx[cat_rows[row]]))
            # Each star's own sigma: the covariance its centroid fit reports, else its centroid Cramér-Rao
            # bound from its flux, PSF and noise (startrack.accuracy), else the sigma_px centroid wrote,
            # else --sigma-px.  The bound alone goes into the crb_* fields.
            nd = noise_frame if isinstance(noise_frame, (int, float)) else None
            bound = stars_crb_from_frame([s], gain, nd)[0]
            bounds.append(bound)
            own = star_covariance(s, gain, nd)
            if own is not None and not sigma_px:
                sp = math.sqrt(0.5 * (own[0, 0] + own[1, 1]))
            else:
                sp = s.get("sigma_px")
                sp = sp if isinstance(sp, (int, float)) and sp > 0 else (sigma_px if sigma_px else 0.5)
            sig.append(max(sp, sigma_floor_px) / cam.focal_length_px)
            labels.append((int(m["star"]), int(m["id"])))
        result = estimate_attitude(np.array(body).reshape(-1, 3), np.array(ref).reshape(-1, 3), np.array(sig),
                                   method, labels, gate, not unweighted)
        if result.status == "ok":
            used = [labels.index(u) for u in result.used]
            if all(bounds[k] is not None for k in used):
                try:
                    result.bound = attitude_crb(cam, np.array([body[k] for k in used]),
                                                np.array([bounds[k] for k in used])).section()
                except BadInputError:
                    pass
        section = result.section()
        if misfits:
            section["rejected"] = misfits + section.get("rejected", [])
        section["epoch"] = float(ep)
        section["apparent"] = setting.record()
        if missing:
            section["not_in_catalog"] = missing[:20]
        doc["attitude"] = section
        if result.status == "ok":
            # The WCS maps pixels to astrometric (catalog) positions, as astrometry.net's does.
            wcs_dcm, wcs_cam = astrometric_attitude(result.dcm, cam, setting.state)
        if result.status == "ok" and wcs_path:
            from startrack.formats.atomic import atomic_path
            hdr = wcs_header(wcs_dcm, wcs_cam, mirrored=mirrored)
            path = wcs_names(index)
            from astropy.io import fits

            with atomic_path(path, suffix=".fits") as tmp:
                fits.PrimaryHDU(header=hdr).writeto(tmp, overwrite=True)
            section["wcs_path"] = path
        if result.status == "ok":
            section["wcs"] = {k: v for k, v in wcs_header(wcs_dcm, wcs_cam, mirrored=mirrored).items()
                              if k not in ("COMMENT", "HISTORY")}
        return doc

    run_frames(input, output, "attitude", process, quiet, "attitude", need=("stars",), jobs=jobs, resume=resume)


def _frame_gain(doc):
    """The gain (e/DN) the frame's centroiding used, else the renderer's; None when unknown."""
    for value in (((doc.get("centroid") or {}).get("params") or {}).get("gain_e_per_dn"),
                  (((doc.get("render") or {}).get("params") or {}).get("sensor") or {}).get("gain_e_per_dn")):
        if isinstance(value, (int, float)) and value > 0:
            return float(value)
    return None
