"""Cramér-Rao bounds: a star's centroid and a frame's attitude (issue 21).

Centroid bound (per star).  The star is the pixel-integrated Gaussian the
renderer draws (paper 003 Eqs. 4-5): pixel ``k`` expects
``mu_k = F gx_k(x) gy_k(y)`` electrons above the background, with
``gx_k(x) = [erf((k + 1/2 - x) / (sqrt 2 s)) - erf((k - 1/2 - x) / (sqrt 2 s))] / 2``.
Its noise is Poisson (star and background shot noise) plus Gaussian read
noise, so its variance is ``mu_k + v`` with ``v = B + r^2`` (background
electrons plus read-noise variance per pixel).  With the Gaussian
approximation of that noise the Fisher information of ``theta = (x, y, F)`` is

    I_ab = sum_k (d mu_k / d theta_a) (d mu_k / d theta_b) / (mu_k + v)

(Kay 1993, Eq. 3.31, the variance's own dependence on ``theta`` neglected as
usual for shot-noise-limited centroiding).  The flux ``F`` is unknown and
estimated with the position, so the bound on ``(x, y)`` is the upper-left
2 x 2 block of ``I^-1`` (a nuisance parameter can only widen it); the
background level and the PSF width are taken as known (they come from the
whole frame or from calibration).

Attitude bound (per frame).  A small rotation ``dtheta`` of the camera frame
moves star ``i``'s image by ``H_i dtheta`` (``H_i`` the 2 x 3 Jacobian of the
camera projection, distortion included, taken numerically); with the centroid
bounds ``C_i`` (2 x 2, px^2) the attitude's Fisher information is the sum of
the stars' projected information ``J = sum_i H_i^T C_i^-1 H_i`` and the bound
is ``P = J^-1`` (rad^2, camera frame: x and y cross-boresight, z roll).  For a
pinhole camera and isotropic ``C_i = s_i^2 I`` this tends to the QUEST
covariance ``[sum_i (I - b_i b_i^T) / (s_i / f)^2]^-1`` (Shuster & Oh 1981)
as the field narrows.
"""
from __future__ import annotations

import math

import numpy as np

from startrack.errors import BadInputError, ParameterError

__all__ = [
    "AttitudeBound",
    "attitude_crb",
    "attitude_fisher",
    "blended_references",
    "centroid_crb",
    "centroid_crb_px",
    "error_vector",
    "frame_bound",
    "misfits_to_drop",
    "projection_jacobian",
    "reference_stars",
    "star_covariance",
    "star_snr",
    "stars_crb_from_frame",
    "startrack_frame",
    "summarise",
]

_SQRT2 = math.sqrt(2.0)
_ARCSEC = math.degrees(1.0) * 3600.0
_erf = np.vectorize(math.erf, otypes=[np.float64])


def _fractions(centre, sigma, lo, n):
    """Pixel fractions ``g_k`` and their derivatives ``d g_k / d centre`` for pixels lo..lo+n-1."""
    edges = lo + np.arange(n + 1) - 0.5
    z = (edges - centre) / (_SQRT2 * sigma)
    cdf = 0.5 * _erf(z)
    dens = np.exp(-z * z) / (math.sqrt(2.0 * math.pi) * sigma)
    return np.diff(cdf), -(np.diff(dens))


