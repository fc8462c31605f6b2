"""Ground calibration of the camera: focal length, principal point and radial distortion.

Paper 000 (Sec. 3.3, after Medaglia 2016) calibrates the focal length and the
principal point by least squares; we solve the bundle problem directly: over
one or many identified frames, minimise the pixel residuals between the
measured stars and the catalog stars projected through the camera model,

    r = (x, y)_measured - project(exp(-[d_k x]) A_k r_i; f, cx, cy, k1, k2[, k3, k4]),

for the intrinsics and a small attitude correction ``d_k`` per frame
(Levenberg-Marquardt; Jacobian by central differences).  The uncertainty is
``sqrt(diag((J^T J)^-1)) s`` with ``s^2`` the residual variance per degree of
freedom.

The projection itself (pinhole or one of the fisheyes of :mod:`startrack.camera`) is chosen by
:func:`calibrate_projection`: each candidate fitted with its significant distortion terms, the one of
least Bayesian information criterion ``n ln(RSS / n) + p ln(n)`` kept (Schwarz 1978: the residual
against a penalty of ``ln n`` per parameter, so a projection wins by fitting, not by its extra terms).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from startrack.errors import BadInputError, ParameterError

__all__ = ["CalibrationResult", "calibrate", "calibrate_significant", "calibrate_projection", "PARAMS"]

PARAMS = ("focal_length_px", "cx", "cy", "k1", "k2", "k3", "k4")
FISHEYE_TERMS = ("k3", "k4")        # a pinhole has k1 and k2 only


@dataclass
class CalibrationResult:
    camera: object
    sigma: dict
    rms_before_px: float
    rms_after_px: float
    n_frames: int
    n_stars: int
    fov_deg: tuple
    fov_sigma_deg: tuple
    significance: dict = None
    dropped: dict = None
    projections: dict = None        # calibrate_projection: each candidate's BIC, RMS and parameters

    @property
    def bic(self) -> float:
        """The Bayesian information criterion of the fit: ``n ln(RSS / n) + p ln(n)`` over the 2 n residuals."""
        n = 2 * self.n_stars
        p = len(self.sigma) + 3 * self.n_frames
        rss = max(self.rms_after_px ** 2 * n / 2.0, 1e-300)
        return n * math.log(rss / n) + p * math.log(n)

    def to_dict(self) -> dict:
        doc = self.camera.to_dict(standalone=True)
        arcsec = self.camera.pixel_scale_arcsec
        doc["calibration"] = {
            "frames": self.n_frames, "stars": self.n_stars,
            "sigma": {k: float(v) for k, v in self.sigma.items()},
            "rms_residual_before_px": self.rms_before_px, "rms_residual_after_px": self.rms_after_px,
            "rms_residual_before_arcsec": self.rms_before_px * arcsec,
            "rms_residual_after_arcsec": self.rms_after_px * arcsec,
            "fov_deg": list(self.fov_deg), "fov_sigma_deg": list(self.fov_sigma_deg),
            "method": "Levenberg-Marquardt bundle adjustment (intrinsics + per-frame attitude)",
        }
        if self.significance:
            doc["calibration"]["significance_sigma"] = {k: float(v) for k, v in self.significance.items()}
        if self.dropped:
            doc["calibration"]["not_fitted"] = {k: f"not significant ({v:.1f} sigma): fixed at its default"
                                                for k, v in self.dropped.items()}
        if self.projections:
            doc["calibration"]["projections"] = self.projections
        return doc


def _rot(d):
    """Passive rotation by the small vector ``d``: ``exp(-[d x])`` (Rodrigues)."""
    from startrack.rotations import quaternion_to_dcm

    angle = float(np.linalg.norm(d))
    if angle == 0:
        return np.eye(3)
    axis = d / angle
    return quaternion_to_dcm(np.concatenate([axis * math.sin(angle / 2), [math.cos(angle / 2)]]))


# The value a parameter takes when it is not fitted: no distortion, the image centre.
def _default(camera, name):
    return {"k1": 0.0, "k2": 0.0, "k3": 0.0, "k4": 0.0, "cx": (camera.width - 1) / 2.0,
            "cy": (camera.height - 1) / 2.0}.get(name)


def calibrate_significant(frames, camera, fit=PARAMS, min_sigma: float = 3.0, iterations: int = 30):
    """Fit only what the data constrain.

    All of ``fit`` is fitted; then, while the least significant optional
    parameter (k4, k3, k2, k1, then the principal point) differs from its default (no
    distortion, the image centre) by less than ``min_sigma`` of its
    uncertainty, it is fixed at its default and the rest fitted again.  The
    focal length is always fitted.  The result reports every fitted parameter's
    significance (|value - default| / sigma) and the parameters left out with theirs.
    """
    from dataclasses import replace

    fit = [p for p in PARAMS if p in set(fit) and (p not in FISHEYE_TERMS or not camera.is_pinhole)]
    dropped = {}
    base = camera
    while True:
        res = calibrate(frames, base, fit, iterations)
        sig = {}
        for name in fit:
            d = _default(camera, name)
            s_ = res.sigma.get(name, 0.0)
            if d is not None:
                sig[name] = abs(getattr(res.camera, name) - d) / s_ if s_ > 0 else float("inf")
        pair = max(sig.get("cx", 0.0), sig.get("cy", 0.0))
        # A higher term goes before a lower one: k2 is tested only once k3 and k4 are out, and so on.
        optional = []
        for n in ("k4", "k3", "k2", "k1"):
            if n in fit:
                if sig[n] < min_sigma:
                    optional.append(n)
                break
        if ("cx" in fit or "cy" in fit) and pair < min_sigma:
            optional.append("cx" if "cx" in fit else "cy")
            sig["cx" if "cx" in fit else "cy"] = pair
        if not optional:
            res.significance = sig
            res.dropped = dropped
            return res
        worst = min(optional, key=lambda n: sig[n])
        if worst in ("cx", "cy"):
            # the principal point goes as a pair
            for n in ("cx", "cy"):
                if n in fit:
                    dropped[n] = sig[n]
                    fit.remove(n)
                    base = replace(base, **{n: _default(camera, n)})
        else:
            dropped[worst] = sig[worst]
            fit.remove(worst)
            base = replace(base, **{worst: 0.0})


def calibrate(frames, camera, fit=PARAMS, iterations: int = 30):
    """Fit the camera to ``frames``: list of ``(dcm, xy (n, 2), ref (n, 3))``.

    Parameters
    ----------
    camera : Camera
        Starting values (the parameters not in ``fit`` stay fixed).
    fit : iterable of str
        Among ``focal_length_px``, ``cx``, ``cy``, ``k1``, ``k2`` (and ``k3``, ``k4`` for a fisheye).
    """

    if camera.is_pinhole and set(fit) & set(FISHEYE_TERMS):
        raise ParameterError("fit", "k3 and k4 are a fisheye's terms; the camera is a pinhole")
    fit = [p for p in PARAMS if p in set(fit)]
    if not fit:
        raise ParameterError("fit", f"choose among {', '.join(PARAMS)}")
    frames = [(np.asarray(a, float), np.asarray(xy, float), np.asarray(r, float)) for a, xy, r in frames if len(xy) >= 3]
    n_obs = sum(len(xy) for _, xy, _ in frames)
    n_par = len(fit) + 3 * len(frames)
    if not frames or 2 * n_obs <= n_par + 2:
        raise BadInputError("frames", None, f"{n_obs} identified stars in {len(frames)} frame(s): too few to fit "
                            f"{len(fit)} camera parameters")

    from startrack.camera import Camera, parameter_bounds

    fields = {f.name: getattr(camera, f.name) for f in dataclasses.fields(camera)}
    fields["extra"] = dict(camera.extra)

    def unpack(p, checked=False):
        # The probes of the Jacobian may lie a difference step past a bound (unchecked); the result is checked.
        values = {**fields, **{name: float(p[i]) for i, name in enumerate(fit)}}
        cam = Camera(**values) if checked else Camera._probe(values)
        deltas = p[len(fit):].reshape(-1, 3)
        return cam, deltas

    def residuals(p):
        cam, deltas = unpack(p)
        out = []
        for (a, xy, ref), d in zip(frames, deltas, strict=True):
            v = ref @ (_rot(d) @ a).T
            x, y = cam.vectors_to_pixels(v)
            out.append(np.column_stack([xy[:, 0] - x, xy[:, 1] - y]).ravel())
        r = np.concatenate(out)
        return np.where(np.isfinite(r), r, 1e3)

    p = np.concatenate([[getattr(camera, name) for name in fit], np.zeros(3 * len(frames))])
    scales = np.array([{"focal_length_px": camera.focal_length_px * 1e-6, "cx": 1e-3, "cy": 1e-3, "k1": 1e-6,
                        "k2": 1e-6, "k3": 1e-6, "k4": 1e-6}[n] for n in fit] + [1e-7] * (3 * len(frames)))
    # Steps keep the focal length and principal point within the camera's bounds (camera.parameter_bounds); the
    # lens terms' bound is on their effect at the corners, which the stars there constrain: checked on the result.
    bounds = parameter_bounds(camera.width, camera.height)
    lower = np.array([bounds.get(n, (-np.inf, np.inf))[0] for n in fit] + [-np.inf] * (3 * len(frames)))
    upper = np.array([bounds.get(n, (-np.inf, np.inf))[1] for n in fit] + [np.inf] * (3 * len(frames)))
    r = residuals(p)
    rms_before = float(np.sqrt(np.mean(r**2) * 2))
    lam = 1e-3
    cost = float(r @ r)
    for _ in range(iterations):
        jac = np.empty((len(r), len(p)))
        for j in range(len(p)):
            dp = np.zeros_like(p)
            dp[j] = scales[j]
            jac[:, j] = (residuals(p + dp) - residuals(p - dp)) / (2 * scales[j])
        jtj = jac.T @ jac
        g = jac.T @ r
        improved = False
        for _ in range(10):
            trial = np.clip(p + np.linalg.solve(jtj + lam * np.diag(np.diag(jtj) + 1e-12), -g), lower, upper)
            step = trial - p
            rt = residuals(trial)
            ct = float(rt @ rt)
            if ct < cost:
                p, r, cost = trial, rt, ct
                lam = max(lam / 3, 1e-9)
                improved = True
                break
            lam *= 10
        if not improved or np.max(np.abs(step) / np.maximum(scales * 1e3, 1e-12)) < 1e-3:
            break
    dof = max(1, len(r) - len(p))
    s2 = cost / dof
    try:
        cov = np.linalg.inv(jtj) * s2
    except np.linalg.LinAlgError:
        cov = np.full((len(p), len(p)), np.nan)
    try:
        cam, _ = unpack(p, checked=True)
    except ParameterError as exc:
        raise BadInputError("frames", None, f"the fitted camera is no lens ({exc}): the stars do not determine "
                            f"{', '.join(fit)}; fit fewer terms") from None
    sigma = {name: float(math.sqrt(max(cov[i, i], 0.0))) for i, name in enumerate(fit)}
    rms_after = float(np.sqrt(np.mean(r**2) * 2))
    fx, fy = cam.fov_deg
    sf = sigma.get("focal_length_px", 0.0) / cam.focal_length_px
    # The field's sensitivity to f, numerically (the exact derivative for every projection): FOV(f (1 + e)).
    eps = 1e-6
    gx, gy = cam.with_focal_length(cam.focal_length_px * (1 + eps)).fov_deg
    dfx = abs(gx - fx) / eps * sf
    dfy = abs(gy - fy) / eps * sf
    return CalibrationResult(cam, sigma, rms_before, rms_after, len(frames), n_obs, (fx, fy), (dfx, dfy))


def _start_for(frames, camera, projection):
    """``camera`` as ``projection``, its distortion cleared and ``f`` the median of measured radius over
    ``g(theta)`` of the catalog stars (their angle from the boresight at each frame's attitude)."""
    from startrack.camera import projection_radius

    cam = camera.replace(projection=projection, k1=0.0, k2=0.0, k3=0.0, k4=0.0)
    ratios = []
    for a, xy, ref in frames:
        v = np.asarray(ref) @ np.asarray(a).T
        theta = np.arccos(np.clip(v[:, 2], -1.0, 1.0))
        radius = np.hypot(xy[:, 0] - cam.cx, xy[:, 1] - cam.cy)
        g = projection_radius(projection, theta)
        ok = (theta > math.radians(2.0)) & np.isfinite(g) & (g > 0)
        ratios.append(radius[ok] / g[ok])
    ratios = np.concatenate(ratios) if ratios else np.zeros(0)
    return cam.with_focal_length(float(np.median(ratios))) if len(ratios) else cam


def calibrate_projection(frames, camera, projections=None, fit=PARAMS, min_sigma: float = 3.0,
                         iterations: int = 30) -> CalibrationResult:
    """:func:`calibrate_significant` for each of ``projections`` (default: every one the stars allow: a
    pinhole only when every star is less than 85 deg off-axis, an orthographic one below 90), and the
    fit of least BIC (:attr:`CalibrationResult.bic`).  The result's ``projections`` holds every
    candidate's ``bic``, ``rms_px``, ``focal_length_px`` and fitted terms (a candidate whose fit failed:
    its ``error``)."""
    from startrack.camera import PROJECTIONS
    from startrack.errors import StartrackError

    frames = [(np.asarray(a, float), np.asarray(xy, float), np.asarray(r, float)) for a, xy, r in frames if len(xy) >= 3]
    widest = 0.0
    for a, _, ref in frames:
        widest = max(widest, float(np.max(np.arccos(np.clip((ref @ a.T)[:, 2], -1, 1)))))
    if projections is None:
        projections = [p for p in PROJECTIONS if not (p == "pinhole" and widest > math.radians(85.0))
                       and not (p == "orthographic" and widest >= math.radians(90.0))]
    best, table = None, {}
    for projection in projections:
        try:
            res = calibrate_significant(frames, _start_for(frames, camera, projection), fit, min_sigma, iterations)
        except (StartrackError, np.linalg.LinAlgError) as exc:
            table[projection] = {"error": str(exc)}
            continue
        terms = {k: float(getattr(res.camera, k)) for k in ("k1", "k2", "k3", "k4") if k in res.sigma}
        table[projection] = {"bic": float(res.bic), "rms_px": float(res.rms_after_px),
                             "focal_length_px": float(res.camera.focal_length_px), **terms}
        if best is None or res.bic < best.bic:
            best = res
    if best is None:
        raise BadInputError("frames", None, "no projection could be fitted: " +
                            "; ".join(f"{k}: {v.get('error')}" for k, v in table.items()))
    best.projections = table
    return best
