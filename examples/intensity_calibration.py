"""Paper 003's Eq. 9 calibration the paper's way: the intensity of identified bright stars averaged over images.

    .venv/bin/python examples/intensity_calibration.py -d DB --fov-deg F --size WxH [--mag-max M]
        [--sigma-arcsec S] [--mag-noise E] [--frames 100] [--seed 1] [--k 3]

"In_k is obtained by averaging the intensity values of an identified bright star in different images"
(paper 003 Sec. 4.1).  Star lists of the sensor (as ``startrack evaluate`` makes them) are identified
with the pyramid; the brightest identified star of each gives ``In_k = In 2.512^(m - k)`` with ``m``
its catalog magnitude, and their mean is the calibration.  Prints ``K:IN_K``, the value of
``--brightness-calibration``.
"""
from __future__ import annotations

import argparse


def calibrate(db, camera, catalog, frames: int, seed: int, sigma_px: float, mag_noise: float, mag_limit: float,
              k: float = 3.0):
    """``(k, In_k, frames used)`` from ``frames`` star lists identified by the pyramid."""
    import numpy as np

    from startrack.evaluate import Condition, make_frames
    from startrack.identify import IdentifyParams, identify_stars
    from startrack.identify.brightness import intensity_calibration

    params = IdentifyParams(sigma_px=max(sigma_px, 0.01))
    samples = []
    index = {int(i): n for n, i in enumerate(db.star_id)}
    for stars, _, _ in make_frames(catalog, camera, Condition(sigma_px=sigma_px, mag_noise=mag_noise), frames, seed,
                                   mag_limit=mag_limit):
        res = identify_stars(stars, camera, db, "pyramid", params)
        if res.status != "ok":
            continue
        best = min(res.matches, key=lambda m: m.star)       # stars come brightest first
        samples.append((float(db.star_mag[index[int(best.id)]]), float(stars[best.star]["flux"])))
    cal = intensity_calibration(np.array(samples), k)
    return cal[0], cal[1], len(samples)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-d", "--database", required=True)
    ap.add_argument("--fov-deg", type=float, required=True)
    ap.add_argument("--size", required=True)
    ap.add_argument("--mag-max", type=float, default=None)
    ap.add_argument("--sigma-arcsec", type=float, default=5.0)
    ap.add_argument("--mag-noise", type=float, default=0.0)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--k", type=float, default=3.0)
    a = ap.parse_args(argv)

    from startrack.camera import Camera
    from startrack.catalog import load_catalog
    from startrack.kvector import load_kvector

    w, h = (int(v) for v in a.size.lower().split("x"))
    cam = Camera.from_fov(a.fov_deg, w, h)
    db = load_kvector(a.database)
    lim = a.mag_max if a.mag_max is not None else float(db.star_mag.max())
    cat = load_catalog(None, mag_max=lim).filter_magnitude(None, lim)
    k, in_k, n = calibrate(db, cam, cat, a.frames, a.seed, a.sigma_arcsec / cam.pixel_scale_arcsec, a.mag_noise, lim,
                           a.k)
    if n == 0:
        raise SystemExit("intensity_calibration: no frame identified")
    print(f"{k:g}:{in_k:.6g}")


if __name__ == "__main__":
    main()