def centroid_crb(flux_e, sigma_psf_px, noise_var_e, x=0.0, y=0.0, flux_known=False):
    """Cramér-Rao bound on a star's position: the 2 x 2 covariance (px^2).

    Parameters
    ----------
    flux_e : float
        The star's total signal (electrons; or DN when ``noise_var_e`` is in
        DN^2 and shot noise is folded into it, see :func:`stars_crb_from_frame`).
    sigma_psf_px : float
        Gaussian PSF sigma (px), before pixel integration.
    noise_var_e : float
        Variance per pixel not due to the star: background electrons plus read
        noise squared (e^2).
    x, y : float
        Sub-pixel position (only the phase matters: the bound depends on where
        the star falls inside its pixel).
    flux_known : bool
        Treat the flux as known (the tighter, fixed-flux bound).

    Returns
    -------
    ndarray (2, 2)
        Lower bound on the covariance of any unbiased ``(x, y)`` estimate, px^2.
    """
    f = float(flux_e)
    s = float(sigma_psf_px)
    v = float(noise_var_e)
    if not (math.isfinite(f) and f > 0 and math.isfinite(s) and s > 0 and math.isfinite(v) and v >= 0):
        raise BadInputError("centroid_crb", None, f"needs flux > 0, PSF sigma > 0, noise variance >= 0; got "
                                                   f"{flux_e!r}, {sigma_psf_px!r}, {noise_var_e!r}")
    half = math.ceil(6.0 * s) + 2
    n = 2 * half + 1
    xi = math.floor(x + 0.5)
    yi = math.floor(y + 0.5)
    gx, dgx = _fractions(x, s, xi - half, n)
    gy, dgy = _fractions(y, s, yi - half, n)
    mu = f * np.outer(gy, gx)
    var = mu + v
    if v == 0:
        var = np.maximum(var, 1e-300)
    d_x = f * np.outer(gy, dgx)
    d_y = f * np.outer(dgy, gx)
    d_f = np.outer(gy, gx)
    grads = (d_x, d_y, d_f)
    info = np.array([[float(np.sum(a * b / var)) for b in grads] for a in grads])
    if flux_known:
        return np.linalg.inv(info[:2, :2])
    return np.linalg.inv(info)[:2, :2]


def centroid_crb_px(flux_e, sigma_psf_px, noise_var_e, x=0.0, y=0.0, flux_known=False):
    """Per-axis 1-sigma centroid bound (px): ``sqrt(trace(C) / 2)`` of :func:`centroid_crb`."""
    c = centroid_crb(flux_e, sigma_psf_px, noise_var_e, x, y, flux_known)
    return math.sqrt(0.5 * (c[0, 0] + c[1, 1]))


def projection_jacobian(camera, body, step_rad=1e-6):
    """``H_i = d (x_i, y_i) / d dtheta`` (px / rad), shape (n, 2, 3).

    ``dtheta`` is a small rotation of the camera frame: a direction ``b``
    becomes ``b - dtheta x b`` in camera coordinates.  Central differences of
    :meth:`Camera.vectors_to_pixels`, so any distortion model is included.
    """
    b = np.asarray(body, dtype=np.float64).reshape(-1, 3)
    h = np.empty((len(b), 2, 3))
    for k in range(3):
        e = np.zeros(3)
        e[k] = step_rad
        plus = b - np.cross(e, b)
        minus = b + np.cross(e, b)
        xp, yp = camera.vectors_to_pixels(plus / np.linalg.norm(plus, axis=1, keepdims=True))
        xm, ym = camera.vectors_to_pixels(minus / np.linalg.norm(minus, axis=1, keepdims=True))
        h[:, 0, k] = (xp - xm) / (2 * step_rad)
        h[:, 1, k] = (yp - ym) / (2 * step_rad)
    return h


def attitude_fisher(camera, body, star_cov_px2):
    """Fisher information of the attitude, ``J = sum_i H_i^T C_i^-1 H_i`` (rad^-2).

    ``star_cov_px2`` is (n, 2, 2) or (n,) (isotropic variances, px^2).
    """
    h = projection_jacobian(camera, body)
    c = np.asarray(star_cov_px2, dtype=np.float64)
    if c.ndim == 1:
        c = c[:, None, None] * np.eye(2)[None]
    cinv = np.linalg.inv(c)
    return np.einsum("nia,nij,njb->ab", h, cinv, h)


class AttitudeBound:
    """The attitude Cramér-Rao bound of one frame (rad^2 covariance, camera frame)."""

    def __init__(self, cov_rad2):
        self.cov_rad2 = np.asarray(cov_rad2, dtype=np.float64)

    @property
    def pitch_yaw_rad(self):
        return math.sqrt(self.cov_rad2[0, 0]), math.sqrt(self.cov_rad2[1, 1])

    @property
    def cross_boresight_rad(self):
        """Per-axis cross-boresight bound, ``sqrt((P_xx + P_yy) / 2)``."""
        return math.sqrt(0.5 * (self.cov_rad2[0, 0] + self.cov_rad2[1, 1]))

    @property
    def roll_rad(self):
        return math.sqrt(self.cov_rad2[2, 2])

    def section(self) -> dict:
        """Fields for the frame document's attitude section (arcsec)."""
        return {"crb_cross_boresight_arcsec": self.cross_boresight_rad * _ARCSEC,
                "crb_pitch_yaw_arcsec": [v * _ARCSEC for v in self.pitch_yaw_rad],
                "crb_roll_arcsec": self.roll_rad * _ARCSEC}


