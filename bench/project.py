"""Camera projection and automatic bounds: speed against what a user would otherwise write.

    python bench/project.py [--points 1000000] [--cameras 24] [dataset]   # dataset under $VOLCAP_DATA for bounds

Projection of N world points into every camera of a distorted 24-camera ring (1920x1080, k1 k2 p1 p2 k3):
cv2.projectPoints per camera, our float64 NumPy Cameras.project, our OpenCL project_points_cl (kernels/
project.cl). Max difference to OpenCV is printed too. Bounds: nodes.bounds.auto_bounds on a real dataset's
shipped masks (no library baseline: the alternative is a box typed by hand).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from nodes.common.cameras import Camera, Cameras, look_at, project_points_cl  # noqa: E402


def best(fn, repeats=5):
    times, out = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return 1e3 * min(times), out


def ring(n: int) -> Cameras:
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        c = look_at([3 * np.cos(a), 3 * np.sin(a), 1.2], [0, 0, 0.9], [0, 0, 1], 50, 1920, 1080, name=f"cam{i:02d}")
        cams.append(Camera(c.name, c.width, c.height, c.K, c.Rt, [-0.12, 0.03, 1e-4, -2e-4, -0.002]))
    return Cameras(cams)


def main():
    import cv2

    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--cameras", type=int, default=24)
    ap.add_argument("dataset", nargs="?", default="thu_wd_human")
    args = ap.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from machine import describe

    print(describe())
    cams = ring(args.cameras)
    rng = np.random.default_rng(0)
    X = rng.uniform([-0.8, -0.8, 0], [0.8, 0.8, 1.8], (args.points, 3))

    def opencv():
        out = []
        for c in cams:
            rvec, _ = cv2.Rodrigues(c.Rt[:, :3])
            uv, _ = cv2.projectPoints(X, rvec, c.Rt[:, 3], c.K, c.dist)
            out.append(uv[:, 0])
        return np.stack(out)

    t_cv, ref = best(opencv, 3)
    t_np, ours_np = best(lambda: np.stack([cams.project(X, v)[0] for v in range(len(cams))]), 3)
    project_points_cl(cams, X[:1000])  # build the kernel once
    t_cl, ours_cl = best(lambda: project_points_cl(cams, X)[0])
    n = args.points * len(cams)
    print(f"projection of {args.points:,} points into {len(cams)} distorted 1920x1080 cameras ({n / 1e6:.0f} M projections)")
    print(f"{'method':34s} {'ms':>9s} {'Mpts/s':>8s} {'max |du| vs OpenCV px':>22s}")
    for name, t, uv in (("cv2.projectPoints (per camera)", t_cv, ref), ("NumPy Cameras.project (float64)", t_np, ours_np),
                        ("OpenCL project_points_cl", t_cl, np.asarray(ours_cl).reshape(ref.shape))):
        print(f"{name:34s} {t:9.1f} {n / t / 1e3:8.1f} {np.abs(uv - ref).max():22.2e}")

    data = Path(os.environ.get("VOLCAP_DATA", ROOT.parent / "shared" / "data")) / args.dataset
    if data.is_dir():
        from nodes.common.bounds import auto_bounds
        from nodes.capture.load import load_capture

        cap = load_capture(data)
        t_b, box = best(lambda: auto_bounds(cap["masks"].masks, cap["cameras"]), 3)
        print(f"auto_bounds on {args.dataset} ({len(cap['cameras'])} views): {t_b:.0f} ms, box {np.round(box, 3).tolist()}")


if __name__ == "__main__":
    main()
