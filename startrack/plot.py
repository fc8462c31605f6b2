"""Pictures people would rather look at than read: annotated images (OpenCV drawing).

Library code: takes arrays and dicts, writes PNG files atomically; never prints.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["stretch", "annotate_stars"]


def stretch(image: np.ndarray, low_pct: float = 70.0, high_pct: float = 99.95) -> np.ndarray:
    """An 8-bit display version: smooth background removed, percentile limits, asinh stretch."""
    import cv2

    img = np.asarray(image, dtype=np.float32)
    h, w = img.shape
    small = cv2.resize(img, (max(1, w // 32), max(1, h // 32)), interpolation=cv2.INTER_AREA)
    small = cv2.medianBlur(small, 3) if min(small.shape) >= 3 else small
    img = (img - cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)).astype(np.float64)
    lo, hi = np.percentile(img[:: max(1, img.shape[0] // 256), :: max(1, img.shape[1] // 256)], [low_pct, high_pct])
    if hi <= lo:
        hi = lo + 1.0
    x = np.clip((img - lo) / (hi - lo), 0, None)
    y = np.arcsinh(10.0 * x) / np.arcsinh(10.0)
    return np.clip(y * 255.0, 0, 255).astype(np.uint8)


def annotate_stars(path: str, image: np.ndarray, stars: list, rejected: list | None = None, labels: dict | None = None,
                   predicted: list | None = None, title: str | None = None, n_numbered: int = 20) -> None:
    """Write a PNG of ``image`` with the detected stars circled.

    Parameters
    ----------
    stars : list of dict
        ``x``, ``y`` (and ``flux``), brightest first: green circles, the
        ``n_numbered`` brightest numbered by rank (0 = brightest).
    rejected : list of dict, optional
        Set-aside detections (hot pixels, trails): red crosses.
    labels : dict, optional
        Star index -> text (e.g. ``"HIP 24436 Rigel"``) drawn beside it.
    predicted : list of (x, y), optional
        Catalog positions predicted from an attitude: small blue squares.
    """
    import cv2

    from startrack.formats.atomic import atomic_path

    base = stretch(image)
    canvas = cv2.cvtColor(base, cv2.COLOR_GRAY2BGR)
    scale = max(1.0, max(image.shape) / 1024.0)
    thick = max(1, int(round(scale)))
    font = cv2.FONT_HERSHEY_SIMPLEX
    for x, y in predicted or []:
        if np.isfinite(x) and np.isfinite(y):
            c = (int(round(x)), int(round(y)))
            cv2.rectangle(canvas, (c[0] - 4, c[1] - 4), (c[0] + 4, c[1] + 4), (255, 160, 0), thick)
    for r in rejected or []:
        c = (int(round(r["x"])), int(round(r["y"])))
        cv2.drawMarker(canvas, c, (0, 0, 255), cv2.MARKER_TILTED_CROSS, int(8 * scale), thick)
    for i, s in enumerate(stars):
        c = (int(round(s["x"])), int(round(s["y"])))
        radius = int(max(5, min(25, 3 + 2 * math.log10(max(s.get("flux", 10.0), 10.0)))) * scale)
        cv2.circle(canvas, c, radius, (0, 220, 0), thick, lineType=cv2.LINE_AA)
        text = None
        if labels and i in labels:
            text = labels[i]
        elif i < n_numbered:
            text = str(i)
        if text:
            cv2.putText(canvas, text, (c[0] + radius + 2, c[1] - radius), font, 0.45 * scale, (0, 255, 255), thick,
                        cv2.LINE_AA)
    if title:
        cv2.putText(canvas, title, (8, int(20 * scale)), font, 0.55 * scale, (255, 255, 255), thick, cv2.LINE_AA)
    with atomic_path(path, suffix=".png") as tmp:
        if not cv2.imwrite(tmp, canvas):
            from startrack.errors import BadInputError

            raise BadInputError(path, None, "could not write the PNG")


def _figure():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        from startrack.errors import BadInputError

        raise BadInputError("--plot", None, "needs matplotlib: pip install 'startrack[plot]'") from None
    return plt


def _save(fig, path):
    import os

    from startrack.formats.atomic import atomic_path

    with atomic_path(path, suffix=os.path.splitext(path)[1] or ".png") as tmp:
        fig.savefig(tmp, format="png")


def plot_track_errors(docs: list, path: str, title: str = "") -> dict:
    """Per-frame cross-boresight and roll error (arcsec) of tracked frames against their truth, coloured by mode.

    Returns the statistics it plots: RMS errors per mode, mode fractions and
    the recovery after losses (frames from the first lost frame of a loss to
    the next tracked frame).
    """
    import math

    from startrack.rotations import attitude_error, quaternion_to_dcm

    plt = _figure()
    rows = []
    for k, d in enumerate(docs):
        mode = (d.get("track") or {}).get("mode")
        att = d.get("attitude") or {}
        cross = roll = float("nan")
        if att.get("status") == "ok" and "truth" in d:
            _, c, r = attitude_error(quaternion_to_dcm(att["quaternion"]), quaternion_to_dcm(d["truth"]["quaternion"]))
            cross, roll = math.degrees(c) * 3600, math.degrees(r) * 3600
        rows.append((k, mode, cross, roll))
    colours = {"lis": "tab:blue", "track": "tab:green", "single-star": "tab:orange", "lost": "tab:red",
               None: "tab:purple"}
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(10, 6), dpi=110, sharex=True)
    for mode, colour in colours.items():
        sel = [r for r in rows if r[1] == mode]
        if not sel:
            continue
        ax1.scatter([r[0] for r in sel], [r[2] for r in sel], s=8, c=colour,
                    label=f"{mode or 'solved'} ({len(sel)})")
        ax2.scatter([r[0] for r in sel], [abs(r[3]) for r in sel], s=8, c=colour)
        for r in sel:
            if mode == "lost":
                ax1.axvspan(r[0] - 0.5, r[0] + 0.5, color="tab:red", alpha=0.15, lw=0)
                ax2.axvspan(r[0] - 0.5, r[0] + 0.5, color="tab:red", alpha=0.15, lw=0)
    ax1.set_ylabel("cross-boresight error (arcsec)")
    ax2.set_ylabel("|roll error| (arcsec)")
    ax2.set_xlabel("frame")
    ax1.set_yscale("symlog", linthresh=1)
    ax2.set_yscale("symlog", linthresh=10)
    ax1.grid(alpha=0.3)
    ax2.grid(alpha=0.3)
    ax1.legend(fontsize=8, loc="upper right")
    fig.suptitle(title or "tracking errors per frame")
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)
    stats = {"frames": len(rows), "modes": {m or "solved": sum(1 for r in rows if r[1] == m) / max(1, len(rows))
                                             for m in colours}}
    for m in ("track", "lis", "single-star", None):
        sel = [r for r in rows if r[1] == m and r[2] == r[2]]
        if sel:
            stats[f"rms_cross_{m or 'solved'}_arcsec"] = float(math.sqrt(sum(r[2] ** 2 for r in sel) / len(sel)))
            stats[f"rms_roll_{m or 'solved'}_arcsec"] = float(math.sqrt(sum(r[3] ** 2 for r in sel) / len(sel)))
    recoveries = []
    k = 0
    while k < len(rows):
        if rows[k][1] == "lost":
            start = k
            while k < len(rows) and rows[k][1] == "lost":
                k += 1
            if k < len(rows):
                recoveries.append({"lost_from": start, "lost_frames": k - start, "recovered_at": k,
                                   "recovered_by": rows[k][1]})
        k += 1
    stats["recoveries"] = recoveries
    return stats


def plot_residuals(doc: dict, path: str, scale: float = 200.0) -> None:
    """Residual quiver plot: for each star used in the attitude, the arrow from the catalog position
    (projected with the solved attitude) to the measured position, magnified ``scale`` times."""
    import numpy as np

    from startrack.camera import Camera
    from startrack.catalog import load_catalog

    plt = _figure()
    att = doc.get("attitude") or {}
    cam = Camera.from_dict(doc["camera"])
    cat = load_catalog()
    rows = cat.rows_by_id()
    vec = cat.vectors()
    a = np.asarray(att["dcm"])
    xs, ys, us, vs = [], [], [], []
    for r in att.get("residuals", []):
        s = doc["stars"][r["star"]]
        k = rows.get(int(r["id"]))
        if k is None:
            continue
        px, py = cam.vectors_to_pixels(a @ vec[k])
        xs.append(px)
        ys.append(py)
        us.append(s["x"] - px)
        vs.append(s["y"] - py)
    fig, ax = plt.subplots(figsize=(8, 8 * cam.height / cam.width + 0.5), dpi=110)
    ax.quiver(xs, ys, np.array(us) * scale, np.array(vs) * scale, angles="xy", scale_units="xy", scale=1,
              color="tab:blue", width=0.003)
    ax.scatter(xs, ys, s=6, c="k")
    ax.set_xlim(-0.5, cam.width - 0.5)
    ax.set_ylim(cam.height - 0.5, -0.5)
    ax.set_aspect("equal")
    rms = att.get("rms_residual_arcsec")
    ax.set_title(f"residuals x{scale:g} (RMS {rms:.2f} arcsec, {len(xs)} stars)" if rms else "residuals")
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def annotate_solution(path: str, image, doc: dict, catalog=None, mag_limit: float | None = None) -> None:
    """The picture of a solved frame: detections, identified stars labelled (HIP and proper name), catalog
    stars predicted from the attitude, a north/east compass and the boresight coordinates."""
    import math

    import cv2
    import numpy as np

    from startrack.camera import Camera
    from startrack.catalog import load_catalog
    from startrack.formats.atomic import atomic_path
    from startrack.names import star_label

    cam = Camera.from_dict(doc["camera"])
    stars = doc.get("stars") or []
    ident = doc.get("identification") or {}
    att = doc.get("attitude") or {}
    base = stretch(image)
    canvas = cv2.cvtColor(base, cv2.COLOR_GRAY2BGR)
    scale = max(1.0, max(image.shape) / 1024.0)
    thick = max(1, int(round(scale)))
    font = cv2.FONT_HERSHEY_SIMPLEX
    if att.get("status") == "ok":
        cat = catalog or load_catalog()
        if mag_limit is not None:
            cat = cat.filter_magnitude(None, mag_limit)
        a = np.asarray(att["dcm"])
        cam_vec = cat.vectors() @ a.T
        front = cam_vec[:, 2] > 0
        x, y = cam.vectors_to_pixels(cam_vec[front])
        inside = cam.in_image(x, y)
        for px, py in zip(x[inside], y[inside]):
            c = (int(round(px)), int(round(py)))
            cv2.rectangle(canvas, (c[0] - 5, c[1] - 5), (c[0] + 5, c[1] + 5), (255, 160, 0), thick)
        # Compass at the lower left: north and east directions at the image centre.
        bore = a[2]
        ra, dec = math.radians(att["ra"]), math.radians(att["dec"])
        north = np.array([-math.sin(dec) * math.cos(ra), -math.sin(dec) * math.sin(ra), math.cos(dec)])
        east = np.array([-math.sin(ra), math.cos(ra), 0.0])
        origin = (int(60 * scale), int(image.shape[0] - 60 * scale))
        for vec_dir, label, colour in ((north, "N", (0, 0, 255)), (east, "E", (0, 200, 255))):
            d = a @ (bore + 0.01 * vec_dir)
            px, py = cam.vectors_to_pixels(d)
            v = np.array([px - cam.cx, py - cam.cy])
            v = v / max(np.linalg.norm(v), 1e-9) * 40 * scale
            tip = (int(origin[0] + v[0]), int(origin[1] + v[1]))
            cv2.arrowedLine(canvas, origin, tip, colour, thick + 1, tipLength=0.25)
            cv2.putText(canvas, label, (tip[0] + 4, tip[1] + 4), font, 0.6 * scale, colour, thick + 1, cv2.LINE_AA)
        text = (f"RA {att['ra']:.4f}  Dec {att['dec']:+.4f}  roll {att['roll']:.2f} deg   "
                f"({att.get('n_stars', 0)} stars, sigma {att.get('sigma_cross_boresight_arcsec', float('nan')):.1f}\" / "
                f"{att.get('sigma_roll_arcsec', float('nan')):.0f}\")")
        cv2.putText(canvas, text, (8, int(image.shape[0] - 10 * scale)), font, 0.5 * scale, (255, 255, 255), thick,
                    cv2.LINE_AA)
    labels = {m["star"]: star_label(m["id"]) for m in ident.get("matches", [])}
    for i, s in enumerate(stars):
        c = (int(round(s["x"])), int(round(s["y"])))
        colour = (0, 220, 0) if i in labels else (140, 140, 140)
        cv2.circle(canvas, c, int(8 * scale), colour, thick, lineType=cv2.LINE_AA)
        if i in labels:
            cv2.putText(canvas, labels[i], (c[0] + int(10 * scale), c[1] - int(6 * scale)), font, 0.42 * scale,
                        (0, 255, 255), thick, cv2.LINE_AA)
    status = ident.get("status", "?")
    title = f"{status}: {len(labels)} of {len(stars)} stars identified ({ident.get('algorithm', '')})"
    cv2.putText(canvas, title, (8, int(20 * scale)), font, 0.55 * scale, (255, 255, 255), thick, cv2.LINE_AA)
    with atomic_path(path, suffix=".png") as tmp:
        cv2.imwrite(tmp, canvas)