def attitude_crb(camera, body, star_cov_px2) -> AttitudeBound:
    """Attitude Cramér-Rao bound from the stars' directions and centroid bounds.

    Parameters
    ----------
    camera : startrack.camera.Camera
    body : array (n, 3)
        Camera-frame unit vectors of the stars used.
    star_cov_px2 : array (n, 2, 2) or (n,)
        Each star's centroid bound (:func:`centroid_crb`), px^2.

    Returns
    -------
    AttitudeBound
        ``None``-free: raises :class:`BadInputError` when the geometry carries
        no information about some axis (fewer than two distinct directions).
    """
    j = attitude_fisher(camera, body, star_cov_px2)
    if not np.all(np.isfinite(j)) or np.linalg.cond(j) > 1e12:
        raise BadInputError("attitude_crb", None, "the stars do not determine all three axes")
    return AttitudeBound(np.linalg.inv(j))


def stars_crb_from_frame(stars, gain_e_per_dn=None, noise_dn=None):
    """Centroid bounds (n, 2, 2 px^2) of a frame document's stars, from what centroid measured.

    Each star needs ``x``, ``y``, ``flux`` (DN above the background) and a PSF
    width (``psf_sigma_px``, else ``fwhm_px / 2.3548``); its per-pixel noise is
    its own ``noise_dn`` (the background noise where it lies), else the
    frame's ``noise_dn``.  The computation runs in DN: a pixel's variance is
    ``mu_k / g + n^2`` with ``g`` the gain (e/DN), so that the shot noise of the
    star is included when the gain is known (otherwise only the background
    noise ``n^2`` is, which understates the bound of bright stars).
    Returns ``None`` for a star lacking any of these.
    """
    out = []
    for s in stars:
        flux = s.get("flux")
        sig = s.get("psf_sigma_px")
        if not isinstance(sig, (int, float)) and isinstance(s.get("fwhm_px"), (int, float)):
            sig = s["fwhm_px"] / 2.3548
        nd = s.get("noise_dn", noise_dn)
        ok = all(isinstance(v, (int, float)) and math.isfinite(v) for v in (flux, sig, nd, s.get("x"), s.get("y")))
        if not ok or flux <= 0 or sig <= 0 or nd < 0:
            out.append(None)
            continue
        if gain_e_per_dn:
            # Work in electrons: F g electrons, (n g)^2 e^2 per pixel; convert back to px (unitless).
            cov = centroid_crb(flux * gain_e_per_dn, sig, (nd * gain_e_per_dn) ** 2, s["x"], s["y"])
        else:
            cov = centroid_crb(flux, sig, max(nd * nd, 1e-12), s["x"], s["y"])
        out.append(cov)
    return out


def star_snr(flux_e, sigma_psf_px, noise_var_e):
    """``SNR = F / sqrt(F + 4 pi s^2 v)`` (the optimal-aperture SNR of :mod:`startrack.centroid_accuracy`)."""
    f = np.asarray(flux_e, dtype=np.float64)
    return f / np.sqrt(f + 4.0 * math.pi * sigma_psf_px**2 * noise_var_e)


def blended_references(catalog, render_catalog, camera, merge_px=None):
    """The identification catalog's stars at the directions the sensor sees them.

    Stars closer than ``merge_px`` pixels (default
    :data:`startrack.catalog.DEFAULT_MERGE_PX`, two PSF sigmas) image as one
    blob whose centroid is the group's photocentre, not the brighter star:
    the rendered (deeper) catalog is merged
    (:meth:`startrack.catalog.Catalog.merge_close`) and the entries whose id
    is in ``catalog`` are kept, at their photocentre with their summed
    brightness.  A star's companions fainter than the identification
    catalog's limit still move its centroid, so the reference must know them.
    """
    from startrack.catalog import DEFAULT_MERGE_PX, merge_radius_arcsec

    merged = render_catalog.merge_close(merge_radius_arcsec(camera, DEFAULT_MERGE_PX if merge_px is None else merge_px))
    ids = {int(i) for i in catalog.id}
    return merged.subset(np.array([int(i) in ids for i in merged.id], dtype=bool))


