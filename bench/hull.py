"""Hull speed: dense NumPy vs dense OpenCL vs sparse coarse-to-fine OpenCL, ms per frame (min of repeats).

Synthetic ring rig of 1920x1080 cameras looking at a blob figure (torso, head, limbs: ellipsoids).
    python bench/hull.py                 # 128^3, 256^3, 512^3 x 8, 16, 24 cameras
    python bench/hull.py --quick         # 128^3 x 24 only
Masks are uploaded and prepared on every call (part of the time), as in a real per-frame run; the column
"prep ms" is that part alone (bit packing and block summed-area tables of the masks).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from nodes.common.cameras import Cameras, look_at  # noqa: E402
from nodes.common.types import MaskSet  # noqa: E402
from nodes.common.silhouettes import SilhouetteBits  # noqa: E402
from nodes.hull.hull import HullCL, hull_grid, hull_reference  # noqa: E402

# (centre, radii) of the figure's ellipsoids, metres, z up
FIGURE = [((0, 0, 1.2), (0.18, 0.12, 0.3)), ((0, 0, 1.65), (0.11, 0.11, 0.12)),
          ((-0.1, 0, 0.5), (0.07, 0.07, 0.45)), ((0.1, 0, 0.5), (0.07, 0.07, 0.45)),
          ((-0.35, 0, 1.3), (0.3, 0.05, 0.05)), ((0.35, 0, 1.3), (0.3, 0.05, 0.05))]
BOX = np.array([[-0.95, -0.95, 0.0], [0.95, 0.95, 1.9]])  # a cube: resolution 128 gives 128^3 voxels


def ring_rig(n: int, width=1920, height=1080, radius=3.5) -> Cameras:
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = [radius * np.cos(a), radius * np.sin(a), 1.0 + 0.6 * (i % 3)]
        cams.append(look_at(eye, [0, 0, 0.95], [0, 0, 1], 45, width, height, f"cam{i:02d}"))
    return Cameras(cams)


def figure_masks(cams: Cameras, figure=FIGURE) -> MaskSet:
    """Silhouettes of a union of ellipsoids: filled convex hulls of projected surface samples."""
    u = np.random.default_rng(1).normal(size=(3000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    masks = []
    for v, cam in enumerate(cams):
        m = np.zeros((cam.height, cam.width), np.uint8)
        for c, r in figure:
            uv, _ = cams.project(np.asarray(c) + u * np.asarray(r), v)
            cv2.fillPoly(m, [cv2.convexHull(np.round(uv * 16).astype(np.int32))], 255, cv2.LINE_8, shift=4)
        masks.append(m)
    return MaskSet(masks)


def best_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    return min(times)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from machine import describe

    print(describe())
    cases = [(128, 24)] if args.quick else [(r, n) for n in (24, 16, 8) for r in (128, 256, 512)]
    h = HullCL.get()
    print(f"{'grid':>14} {'cams':>4} {'voxels in':>10} {'numpy ms':>9} {'dense ms':>9} {'sparse ms':>9} {'prep ms':>8} {'equal':>6}")
    for res, ncam in cases:
        cams = ring_rig(ncam)
        masks = [np.ascontiguousarray(m) for m in figure_masks(cams).masks]
        bmin, bmax, dims = hull_grid(BOX, res)
        vs = (bmax - bmin) / np.array(dims)
        run = lambda method: h.hull(masks, cams, bmin, vs, dims, method=method)  # noqa: E731
        sparse = run("sparse")
        dense = run("dense")
        t_sparse = best_ms(lambda: run("sparse"), args.repeats)
        t_dense = best_ms(lambda: run("dense"), max(1, args.repeats // 2))
        t_prep = best_ms(lambda: SilhouetteBits.from_masks(masks, out=h.silhouettes), args.repeats)
        t_np = "-"
        if res <= 128:
            t = time.perf_counter()
            ref = hull_reference(masks, cams, bmin, vs, dims)
            t_np = f"{(time.perf_counter() - t) * 1e3:9.0f}"
            same = bool(np.array_equal(ref, sparse) and np.array_equal(ref, dense))
        else:
            same = bool(np.array_equal(dense, sparse))
        grid = "x".join(map(str, dims))
        print(f"{grid:>14} {ncam:>4} {int(sparse.sum()):>10} {t_np:>9} {t_dense:9.1f} {t_sparse:9.1f} {t_prep:8.1f} {str(same):>6}", flush=True)


if __name__ == "__main__":
    main()
