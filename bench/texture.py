"""Texturing speed per frame: 100k faces, 24 views at 1920x1080 (the synthetic figure, subdivided), split into
visibility / selection / levelling / atlas / baking, with a new atlas and with the atlas reused (a tracked
sequence), next to MeshLab (pymeshlab texture from registered rasters) and xatlas alone, on the same mesh in
the same run. Goals (issue 15): <= 2 s per frame with atlas reuse, <= 5 s with a new atlas, on a 2-core CPU.
"New atlas" is a segment's first frame (what reuse.py keeps per connectivity and atlas is forgotten before it);
"atlas reused" a later frame of the segment.

    python3 bench/texture.py [--repeat 3] [--no-meshlab] [--no-xatlas] [--size 2048]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from machine import describe, load_average  # noqa: E402
from nodegraph.testing import run_node  # noqa: E402
from nodes.texture import reuse as reuse_memo  # noqa: E402
from nodes.texture.texturing import Settings, texture_mesh  # noqa: E402

STEPS = ("visibility", "selection", "levelling", "atlas", "baking")


def scene(faces_wanted=100_000, cameras=24, width=1920, height=1080):
    out = run_node("synth", {}, {"scene": "figure", "cameras": cameras, "width": width, "height": height, "rig": "dome"})
    mesh = out["mesh"]
    while len(mesh.faces) * 4 <= faces_wanted * 1.2:
        mesh = mesh.subdivide()
    return mesh, out["images"].images, out["masks"].masks, out["cameras"]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--no-meshlab", action="store_true")
    ap.add_argument("--no-xatlas", action="store_true")
    args = ap.parse_args()
    print(describe())
    mesh, images, masks, cams = scene()
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    print(f"mesh: {len(V)} vertices, {len(F)} faces; {len(cams)} views {cams[0].width}x{cams[0].height}; atlas {args.size}^2")
    s = Settings(size=args.size)
    texture_mesh(V, F, images, masks, cams, s)                      # warm-up: kernels built, buffers made
    new, reuse = [], []
    atlas = None
    cpu_new, cpu_reuse = [], []
    for _ in range(args.repeat):
        reuse_memo.clear()              # a new atlas: nothing known about this connectivity or layout yet
        t, c = time.perf_counter(), time.process_time()
        r = texture_mesh(V, F, images, masks, cams, s)
        new.append((time.perf_counter() - t, r.timings))
        cpu_new.append(time.process_time() - c)
        atlas = r.atlas
        t, c = time.perf_counter(), time.process_time()
        r2 = texture_mesh(V, F, images, masks, cams, s, atlas=atlas)
        reuse.append((time.perf_counter() - t, r2.timings))
        cpu_reuse.append(time.process_time() - c)
    print(f"stats: {r.stats}")

    def row(label, runs):
        best = min(runs, key=lambda x: x[0])
        steps = " | ".join(f"{best[1].get(k, 0.0):.2f}" for k in STEPS)
        print(f"| {label} | {steps} | **{best[0]:.2f}** | {np.median([x[0] for x in runs]):.2f} |")

    print(f"\nload average after: {load_average()}")
    print("| per frame, wall s | " + " | ".join(STEPS) + " | total (best) | total (median) |")
    print("|---|" + "---|" * (len(STEPS) + 2))
    row("ours, new atlas", new)
    row("ours, atlas reused", reuse)
    print(f"CPU seconds per frame (all threads of this process; load-independent): new atlas {min(cpu_new):.2f}, "
          f"atlas reused {min(cpu_reuse):.2f}")
    from nodes.texture.atlas import atlas_stats
    from nodes.texture.bake import uv_raster

    ours = atlas_stats(atlas, uv_raster(atlas.face_uv, atlas.size), V, F)
    print(f"our atlas: {ours['charts']} charts, texel use {ours['texel_use']:.2f}, area stretch 5th percentile "
          f"{ours['stretch_p05']:.2f}")
    if not args.no_xatlas:
        import xatlas

        t = time.perf_counter()
        xa = xatlas.Atlas()
        xa.add_mesh(V.astype(np.float32), F.astype(np.uint32))
        xa.generate()
        sec = time.perf_counter() - t
        print(f"| xatlas (charts + packing) alone | | | | {sec:.2f} | | | |")
        print(f"xatlas: {xa.chart_count} charts, utilization {float(np.mean(xa.utilization)):.2f}, "
              f"{xa.width}x{xa.height} at its default texel density")
    if not args.no_meshlab:
        from meshlab_peer import meshlab_texture

        try:
            _, sec = meshlab_texture(V, F, images, cams, size=args.size, masks=masks)
            print(f"| MeshLab texture from registered rasters (filter time) | | | | | | {sec:.2f} | |")
        except Exception as exc:
            print(f"MeshLab failed: {exc}")
    print(f"load average at the end: {load_average()}")


if __name__ == "__main__":
    main()