def reference_stars(camera, dcm, catalog, sensor, vectors=None, focal_length_px=None):
    """The identification catalog's stars as the sensor sees them at attitude ``dcm``: truth-like dicts.

    ``x``, ``y`` (the catalog direction projected, at ``focal_length_px`` when
    the frame was rendered with another focal length), ``electrons`` (from the
    catalog magnitude), ``id`` and ``saturated`` (the brightest pixel over the
    full well), for the entries inside the image.  With a catalog whose
    unresolved doubles are merged (:meth:`startrack.catalog.Catalog.merge_close`
    on the deeper catalog that was rendered) an entry is the photocentre and
    the summed brightness of its group: what the centroider measures.
    """
    from startrack.render import _peak_fraction, electrons_from_magnitude, project_stars

    cam = camera if focal_length_px is None else camera.with_focal_length(focal_length_px)
    vec = catalog.vectors() if vectors is None else vectors
    index, x, y = project_stars(vec, dcm, cam)
    e = electrons_from_magnitude(catalog.mag[index], sensor)
    sat = e * _peak_fraction(sensor.psf_sigma_px) + sensor.background_e >= sensor.full_well_e
    return [{"id": int(catalog.id[i]), "x": float(a), "y": float(b), "electrons": float(c), "saturated": bool(d)}
            for i, a, b, c, d in zip(index, x, y, e, sat)]


def frame_bound(camera, truth_stars, sensor, ids=None, max_stars=None, min_snr=5.0):
    """The frame's own attitude bound: the Cramér-Rao bound of the stars a tracker could use.

    Those are the stars of ``truth_stars`` (the rendered stars of
    :func:`startrack.render.render_image`, or :func:`reference_stars`) whose id
    is in ``ids`` (the identification catalog; all when ``None``), not
    saturated, inside the image, with SNR >= ``min_snr``; the ``max_stars``
    brightest of them.  Each contributes its centroid bound (true electrons,
    the sensor's background and read noise, its PSF, its pixel phase).
    Returns ``(AttitudeBound or None, n_stars)``.
    """
    v = sensor.background_e + sensor.read_noise_e**2
    s = sensor.psf_sigma_px
    keep = [t for t in truth_stars if (ids is None or int(t["id"]) in ids) and not t.get("saturated")
            and -0.5 <= t["x"] <= camera.width - 0.5 and -0.5 <= t["y"] <= camera.height - 0.5
            and star_snr(t["electrons"], s, v) >= min_snr]
    keep.sort(key=lambda t: -t["electrons"])
    keep = keep[:max_stars] if max_stars else keep
    if len(keep) < 2:
        return None, len(keep)
    covs = np.array([centroid_crb(t["electrons"], s, v, t["x"], t["y"]) for t in keep])
    body = camera.pixels_to_vectors(np.array([t["x"] for t in keep]), np.array([t["y"] for t in keep]))
    try:
        return attitude_crb(camera, body, covs), len(keep)
    except BadInputError:
        return None, len(keep)


def star_covariance(star, gain_e_per_dn=None, noise_dn=None):
    """The covariance (2 x 2, px^2) of a star's centroid as its estimator reports it, else its bound.

    ``cov_px2`` is what centroid's weighted fit reports: the inverse of its own
    information over the pixels it fitted, with the PSF width and the local
    background estimated alongside, so that a star cut by the image edge has
    the larger sigma it really has.  Without it (another centroid method, an
    older document) the centroid bound from the measured flux, PSF and noise
    (:func:`stars_crb_from_frame`).  ``None`` when neither is known.
    """
    c = star.get("cov_px2")
    if isinstance(c, (list, tuple)) and len(c) == 2:
        try:
            m = np.array(c, dtype=np.float64).reshape(2, 2)
        except (TypeError, ValueError):
            m = None
        if m is not None and np.all(np.isfinite(m)) and m[0, 0] > 0 and m[1, 1] > 0 and np.linalg.det(m) > 0:
            return m
    return stars_crb_from_frame([star], gain_e_per_dn, noise_dn)[0]


def misfits_to_drop(flags):
    """Which stars to leave out of the attitude for their centroid fit's failed chi-square test.

    ``flags[i]`` is star ``i``'s ``misfit``.  They are left out while at least
    two stars and at least half of them remain; when the misfits are the
    majority the frame's PSF is not the model (optics, not neighbours), and
    all are kept for the attitude's own gate to judge.  Returns a boolean list.
    """
    flags = [bool(f) for f in flags]
    good = len(flags) - sum(flags)
    if good >= 2 and good >= math.ceil(len(flags) / 2):
        return flags
    return [False] * len(flags)


