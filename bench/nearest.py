"""Nearest points, as tracking asks them (kernels/closest.cl nearest_in_grid, nodes/common/closest.PointGrid) against
scipy's cKDTree, the baseline a user would pick (build + query, one core and all), same run, the same distances asserted: the synth
figure's surface in voxel units (about two vertices per voxel, as a refined mesh at 128^3) queried by the same surface
moved by ~0.3 voxel (a fit's matches), by a sample of 6000 bounded at 15 voxels (the ICP's first iteration) and by
points up to 3 voxels off (a coverage query).

    python bench/nearest.py [--repeats 5]
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from machine import describe, load_average  # noqa: E402
from nodes.common.closest import PointGrid  # noqa: E402
from nodes.synth import scenes  # noqa: E402


def best(fn, repeats):
    out, t = None, float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        t = min(t, time.perf_counter() - t0)
    return t, out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args()
    from scipy.spatial import cKDTree

    print(describe())
    mesh = scenes.build("figure", 0).mesh
    v = np.asarray(mesh.vertices, np.float64)
    edge = np.median(np.linalg.norm(v[mesh.edges_unique[:, 0]] - v[mesh.edges_unique[:, 1]], axis=1))
    pts = (v - v.min(axis=0)) / (2 * edge)                      # voxels: two edges per voxel
    rng = np.random.default_rng(0)
    moved = pts + rng.normal(0, 0.3, pts.shape)
    sets = [("surface moved 0.3 voxel", moved, np.inf),
            ("6000 samples, bounded at 15", moved[rng.choice(len(moved), 6000, replace=False)], 15.0),
            ("points up to 3 voxels off", pts + rng.uniform(-3, 3, pts.shape), 2.5)]
    print(f"{len(pts)} points ({np.ptp(pts, axis=0).round(1)} voxels)")
    print(f"{'queries':32s} {'n':>6s} {'grid ms':>8s} {'cKDTree ms':>11s} {'ratio':>6s} {'all cores ms':>13s} {'ratio':>6s}")
    PointGrid(pts).nearest(moved[:10])                           # the kernel built
    for name, q, upper in sets:
        tg, (d, _) = best(lambda: PointGrid(pts).nearest(q, upper), a.repeats)
        tk, (rd, _) = best(lambda: cKDTree(pts).query(q, distance_upper_bound=upper), a.repeats)
        tw, (wd, _) = best(lambda: cKDTree(pts).query(q, distance_upper_bound=upper, workers=-1), a.repeats)
        assert np.array_equal(d, rd) and np.array_equal(d, wd), name
        print(f"{name:32s} {len(q):6d} {1000 * tg:8.2f} {1000 * tk:11.2f} {tk / tg:5.2f}x {1000 * tw:13.2f} {tw / tg:5.2f}x")
    print(f"load average at the end: {load_average()}")


if __name__ == "__main__":
    main()
