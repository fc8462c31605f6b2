"""Study (issue 4), recorded in benchmarks/studies/README.md: how many of the 20 brightest ESA detections are stars.

How many of the 20 brightest detections on each ESA image are real stars.

``startrack centroid``'s default detection (``find_stars`` with default options)
on each image; the image is then solved blind (``solve_image``) and the shipped
catalog (Hp <= 8) projected with that attitude and fitted camera.  A detection
counts as a true star when a catalog star lands within 2 px of it.

    .venv/bin/python benchmarks/studies/esa_true_stars.py
"""
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common, the tools
from common import esa_images  # noqa: E402


def main(radius_px=2.0, n_brightest=20):
    from startrack.catalog import load_catalog
    from startrack.centroid import CentroidOptions, find_stars
    from startrack.imageio import read_image
    from startrack.solve import solve_image

    cat = load_catalog()
    vec = cat.vectors()
    print(f"| image | stars found | true among the {n_brightest} brightest |")
    print("|---|---|---|")
    for path in esa_images():
        img, meta = read_image(path)
        stars = find_stars(img, CentroidOptions(), saturation=meta["saturation"]).stars
        sol = solve_image(img)
        name = os.path.basename(path)
        if sol.status != "ok":
            print(f"| {name} | {len(stars)} | not solved: {sol.reason} |")
            continue
        cam = sol.camera
        cam_vec = vec @ sol.attitude.dcm.T
        front = cam_vec[:, 2] > 0.9
        px, py = cam.vectors_to_pixels(cam_vec[front])
        top = stars[:n_brightest]
        true = sum(1 for s in top if np.min(np.hypot(px - s["x"], py - s["y"])) <= radius_px)
        print(f"| {name} | {len(stars)} | {true}/{len(top)} |")


if __name__ == "__main__":
    main()