def startrack_frame(image, truth, camera, sensor, ref_rows, ref_vectors, max_stars=None, gate=13.8,
                    sigma_floor_px=0.0, max_match_px=1.0, identify=None):
    """startrack's estimate on one rendered frame: centroid (gain known), identification, attitude.

    With ``identify=None`` the identification is taken from the truth: each
    detection within ``max_match_px`` of an identification-catalog entry
    projected at the true attitude (``truth["quaternion"]``, its focal length)
    gets that entry's id, so that this measures accuracy, not identification;
    otherwise ``identify(stars)`` returns a list of ``(star index, catalog id)``
    or ``None`` (failed).  Each star is weighted by the covariance its
    centroid reports (:func:`star_covariance`); stars whose fit fails its
    chi-square test (``misfit``: a neighbour in the window, a distorted
    image) are left out as :func:`misfits_to_drop` says.  Returns the
    :class:`startrack.attitude.AttitudeResult`, or ``None`` when fewer than 2
    stars are identified.
    """
    from startrack.attitude import estimate_attitude
    from startrack.centroid import CentroidOptions, find_stars
    from startrack.rotations import quaternion_to_dcm

    res = find_stars(image, CentroidOptions(gain_e_per_dn=sensor.gain), saturation=sensor.max_dn)
    if identify is not None:
        pairs = identify(res.stars)
        if pairs is None:
            return None
    else:
        pairs = []
        ids = np.empty(len(ref_rows), dtype=np.int64)
        rows = np.empty(len(ref_rows), dtype=np.int64)
        for j, (tid, row) in enumerate(ref_rows.items()):
            ids[j], rows[j] = tid, row
        dcm = quaternion_to_dcm(np.asarray(truth["quaternion"], dtype=np.float64))
        cam = camera.with_focal_length(truth.get("focal_length_px", camera.focal_length_px))
        from startrack.render import project_stars

        index, tx, ty = project_stars(np.asarray(ref_vectors)[rows], dcm, cam, margin_px=2.0 * max_match_px)
        tids = ids[index]
        seen = set()
        for k, s in enumerate(res.stars):
            if s.get("saturated") or not len(tx):
                continue
            d = np.hypot(tx - s["x"], ty - s["y"])
            j = int(np.argmin(d))
            tid = int(tids[j])
            if d[j] <= max_match_px and tid not in seen:
                seen.add(tid)
                pairs.append((k, tid))
    body, ref, sig, labels = [], [], [], []
    pairs = [(k, tid) for k, tid in pairs if not res.stars[k].get("saturated") and tid in ref_rows]
    drop = misfits_to_drop([res.stars[k].get("misfit") for k, _ in pairs])
    for (k, tid), dropped in zip(pairs, drop):
        s = res.stars[k]
        cov = star_covariance(s, sensor.gain, res.background_sigma)
        if cov is None or dropped:
            continue
        body.append(camera.pixels_to_vectors(s["x"], s["y"]))
        ref.append(ref_vectors[ref_rows[tid]])
        sig.append(max(math.sqrt(0.5 * (cov[0, 0] + cov[1, 1])), sigma_floor_px) / camera.focal_length_px)
        labels.append((k, tid))
        if max_stars and len(body) >= max_stars:
            break
    if len(body) < 2:
        return None
    return estimate_attitude(np.array(body), np.array(ref), np.array(sig), "quest", labels, gate)


