"""Synthetic capture speed: the synth node at 24 x 1920x1080 (figure, green and plate backdrops), and the
silhouette rasterizer against an independent cv2.fillPoly silhouette (no rasterizer baseline is named in
REFERENCES.md; fillPoly of every projected triangle is what a user would write with OpenCV) and against the
z-buffer's coverage (MeshRaster.coverage: the silhouette's route before stop 53's raster_cover; the same pixels).

    python bench/synth.py [--cameras 24] [--width 1920] [--height 1080]
"""
import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from machine import describe, load_average  # noqa: E402
from nodes.common import raster  # noqa: E402
from nodes.synth import scenes  # noqa: E402
from nodes.synth import render as synth  # noqa: E402
from nodes.synth.nodes import Synth  # noqa: E402


def timed(fn, repeat=2):
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def fillpoly_silhouettes(vertices, faces, cameras):
    masks = []
    for view, cam in enumerate(cameras):
        uv, _ = cameras.project(vertices, view)
        m = np.zeros((cam.height, cam.width), np.uint8)
        for tri in np.round(uv[faces] * 16).astype(np.int32):
            cv2.fillPoly(m, [tri], 255, shift=4)
        masks.append(m)
    return masks


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--cameras", type=int, default=24)
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    a = ap.parse_args()
    print(describe())
    base = {k: p.default for k, p in Synth.params.items()}
    base.update(cameras=a.cameras, width=a.width, height=a.height)
    rows = []
    for scene, bg in (("figure", "green"), ("figure", "plate"), ("cup", "green")):
        Synth().run(**dict(base, scene=scene, background=bg, width=64, height=48), frame=0)   # build + compile
        t, _ = timed(lambda: Synth().run(**dict(base, scene=scene, background=bg), frame=1))
        rows.append((f"synth {scene}/{bg}", t))
    sc = scenes.build("figure", 1)
    cams = synth.ring_rig(a.cameras, sc.center, sc.radius, 50.0, a.width, a.height)
    v, f = sc.mesh.vertices, sc.mesh.faces
    t_sil, ours = timed(lambda: raster.silhouette(v, f, cams))
    rows.append(("raster.silhouette (OpenCL)", t_sil))

    def zbuffer_coverage():
        r = raster.MeshRaster(v, f, cams)
        return [r.coverage(i) for i in range(len(cams))]

    t_z, zbuf = timed(zbuffer_coverage)
    assert all(np.array_equal(x, y) for x, y in zip(ours, zbuf)), "raster_cover differs from the z-buffer's coverage"
    rows.append(("z-buffer coverage (before stop 53)", t_z))
    t_cv, theirs = timed(lambda: fillpoly_silhouettes(v, f, cams), repeat=1)
    rows.append(("cv2.fillPoly per triangle (baseline)", t_cv))
    ious = [np.logical_and(x > 0, y > 0).sum() / np.logical_or(x > 0, y > 0).sum() for x, y in zip(ours, theirs)]
    print(f"\n{a.cameras} cameras x {a.width}x{a.height}, figure {len(v)} vertices / {len(f)} faces")
    print(f"{'what':40s} {'total s':>9s} {'ms/view':>9s}")
    for name, t in rows:
        print(f"{name:40s} {t:9.2f} {1000 * t / a.cameras:9.1f}")
    print(f"silhouette IoU vs fillPoly: min {min(ious):.4f} (fillPoly also fills pixels touching an edge); "
          f"the z-buffer's coverage: the same pixels, {t_z / t_sil:.2f}x the time")
    print(f"load average at the end: {load_average()}")


if __name__ == "__main__":
    main()
