"""Pictures people would rather look at than read: annotated images (OpenCV drawing).

Library code: takes arrays and dicts, writes PNG files atomically; never prints.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["stretch", "annotate_stars", "annotate_solution", "picture_format", "plot_results", "write_preview"]


# One marker vocabulary for every annotated picture (BGR colours for OpenCV), explained by
# the legend drawn on every picture.
MARKERS = {
    "identified": ((80, 220, 80), "identified (catalog id)"),
    "detected": ((175, 175, 175), "detected"),
    "predicted": ((255, 170, 60), "catalog star predicted"),
    "rejected": ((70, 70, 255), "rejected (hot pixel, trail)"),
    "constellation": ((200, 110, 230), "constellation figure"),
}
_LABEL = (120, 240, 255)
_PANEL = (34, 30, 28)
_TEXT = (235, 235, 235)


def stretch(image: np.ndarray) -> np.ndarray:
    """An 8-bit display version of a sky image: dark sky, faint stars visible, bright stars unsaturated.

    The smooth background (a median mesh, as sky-subtraction does) is removed;
    the sky noise sigma is measured with the median absolute deviation; the
    display range runs from two sigma above the sky (so noise stays dark
    instead of looking like static) to the brightest star peaks, with an asinh
    stretch (astropy.visualization's ``AsinhStretch``) that shows stars from
    a few sigma to saturation.
    """
    import cv2
    from astropy.visualization import AsinhStretch

    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 3:
        img = img.mean(axis=2)
    h, w = img.shape
    small = cv2.resize(img, (max(1, w // 32), max(1, h // 32)), interpolation=cv2.INTER_AREA)
    small = cv2.medianBlur(small, 3) if min(small.shape) >= 3 else small
    img = img - cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
    sample = img[:: max(1, h // 512), :: max(1, w // 512)]
    centre = float(np.median(sample))
    sigma = 1.4826 * float(np.median(np.abs(sample - centre))) or float(np.std(sample)) or 1.0
    lo = centre + 2.0 * sigma
    hi = max(float(np.percentile(img, 99.995)), lo + 60.0 * sigma)
    x = np.clip((img - lo) / (hi - lo), 0.0, 1.0)
    y = AsinhStretch(a=0.02)(x, clip=True)
    return np.clip(y * 255.0, 0, 255).astype(np.uint8)


def write_preview(path: str, image: np.ndarray) -> None:
    """An 8-bit PNG of ``image`` stretched for people (:func:`stretch`): a 16-bit frame whose stars use a
    few per cent of the range looks black in an ordinary viewer.  Written atomically."""
    import cv2

    from startrack.errors import BadInputError
    from startrack.formats.atomic import atomic_path

    with atomic_path(path, suffix=".png") as tmp:
        if not cv2.imwrite(tmp, stretch(image), [cv2.IMWRITE_PNG_COMPRESSION, 9]):
            raise BadInputError(path, None, "could not write the PNG")


class _Picture:
    """An annotated picture: the stretched image above a legend panel, labels that never overlap."""

    def __init__(self, image: np.ndarray, panel_lines: int = 2):
        import cv2

        self.cv2 = cv2
        self.h, self.w = image.shape[:2]
        self.scale = max(0.8, min(2.5, max(self.h, self.w) / 1024.0))
        self.thick = max(1, int(round(self.scale)))
        self.font = cv2.FONT_HERSHEY_SIMPLEX
        self.font_scale = 0.45 * self.scale
        self.line_h = int(round(22 * self.scale))
        self.panel_h = self.line_h * (panel_lines + 2) + int(10 * self.scale)
        self.canvas = np.zeros((self.h + self.panel_h, self.w, 3), dtype=np.uint8)
        self.canvas[: self.h] = cv2.cvtColor(stretch(image), cv2.COLOR_GRAY2BGR)
        self.canvas[self.h:] = _PANEL
        self.occupied: list[tuple[int, int, int, int]] = []
        self.labels: list[tuple[str, tuple[int, int]]] = []

    def text_size(self, text: str) -> tuple[int, int]:
        (tw, th), base = self.cv2.getTextSize(text, self.font, self.font_scale, self.thick)
        return tw, th + base

    def visible(self, x: float, y: float, r: float = 0.0) -> bool:
        """Whether a marker of radius ``r`` at ``(x, y)`` touches the image (a position far outside is skipped:
        OpenCV takes 32-bit coordinates)."""
        try:
            x, y = float(x), float(y)
        except (OverflowError, TypeError, ValueError):
            return False
        return -r - 1 <= x <= self.w + r and -r - 1 <= y <= self.h + r     # False for NaN

    def marker(self, kind: str, x: float, y: float, size: float | None = None) -> tuple[int, int] | None:
        r = int(round((size or 7.0) * self.scale))
        if not self.visible(x, y, r):
            return None
        cv2 = self.cv2
        colour = MARKERS[kind][0]
        c = (int(round(x)), int(round(y)))
        if kind in ("identified", "detected"):
            cv2.circle(self.canvas, c, r, colour, self.thick + (kind == "identified"), lineType=cv2.LINE_AA)
        elif kind == "predicted":
            cv2.rectangle(self.canvas, (c[0] - r, c[1] - r), (c[0] + r, c[1] + r), colour, self.thick)
        else:
            cv2.drawMarker(self.canvas, c, colour, cv2.MARKER_TILTED_CROSS, 2 * r, self.thick + 1)
        if kind == "identified":
            self.occupied.append((c[0] - r, c[1] - r, c[0] + r, c[1] + r))
        return c

    def label(self, text: str, centre: tuple[int, int], radius: float,
              colour: tuple = _LABEL) -> tuple[int, int, int, int] | None:
        """Place ``text`` beside a marker: inside the image, over no other label or identified star.

        A marker off the image gets no label (None)."""
        tw, th = self.text_size(text)
        r = int(round(radius * self.scale)) + 3
        if not self.visible(centre[0], centre[1], r):
            return None
        cx, cy = centre
        own = (cx - r + 3, cy - r + 3, cx + r - 3, cy + r - 3)
        best, best_cost = None, None
        # Rings of candidate spots around the marker, nearest first; each spot is moved inside the
        # frame before it is judged, so a star at the edge gets its label on the inner side.
        for ring in range(4):
            d = r + ring * (th + 2)
            for x0, y0 in ((cx + d, cy - d + th // 2), (cx + d, cy + d + th // 2), (cx - d - tw, cy - d + th // 2),
                           (cx - d - tw, cy + d + th // 2), (cx - tw // 2, cy - d), (cx - tw // 2, cy + d + th),
                           (cx + d, cy + th // 2), (cx - d - tw, cy + th // 2)):
                # whole glyphs and their dark outline inside the image (drawn 3 px above y0)
                m = self.thick + 2
                x0 = int(min(max(x0, m), max(m, self.w - tw - m)))
                y0 = int(min(max(y0, th + 4 + m), self.h - 1))
                box = (x0, y0 - th, x0 + tw, y0)
                cost = sum(_overlap(box, o) for o in self.occupied if o != own) + _overlap(box, own)
                cost += ring * 0.5
                if best_cost is None or cost < best_cost:
                    best, best_cost = (x0, y0), cost
            if best_cost is not None and best_cost < 1.0:
                break
        x0, y0 = best
        box = (x0, y0 - th, x0 + tw, y0)
        self.occupied.append(box)
        self.labels.append((text, (x0, y0), colour))
        return box

    def draw_labels(self) -> None:
        cv2 = self.cv2
        for text, (x0, y0), colour in self.labels:
            # A dark outline keeps the label readable over stars and bright sky.
            cv2.putText(self.canvas, text, (x0, y0 - 3), self.font, self.font_scale, (0, 0, 0), self.thick + 2,
                        cv2.LINE_AA)
            cv2.putText(self.canvas, text, (x0, y0 - 3), self.font, self.font_scale, colour, self.thick,
                        cv2.LINE_AA)

    def polyline(self, points: np.ndarray, colour: tuple) -> None:
        """A line through ``points`` (image x, y), clipped to the image."""
        cv2 = self.cv2
        pts = np.round(np.asarray(points, dtype=float)).astype(np.int64)
        for (x0, y0), (x1, y1) in zip(pts[:-1], pts[1:]):
            ok, p0, p1 = cv2.clipLine((0, 0, self.w, self.h), (int(x0), int(y0)), (int(x1), int(y1)))
            if ok:
                cv2.line(self.canvas, p0, p1, colour, self.thick, cv2.LINE_AA)

    def panel(self, lines: list[str], kinds: list[str], compass=None) -> None:
        """Text lines, the legend of the markers used and the compass, on the panel below the image."""
        cv2 = self.cv2
        y = self.h + self.line_h
        for line in lines:
            cv2.putText(self.canvas, line, (int(8 * self.scale), y), self.font, 1.1 * self.font_scale, _TEXT,
                        self.thick, cv2.LINE_AA)
            y += self.line_h
        x = int(8 * self.scale)
        y += int(4 * self.scale)
        for kind in kinds:
            c = (x + int(8 * self.scale), y - int(5 * self.scale))
            r = int(6 * self.scale)
            colour, words = MARKERS[kind]
            if kind in ("identified", "detected"):
                cv2.circle(self.canvas, c, r, colour, self.thick + (kind == "identified"), lineType=cv2.LINE_AA)
            elif kind == "predicted":
                cv2.rectangle(self.canvas, (c[0] - r, c[1] - r), (c[0] + r, c[1] + r), colour, self.thick)
            elif kind == "constellation":
                cv2.line(self.canvas, (c[0] - r, c[1] + r // 2), (c[0] + r, c[1] - r // 2), colour, self.thick,
                         cv2.LINE_AA)
            else:
                cv2.drawMarker(self.canvas, c, colour, cv2.MARKER_TILTED_CROSS, 2 * r, self.thick + 1)
            cv2.putText(self.canvas, words, (x + int(20 * self.scale), y), self.font, self.font_scale, _TEXT,
                        self.thick, cv2.LINE_AA)
            x += int(20 * self.scale) + self.text_size(words)[0] + int(22 * self.scale)
        if compass is not None:
            self._compass(*compass)

    def _compass(self, north: np.ndarray, east: np.ndarray) -> None:
        """North and east arrows (unit image-plane directions) in the panel's right corner, letters past the tips."""
        cv2 = self.cv2
        length = 0.32 * self.panel_h
        origin = np.array([self.w - 0.55 * self.panel_h, self.h + 0.5 * self.panel_h])
        for vec, letter, colour in ((north, "N", (90, 90, 255)), (east, "E", (80, 200, 255))):
            v = np.asarray(vec, dtype=float)
            n = np.linalg.norm(v)
            if not n > 0:
                continue
            v = v / n
            tip = origin + length * v
            cv2.arrowedLine(self.canvas, tuple(int(round(t)) for t in origin), tuple(int(round(t)) for t in tip),
                            colour, self.thick + 1, cv2.LINE_AA, tipLength=0.3)
            tw, th = self.text_size(letter)
            at = origin + (length + 0.5 * max(tw, th) + 3 * self.scale) * v
            cv2.putText(self.canvas, letter, (int(at[0] - tw / 2), int(at[1] + th / 2 - 2)), self.font,
                        self.font_scale, colour, self.thick, cv2.LINE_AA)

    def save(self, path: str) -> None:
        """Write the picture: PNG, or PDF/SVG (by the suffix) holding the same raster at one pixel per point."""
        from startrack.errors import BadInputError
        from startrack.formats.atomic import atomic_path

        self.draw_labels()
        fmt = picture_format(path)
        if fmt != "png":
            fig = _figure(figsize=(self.canvas.shape[1] / 72.0, self.canvas.shape[0] / 72.0), dpi=72)
            ax = fig.add_axes((0, 0, 1, 1))
            ax.imshow(self.canvas[:, :, ::-1], interpolation="nearest")    # OpenCV's BGR -> RGB
            ax.set_axis_off()
            _save(fig, path)
            return
        with atomic_path(path, suffix=".png") as tmp:
            # zlib's best level: a third smaller than the default for a noisy sky, and still lossless
            if not self.cv2.imwrite(tmp, self.canvas, [self.cv2.IMWRITE_PNG_COMPRESSION, 9]):
                raise BadInputError(path, None, "could not write the PNG")


def picture_format(path: str) -> str:
    """``"png"``, ``"pdf"`` or ``"svg"`` from the picture's suffix; any other is refused, naming the file."""
    import os

    from startrack.errors import BadInputError
    from startrack.imageio import PLOT_EXTENSIONS

    ext = os.path.splitext(str(path))[1].lower()
    if ext not in PLOT_EXTENSIONS:
        raise BadInputError(str(path), None, f"unknown picture extension {ext or '(none)'!r}: pictures are PNG, PDF "
                                             "or SVG, name it .png, .pdf or .svg")
    return ext[1:]


def _overlap(a, b) -> float:
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    return float(w * h) if w > 0 and h > 0 else 0.0


def _radius(flux) -> float:
    return float(max(5.0, min(14.0, 2.0 + 1.6 * math.log10(max(float(flux or 10.0), 10.0)))))


def annotate_stars(path: str, image: np.ndarray, stars: list, rejected: list | None = None, labels: dict | None = None,
                   predicted: list | None = None, title: str | None = None, n_numbered: int = 20) -> None:
    """Write a PNG of ``image`` with its detections, in the vocabulary of :data:`MARKERS`.

    Parameters
    ----------
    stars : list of dict
        ``x``, ``y`` (and ``flux``), brightest first: "detected" circles, the
        ``n_numbered`` brightest numbered by rank (0 = brightest) when no
        labels are given.
    rejected : list of dict, optional
        Set-aside detections (hot pixels, trails): "rejected" crosses.
    labels : dict, optional
        Star index -> text (e.g. ``"HIP 24436 Rigel"``): those stars are drawn
        "identified" and labelled.
    predicted : list of (x, y), optional
        Catalog positions predicted from an attitude: "predicted" squares.
    """
    pic = _Picture(image, panel_lines=1)
    kinds = []
    for x, y in predicted or []:
        pic.marker("predicted", x, y, 6)
    if predicted:
        kinds.append("predicted")
    labels = labels or {}
    for i, s in enumerate(stars):
        kind = "identified" if i in labels else "detected"
        pic.marker(kind, s["x"], s["y"], _radius(s.get("flux")))
    for r in rejected or []:
        pic.marker("rejected", r["x"], r["y"], 5)
    for i, s in enumerate(stars):
        text = labels.get(i) if labels else (str(i) if i < n_numbered else None)
        if text:
            pic.label(text, (int(round(s["x"])), int(round(s["y"]))), _radius(s.get("flux")))
    kinds = (["identified"] if labels else []) + ["detected"] + kinds + (["rejected"] if rejected else [])
    lines = [title or f"{len(stars)} stars detected" + ("" if labels else " (numbered by brightness, 0 = brightest)")]
    pic.panel(lines, kinds)
    pic.save(path)


def _figure(**kwargs):
    """A matplotlib Figure on the Agg canvas (the object-oriented API: no pyplot, no global backend)."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        from startrack.errors import ParameterError

        raise ParameterError("plot", "needs matplotlib: pip install 'startrack[plot]'") from None
    fig = Figure(**kwargs)
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path):
    """Write a matplotlib figure atomically, in the format of its suffix (PNG, PDF or SVG)."""
    from startrack.formats.atomic import atomic_path

    fmt = picture_format(path)
    with atomic_path(path, suffix="." + fmt) as tmp:
        # no creation date in PDF/SVG: the same figure gives the same file
        metadata = {"CreationDate": None} if fmt == "pdf" else {"Date": None} if fmt == "svg" else None
        fig.savefig(tmp, format=fmt, metadata=metadata)


def plot_track_errors(docs: list, path: str, title: str = "") -> dict:
    """Per-frame cross-boresight and roll error (arcsec) of tracked frames against their truth, coloured by mode.

    Returns the statistics it plots: RMS errors per mode, mode fractions and
    the recovery after losses (frames from the first lost frame of a loss to
    the next tracked frame).
    """
    import math

    from matplotlib.ticker import FixedLocator, FuncFormatter, MaxNLocator, NullLocator

    from startrack.rotations import attitude_error, quaternion_to_dcm

    rows = []
    for k, d in enumerate(docs):
        mode = (d.get("track") or {}).get("mode")
        att = d.get("attitude") or {}
        cross = roll = float("nan")
        if att.get("status") == "ok" and "truth" in d:
            _, c, r = attitude_error(quaternion_to_dcm(att["quaternion"]), quaternion_to_dcm(d["truth"]["quaternion"]))
            cross, roll = float(c) * 3600, float(r) * 3600
        rows.append((k, mode, cross, roll))
    # Frames without a track section (e.g. centroid | identify | attitude) are "solved".
    colours = {"tracking": "tab:green", "single-star": "tab:orange", "lost-in-space": "tab:blue", "lost": "tab:red",
               None: "tab:purple"}
    fig = _figure(figsize=(10, 6), dpi=110)
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    for mode, colour in colours.items():
        sel = [r for r in rows if r[1] == mode]
        if not sel:
            continue
        ax1.scatter([r[0] for r in sel], [r[2] for r in sel], s=8, c=colour, label=f"{mode or 'solved'} ({len(sel)})")
        ax2.scatter([r[0] for r in sel], [abs(r[3]) for r in sel], s=8, c=colour)
        for r in sel:
            if mode == "lost":
                ax1.axvspan(r[0] - 0.5, r[0] + 0.5, color="tab:red", alpha=0.15, lw=0)
                ax2.axvspan(r[0] - 0.5, r[0] + 0.5, color="tab:red", alpha=0.15, lw=0)
    ax1.set_ylabel("cross-boresight error (arcsec)")
    ax2.set_ylabel("|roll error| (arcsec)")
    ax2.set_xlabel("frame")
    # Linear near zero, logarithmic above; plain numbers on the ticks (0, 1, 3, 10, 30, ...), not 10^k.
    for ax, linthresh, ticks in ((ax1, 1, (0, 0.5, 1, 3, 10, 30, 100, 300, 1000, 3000, 10000, 30000, 100000)),
                                 (ax2, 10, (0, 5, 10, 30, 100, 300, 1000, 3000, 10000, 30000, 100000, 300000))):
        ax.set_yscale("symlog", linthresh=linthresh)
        ax.yaxis.set_major_locator(FixedLocator(ticks))
        ax.yaxis.set_minor_locator(NullLocator())
        ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:g}"))
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.tick_params(labelleft=True)
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    # the legend above the panels, where it hides no point
    ax1.legend(fontsize=8, loc="lower left", bbox_to_anchor=(0.0, 1.0), ncol=5, frameon=False, borderaxespad=0.2)
    fig.suptitle(title or "tracking errors per frame")
    fig.tight_layout()
    _save(fig, path)
    stats = {"frames": len(rows), "with_attitude": sum(1 for r in rows if r[2] == r[2]),
             "modes": {m or "solved": sum(1 for r in rows if r[1] == m) / max(1, len(rows)) for m in colours}}
    for m in colours:
        sel = [r for r in rows if r[1] == m and r[2] == r[2]]
        if sel:
            stats[f"rms_cross_{m or 'solved'}_arcsec"] = float(math.sqrt(sum(r[2] ** 2 for r in sel) / len(sel)))
            stats[f"rms_roll_{m or 'solved'}_arcsec"] = float(math.sqrt(sum(r[3] ** 2 for r in sel) / len(sel)))
            stats[f"max_cross_{m or 'solved'}_arcsec"] = float(max(r[2] for r in sel))
            stats[f"max_roll_{m or 'solved'}_arcsec"] = float(max(abs(r[3]) for r in sel))
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

    att = doc.get("attitude") or {}
    cam = Camera.from_dict(doc["camera"])
    cat = _catalog_at_epoch(load_catalog(), att)
    rows = cat.rows_by_id()
    vec = cat.vectors()
    a = _attitude_matrix(att)
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
    fig = _figure(figsize=(8, 8 * cam.height / cam.width + 0.5), dpi=110)
    ax = fig.subplots()
    arrows = ax.quiver(xs, ys, np.array(us) * scale, np.array(vs) * scale, angles="xy", scale_units="xy", scale=1,
                       color="tab:blue", width=0.003)
    ax.scatter(xs, ys, s=6, c="k", label="catalog star, projected with the attitude")
    # the key: an arrow of a round number of arcseconds at this magnification
    key_arcsec = next((v for v in (1, 2, 5, 10, 20, 50, 100) if v / cam.pixel_scale_arcsec * scale >= 0.06 * cam.width),
                      100)
    ax.quiverkey(arrows, 0.55, -0.10, key_arcsec / cam.pixel_scale_arcsec * scale,
                 f'{key_arcsec:g}" to the measured centroid', labelpos="E", coordinates="axes", fontproperties={"size": 8})
    ax.legend(loc="upper left", bbox_to_anchor=(0.0, -0.06), fontsize=8, frameon=False)
    ax.set_xlim(-0.5, cam.width - 0.5)
    ax.set_ylim(cam.height - 0.5, -0.5)
    ax.set_aspect("equal")
    rms = att.get("rms_residual_arcsec")
    epoch = cat.epoch
    ax.set_title((f"residuals x{scale:g} (RMS {rms:.2f} arcsec, {len(xs)} stars, catalog at epoch {epoch:.2f})"
                  if rms else f"residuals x{scale:g} ({len(xs)} stars, catalog at epoch {epoch:.2f})"))
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    fig.tight_layout()
    _save(fig, path)


def annotate_solution(path: str, image, doc: dict, catalog=None, mag_limit: float | None = None,
                      constellations: bool = False) -> None:
    """The picture of a solved frame: detections, identified stars labelled (HIP and proper name), catalog
    stars predicted from the attitude (at the attitude's epoch), a north/east compass and the boresight
    coordinates, in the vocabulary of :data:`MARKERS`.

    With ``constellations``, the stick figures of :mod:`startrack.constellations` (the shipped table) are
    drawn beneath the markers, with the constellations' names.  ``path`` is PNG, PDF or SVG by its suffix.
    """
    from startrack.camera import Camera
    from startrack.catalog import load_catalog
    from startrack.names import star_label

    cam = Camera.from_dict(doc["camera"])
    stars = doc.get("stars") or []
    ident = doc.get("identification") or {}
    att = doc.get("attitude") or {}
    pic = _Picture(image, panel_lines=2)
    kinds = []
    compass = None
    lines = []
    labels = {m["star"]: star_label(m["id"]) for m in ident.get("matches", [])} if ident.get("status") == "ok" else {}
    if att.get("status") == "ok":
        cat = _catalog_at_epoch(catalog or load_catalog(), att)
        if mag_limit is not None:
            cat = cat.filter_magnitude(None, mag_limit)
        a = _attitude_matrix(att)
        mirrored = (doc.get("solve") or {}).get("parity") == "mirrored"
        if constellations:
            _draw_constellations(pic, cat, a, cam, mirrored)
            kinds.append("constellation")
        cam_vec = cat.vectors() @ a.T
        front = cam_vec[:, 2] > 0
        x, y = cam.vectors_to_pixels(cam_vec[front])
        if mirrored:
            x = 2.0 * cam.cx - x            # the image is the camera's flipped (startrack.parity)
        inside = cam.in_image(x, y)
        for px, py in zip(x[inside], y[inside]):
            pic.marker("predicted", px, py, 6)
        kinds.append("predicted")
        compass = _north_east_in_image(a, cam)
        if mirrored:
            compass = tuple(np.array([-d[0], d[1]]) for d in compass)
        lines.append(f"RA {att['ra']:.4f} deg   Dec {att['dec']:+.4f} deg   roll {att['roll']:.2f} deg   "
                     f"1-sigma {att.get('sigma_cross_boresight_arcsec', float('nan')):.1f}\" cross-boresight, "
                     f"{att.get('sigma_roll_arcsec', float('nan')):.0f}\" roll")
    for i, s in enumerate(stars):
        pic.marker("identified" if i in labels else "detected", s["x"], s["y"], _radius(s.get("flux")))
    for i in sorted(labels):
        if 0 <= i < len(stars):
            s = stars[i]
            pic.label(labels[i], (int(round(s["x"])), int(round(s["y"]))), _radius(s.get("flux")))
    status = ident.get("status", "?")
    title = f"{status}: {len(labels)} of {len(stars)} detected stars identified"
    if ident.get("algorithm"):
        title += f" ({ident['algorithm']})"
    pic.panel([title] + lines, ["identified", "detected"] + kinds, compass)
    pic.save(path)


def _draw_constellations(pic, catalog, a, cam, mirrored: bool) -> None:
    """The stick figures and names of the constellations in view, beneath everything else."""
    from startrack.constellations import figure_segments_in_image, load_figures

    colour = MARKERS["constellation"][0]
    for figure, polylines, where in figure_segments_in_image(load_figures(), catalog, a, cam):
        for pts in polylines:
            if mirrored:
                pts = np.column_stack([2.0 * cam.cx - pts[:, 0], pts[:, 1]])
            pic.polyline(pts, colour)
        x = 2.0 * cam.cx - where[0] if mirrored else where[0]
        x = float(min(max(x, 0.0), cam.width - 1.0))
        y = float(min(max(where[1], 0.0), cam.height - 1.0))
        pic.label(figure.name.upper(), (int(round(x)), int(round(y))), 0.0, colour)


def _attitude_matrix(att: dict) -> np.ndarray:
    if "dcm" in att:
        return np.asarray(att["dcm"], dtype=float)
    from startrack.rotations import quaternion_to_dcm

    return quaternion_to_dcm(att["quaternion"])


def _catalog_at_epoch(catalog, att: dict):
    """The catalog propagated to the attitude's epoch (decimal year), when it records one."""
    epoch = att.get("epoch")
    if isinstance(epoch, (int, float)) and math.isfinite(epoch) and abs(epoch - float(catalog.epoch)) > 1e-6:
        return catalog.propagate(float(epoch))
    return catalog


def _north_east_in_image(a: np.ndarray, cam) -> tuple[np.ndarray, np.ndarray]:
    """Image-plane unit directions of celestial north and east at the image centre."""
    from startrack.rotations import _east_north_rad

    centre = cam.pixels_to_vectors(np.array([(cam.width - 1) / 2.0]), np.array([(cam.height - 1) / 2.0]))[0]
    inertial = a.T @ centre
    ra = math.atan2(inertial[1], inertial[0])
    dec = math.asin(max(-1.0, min(1.0, inertial[2])))
    east, north = _east_north_rad(ra, dec)
    x0, y0 = cam.vectors_to_pixels(centre)
    out = []
    for d in (north, east):
        x1, y1 = cam.vectors_to_pixels(a @ (inertial + 1e-3 * d))
        out.append(np.array([float(x1 - x0), float(y1 - y0)]))
    return out[0], out[1]


#: A success panel whose every interval lies above this is drawn on a broken axis (0 and the data's band);
#: below it, on one axis from 0 to 100 %.
BROKEN_AXIS_ABOVE = 0.8


def success_axis_range(lows) -> tuple[float, float] | None:
    """The band (per cent) a broken success axis shows above its stub at 0, or None for one zero-based axis.

    The band holds every Wilson interval with a margin of a tenth of its span, widened to at least
    1 percentage point (so 99.9 % and 99.8 % are told apart without looking like 0 and 100), its
    bottom rounded down to a tick of the span's order, and it ends at 100 %.  None when any interval
    reaches below :data:`BROKEN_AXIS_ABOVE`: then the whole axis from 0 is drawn.
    """
    lows = [v for v in lows if v == v]
    if not lows or min(lows) < BROKEN_AXIS_ABOVE:
        return None
    lo = 100.0 * min(lows)
    span = max(1.0, 1.1 * (100.0 - lo))
    step = 10 ** math.floor(math.log10(span)) / 2
    bottom = max(100.0 * BROKEN_AXIS_ABOVE, math.floor((100.0 - span) / step) * step)
    return bottom, 100.0


def plot_results(rows, path: str, x_field: str | None = None, title: str = "") -> str:
    """Success rate (with its Wilson 95 % interval) and median time against the swept condition, one line per
    algorithm.

    The success axis does not exaggerate: it runs from 0 to 100 %, or, when every interval lies above
    :data:`BROKEN_AXIS_ABOVE`, it is drawn broken (:func:`success_axis_range`): a stub at 0, break marks,
    and the band the intervals occupy, so 99.9 % never looks like a crash.

    Parameters
    ----------
    rows : list of dict
        :func:`startrack.evaluate.evaluate` rows (``algorithm``, ``success``, ``frames``, ``success_rate``,
        ``median_ms``, conditions); rows without their intervals get them from their counts.
    path : str
        The picture to write (atomically): PNG, PDF or SVG by its suffix.
    x_field : str, optional
        The swept condition (default: the first that varies).
    """
    from startrack.evaluate import with_intervals

    picture_format(path)
    rows = [with_intervals(r) for r in rows]
    fields = ["false_stars", "focal_error_pct", "sigma_arcsec" if rows and rows[0].get("sigma_arcsec") is not None
              else "sigma_px", "mag_noise", "drop_fraction", "min_stars"]
    if x_field is None:
        x_field = next((f for f in fields if len({r[f] for r in rows}) > 1), "false_stars")
    names = {"false_stars": "false stars per frame", "focal_error_pct": "focal-length error (%)",
             "sigma_px": "centroid noise (px, 1 sigma)", "sigma_arcsec": "centroid noise (arcsec, 1 sigma)",
             "mag_noise": "magnitude noise (mag)",
             "drop_fraction": "fraction of stars dropped", "min_stars": "minimum stars per frame"}
    from matplotlib.ticker import FuncFormatter, LogLocator, MaxNLocator, NullFormatter

    fig = _figure(figsize=(11, 4.8), dpi=110)
    band = success_axis_range([r["success_rate_low"] for r in rows])
    grid = fig.add_gridspec(2, 2, height_ratios=(7, 1), hspace=0.05, wspace=0.25)
    ax1 = fig.add_subplot(grid[0, 0] if band else grid[:, 0])
    stub = fig.add_subplot(grid[1, 0], sharex=ax1) if band else None
    ax2 = fig.add_subplot(grid[:, 1])
    algorithms = list(dict.fromkeys(r["algorithm"] for r in rows))
    styles = ["-", "--", "-.", ":"]
    markers = ["o", "s", "^", "D", "v", "P", "X", "*"]
    values = sorted({r[x_field] for r in rows})
    step = min((b - a for a, b in zip(values, values[1:])), default=1.0) or 1.0
    for k, algorithm in enumerate(algorithms):
        sub = sorted((r for r in rows if r["algorithm"] == algorithm), key=lambda r: r[x_field])
        # Lines that coincide (several algorithms at 100 %) are told apart by a small sideways
        # offset, a marker and a line style of their own.
        shift = (k - (len(algorithms) - 1) / 2) * 0.06 * step
        xs = [r[x_field] + shift for r in sub]
        style = dict(marker=markers[k % len(markers)], linestyle=styles[k % len(styles)], label=algorithm,
                     markersize=5, linewidth=1.4, alpha=0.9)
        rate = [100 * r["success_rate"] for r in sub]
        err = [[100 * (r["success_rate"] - r["success_rate_low"]) for r in sub],
               [100 * (r["success_rate_high"] - r["success_rate"]) for r in sub]]
        for ax in (ax1, stub) if stub is not None else (ax1,):
            ax.errorbar(xs, rate, yerr=err, capsize=3, elinewidth=1.0, **style)
        ax2.plot(xs, [r["median_ms"] for r in sub], **style)
    integer = x_field in ("false_stars", "min_stars")
    for ax in (stub if stub is not None else ax1, ax2):
        ax.set_xlabel(names.get(x_field, x_field))
        if integer:
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        else:
            ax.set_xticks(values)
    ax1.set_ylabel("success rate (%), 95 % interval")
    ax1.grid(alpha=0.3)
    ax1.legend(fontsize=8, loc="lower left")
    if band is None:
        ax1.set_ylim(0, 102)
    else:
        ax1.set_ylim(band[0], band[1] + 0.02 * (band[1] - band[0]))
        stub.set_ylim(0, 1.02 * (band[1] - band[0]) / 7)     # the stub: zero, at the band's scale
        stub.set_yticks([0])
        stub.grid(alpha=0.3)
        ax1.tick_params(labelbottom=False, bottom=False)
        ax1.spines["bottom"].set_visible(False)
        stub.spines["top"].set_visible(False)
        # break marks across both axes' y spines (matplotlib's broken-axis idiom)
        mark = dict(marker=[(-1, -0.5), (1, 0.5)], markersize=10, linestyle="none", color="k", mec="k", mew=1,
                    clip_on=False)
        ax1.plot([0, 1], [0, 0], transform=ax1.transAxes, **mark)
        stub.plot([0, 1], [1, 1], transform=stub.transAxes, **mark)
        ax1.text(0.99, 0.02, f"axis broken: 0 to {band[0]:g} % left out", transform=ax1.transAxes, ha="right",
                 va="bottom", fontsize=8, color="0.3")
    ax2.set_ylabel("median identification time (ms)")
    ax2.set_yscale("log")
    # 1-2-5 ticks with plain numbers: a range within one decade still has labels
    ax2.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    ax2.yaxis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:g}"))
    ax2.yaxis.set_minor_formatter(NullFormatter())
    ax2.grid(alpha=0.3, which="both")
    n = rows[0]["frames"] if rows else 0
    fixed = [f"{names.get(f, f)} {rows[0][f]:g}" for f in fields if f != x_field and rows and
             rows[0].get(f) and len({r[f] for r in rows}) == 1]
    conditions = f"{n:,} random attitudes per point" + (f"; {', '.join(fixed)}" if fixed else "")
    fig.suptitle(f"{title}\n{conditions}" if title else conditions, fontsize=10)
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.12, top=0.86)
    _save(fig, path)
    return path