def evaluate_accuracy(camera, catalog, n, seed, sensor=None, render_catalog=None, identify=None, max_stars=None,
                      progress=None, merge_px=None, done=(), on_frame=None):
    """Attitude error against each frame's Cramér-Rao bound over ``n`` rendered frames.

    Parameters
    ----------
    camera : Camera
    catalog : Catalog
        The identification catalog (its stars are the ones that can be used).
    n, seed : int
        Frames, and the seed of their attitudes and noise (frame ``k`` uses ``[seed, k]``).
    sensor : startrack.render.Sensor, optional
        Default ``Sensor()``.
    render_catalog : Catalog, optional
        Stars to render (default ``catalog``); fainter stars make a realistic sky.
    identify : callable, optional
        ``identify(stars) -> [(star index, id), ...] or None``; default: from the truth.
    max_stars : int, optional
        At most this many stars per frame (the brightest), in the estimate and in the bound.
    progress : callable, optional
        ``progress(done, total)``.
    merge_px : float, optional
        Unresolved separation for the reference directions (:func:`blended_references`).
    done : iterable of dict, optional
        The records ``on_frame`` was given for frames ``0 .. m-1`` by an earlier call with the same
        arguments, in order: those frames are taken from them, not rendered again, and the result is
        the one an uninterrupted call gives (a frame's result depends only on ``[seed, k]``).
    on_frame : callable, optional
        ``on_frame(record)`` as each frame ends, ``record`` a JSON-ready dict: ``frame`` (``k``),
        ``outcome`` (``ok``, ``far``, ``wrong``, ``failed`` or ``no_bound``) and, for the frames
        scored (``ok``, ``far``), ``error`` (3, rad), ``bound`` (3, rad^2, the bound's diagonal) and
        ``cov`` (9, rad^2, the covariance reported, row by row).

    Memory: 15 floats (120 bytes of data) per frame scored, what :func:`summarise` needs, whatever
    ``done`` holds (it is read one record at a time).

    Returns
    -------
    dict
        :func:`summarise` of the frames solved and not wrong, with the
        counts ``failed`` (no attitude), ``far`` (more than 0.1 deg off, but
        within 5 sigma of the covariance reported: NEES <= 25; scored, as
        leaving them out would bias the RMS low), ``wrong`` (beyond) and
        ``no_bound`` (fewer than 2 usable stars in view).
    """
    from startrack.render import Scene, Sensor, render_image
    from startrack.rotations import quaternion_to_dcm, random_quaternions

    sensor = sensor or Sensor()
    render_catalog = render_catalog or catalog
    rvec = render_catalog.vectors()
    refs = blended_references(catalog, render_catalog, camera, merge_px)
    rows = refs.rows_by_id()
    ivec = refs.vectors()
    dcms = quaternion_to_dcm(random_quaternions(n, np.random.default_rng(seed)))
    errs, crbs, covs = [], [], []
    counts = {"failed": 0, "far": 0, "wrong": 0, "no_bound": 0}

    def add(rec):
        if rec["outcome"] in counts:
            counts[rec["outcome"]] += 1
        if rec["outcome"] in ("ok", "far"):
            errs.append(np.asarray(rec["error"], dtype=np.float64).reshape(3))
            crbs.append(np.asarray(rec["bound"], dtype=np.float64).reshape(3))
            covs.append(np.asarray(rec["cov"], dtype=np.float64).reshape(3, 3))

    start = 0
    for rec in done:
        if not isinstance(rec, dict) or rec.get("frame") != start or start >= n \
                or rec.get("outcome") not in ("ok", "far", "wrong", "failed", "no_bound"):
            raise ParameterError("done", f"record {start} is not frame {start}'s of {n} (got {rec!r:.80})",
                                 "evaluate_accuracy")
        try:
            add(rec)
        except (KeyError, TypeError, ValueError) as exc:
            raise ParameterError("done", f"frame {start}'s record is damaged ({type(exc).__name__}: {exc})",
                                 "evaluate_accuracy") from None
        start += 1
    if progress and start:
        progress(start, n)
    for k in range(start, n):
        img, truth = render_image(render_catalog, camera, dcms[k], sensor, Scene(), np.random.default_rng([seed, k]),
                                  vectors=rvec)
        bound, _ = frame_bound(camera, reference_stars(camera, dcms[k], refs, sensor, ivec, truth["focal_length_px"]),
                               sensor, None, max_stars)
        rec = {"frame": k, "outcome": "no_bound"}
        if bound is not None:
            att = startrack_frame(img, truth, camera, sensor, rows, ivec, max_stars, identify=identify)
            if att is None or att.status != "ok":
                rec["outcome"] = "failed"
            else:
                e = error_vector(att.dcm, dcms[k])
                rec["outcome"] = "ok"
                if np.linalg.norm(e) > math.radians(0.1):
                    # Off by more than 0.1 deg: wrong when also beyond 5 sigma of its own covariance,
                    # else "far" (two close stars leave the roll loose: off, but as it says).
                    rec["outcome"] = "far" if float(e @ np.linalg.solve(att.cov_rad2, e)) <= 25.0 else "wrong"
                if rec["outcome"] != "wrong":
                    rec.update(error=[float(v) for v in e], bound=[float(v) for v in np.diag(bound.cov_rad2)],
                               cov=[float(v) for v in np.asarray(att.cov_rad2).ravel()])
        add(rec)
        if on_frame:
            on_frame(rec)
        if progress:
            progress(k + 1, n)
    out = summarise(errs, crbs, covs if covs else None)
    out.update(counts)
    return out


