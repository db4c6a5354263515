#!/usr/bin/env python3
"""Landmarks from a Middlebury ground-truth disparity (docs/results.md, "Landmarks and
alignment"): samples N correspondences (x, y) -> (x - d, y) of known disparity, 12 px
inside both images, with a fixed seed (7), and writes beside each points file a truth
with those points' 9x9 neighbourhoods marked unknown, so that `deepmorph eval --truth`
measures the endpoint error on the other pixels only.

usage: points_from_disparity.py DISPARITY.png OUT_DIR N [N ...]
writes OUT_DIR/points_N.csv and OUT_DIR/truth_N.png (needs numpy and pillow)
"""
import sys

import numpy as np
from PIL import Image


def main():
    src, out, counts = sys.argv[1], sys.argv[2], [int(n) for n in sys.argv[3:]]
    raw = np.array(Image.open(src)).astype(np.int64)
    d = raw / 256.0
    h, w = d.shape
    ys, xs = np.nonzero(raw > 0)
    margin = 12
    ok = (xs >= margin) & (xs < w - margin) & (ys >= margin) & (ys < h - margin)
    ok &= xs - d[ys, xs] >= margin
    ys, xs = ys[ok], xs[ok]
    order = np.random.RandomState(7).permutation(len(xs))
    for n in counts:
        pick = order[:n]
        with open(f"{out}/points_{n}.csv", "w") as f:
            f.write("x_a,y_a,x_b,y_b\n")
            for i in pick:
                x, y = xs[i], ys[i]
                f.write(f"{x},{y},{x - d[y, x]:.4f},{y}\n")
        held = raw.copy()
        for i in pick:
            x, y = xs[i], ys[i]
            held[max(0, y - 4) : y + 5, max(0, x - 4) : x + 5] = 0
        Image.fromarray(held.astype(np.uint16)).save(f"{out}/truth_{n}.png")


if __name__ == "__main__":
    main()