def error_vector(dcm_estimate, dcm_truth):
    """Small-angle error rotation ``phi`` of ``A_est A_true^T`` (rad; camera frame: x, y cross-boresight, z roll)."""
    from startrack.rotations import _rotation_vector_rad

    return _rotation_vector_rad(np.asarray(dcm_estimate) @ np.asarray(dcm_truth).T)


def summarise(errors, bounds, covariances=None):
    """Per-axis efficiency of a set of frames.

    Parameters
    ----------
    errors : array (n, 3)
        Error rotations (rad).
    bounds : array (n, 3)
        Each frame's bound variances (rad^2), diagonal of :class:`AttitudeBound`.
    covariances : array (n, 3, 3), optional
        The covariance each estimate reported, for NEES.

    Returns
    -------
    dict
        ``ratio_cross``, ``ratio_roll``: RMS error over the RMS of the per-frame
        bound (cross-boresight pools x and y), with ``ratio_*_band`` the 95 %
        band of an efficient estimator's ratio over these bounds (normal
        approximation, ``n_eff = (sum b)^2 / sum b^2`` effective frames in
        ``ratio_*_n_eff``); ``z_cross``, ``z_roll``: RMS of
        the per-frame normalised errors ``phi / sqrt(bound)`` (1 for an
        efficient estimator; less sensitive to the few frames with a huge
        bound); ``nees_mean`` and its 95 % band ``nees_band`` (mean of n
        chi-square(3) variables: ``3 +- 1.96 sqrt(6 / n)``); ``nees_in_95``,
        the fraction of frames whose NEES is below the chi-square(3) 95 %
        point 7.81.
    """
    e = np.asarray(errors, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(bounds, dtype=np.float64).reshape(-1, 3)
    n = len(e)
    out = {"frames": n}
    if n == 0:
        return out
    out["rms_cross_arcsec"] = math.sqrt(float(np.mean(e[:, :2] ** 2))) * _ARCSEC
    out["rms_roll_arcsec"] = math.sqrt(float(np.mean(e[:, 2] ** 2))) * _ARCSEC
    out["crb_cross_arcsec"] = math.sqrt(float(np.mean(b[:, :2]))) * _ARCSEC
    out["crb_roll_arcsec"] = math.sqrt(float(np.mean(b[:, 2]))) * _ARCSEC
    out["ratio_cross"] = out["rms_cross_arcsec"] / out["crb_cross_arcsec"]
    out["ratio_roll"] = out["rms_roll_arcsec"] / out["crb_roll_arcsec"]
    # An efficient estimator's ratio^2 is sum(b_i chi2_i) / sum(b_i) (chi2_i of one degree of freedom):
    # mean 1, variance 2 sum(b_i^2) / sum(b_i)^2 = 2 / n_eff.  Frames' bounds differ by orders of
    # magnitude (two close stars leave the roll loose), so a few frames carry the ratio and n_eff is small.
    for axis, bb in (("cross", b[:, :2].ravel()), ("roll", b[:, 2])):
        n_eff = float(np.sum(bb)) ** 2 / float(np.sum(bb * bb))
        half = 1.96 * math.sqrt(2.0 / n_eff)
        out[f"ratio_{axis}_n_eff"] = n_eff
        out[f"ratio_{axis}_band"] = (math.sqrt(max(0.0, 1.0 - half)), math.sqrt(1.0 + half))
    z = e / np.sqrt(b)
    out["z_cross"] = math.sqrt(float(np.mean(z[:, :2] ** 2)))
    out["z_roll"] = math.sqrt(float(np.mean(z[:, 2] ** 2)))
    if covariances is not None:
        c = np.asarray(covariances, dtype=np.float64).reshape(-1, 3, 3)
        nees = np.einsum("ni,ni->n", e, np.linalg.solve(c, e[:, :, None])[:, :, 0])
        half = 1.96 * math.sqrt(6.0 / n)
        out["nees_mean"] = float(np.mean(nees))
        out["nees_band"] = (3.0 - half, 3.0 + half)
        out["nees_in_95"] = float(np.mean(nees <= 7.815))
    return out
