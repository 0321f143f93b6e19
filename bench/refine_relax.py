"""Speed and effect of refine and relax, against the baselines (REFERENCES.md): relax vs
trimesh.smoothing.filter_taubin on the same mesh (time, volume change, roughness), refine time vs a plain
finer grid (refine = vertices onto the hull + 2 rounds of edge splits; "no splits" = Liang & Wong alone).
Prints a table.

    python bench/refine_relax.py [thu_wd_human]      # a real dataset under $VOLCAP_DATA, default thu_wd_human
"""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np
import trimesh

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from nodegraph.testing import run_node  # noqa: E402
from nodes.hull.bounds import auto_bounds  # noqa: E402
from nodes.capture.load import load_capture  # noqa: E402
from nodes.eval.silhouette import silhouette_report  # noqa: E402
from nodes.hull.hull import visual_hull  # noqa: E402
from nodes.common.meshops import largest_component  # noqa: E402
from nodes.mesh.mc import marching_cubes  # noqa: E402
from nodes.mesh.relax import LAMBDA, MU, taubin_cl  # noqa: E402
from nodes.common.meshops import vertex_neighbours  # noqa: E402


def best_of(fn, repeat=5):
    times, out = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return min(times), out


def roughness(m) -> float:
    return float(np.degrees(m.face_adjacency_angles.mean()))


def main(name="thu_wd_human"):
    data = Path(os.environ.get("VOLCAP_DATA", ROOT.parent / "shared" / "data"))
    cap = load_capture(data / name)
    masks, cams = cap["masks"], cap["cameras"]
    box = auto_bounds(masks.masks, cams)
    rows = []

    def row(label, seconds, mesh, base):
        r = silhouette_report(mesh.vertices, mesh.faces, cams, masks)
        rows.append((label, seconds * 1000, len(mesh.vertices), mesh.volume / base.volume - 1, roughness(mesh),
                     r["mean_iou"], r["mesh_outside_mask"], r["mask_not_covered"]))

    meshes = {}
    for res in (128, 256):
        vol = visual_hull(masks, cams, box, res)
        t, mesh = best_of(lambda: trimesh.Trimesh(*largest_component(*marching_cubes(vol)), process=False), 3)
        meshes[res] = (vol, mesh)
        row(f"plain mc {res}^3 (mc time)", t, mesh, mesh)
    vol, mesh = meshes[128]
    args = {"mesh": mesh, "volume": vol, "masks": masks, "cameras": cams}
    run_node("refine", args)  # build kernels once
    t, on_edges = best_of(lambda: run_node("refine", args, {"split_rounds": 0})["mesh"], 3)
    row("refine 128^3, no splits", t, on_edges, mesh)
    t, ref = best_of(lambda: run_node("refine", args)["mesh"], 3)
    row("refine 128^3 (2 split rounds)", t, ref, mesh)
    t, _ = best_of(lambda: run_node("refine", args, {"split_rounds": 0, "method": "numpy"})["mesh"], 1)
    rows.append(("refine 128^3 no splits, NumPy ref.", t * 1000, len(mesh.vertices), *[float("nan")] * 5))
    for it in (5, 10):
        free = {"mesh": ref}
        t, m = best_of(lambda: run_node("relax", free, {"iterations": it, "keep_silhouettes": False})["mesh"])
        row(f"relax {it} it, free", t, m, ref)
        t, m = best_of(lambda: trimesh.smoothing.filter_taubin(ref.copy(), lamb=LAMBDA, nu=-MU, iterations=2 * it))
        row(f"trimesh filter_taubin {it} pairs", t, m, ref)
        kept = {"mesh": ref, "masks": masks, "cameras": cams}
        t, m = best_of(lambda: run_node("relax", kept, {"iterations": it})["mesh"])
        row(f"relax {it} it, keep_silhouettes", t, m, ref)

    for res, (_, m) in meshes.items():  # the smoothing alone, without node overhead (neighbours, normals, clamp)
        off, nb = vertex_neighbours(m.faces, len(m.vertices))
        taubin_cl(m.vertices, off, nb, 10)
        t, _ = best_of(lambda: taubin_cl(m.vertices, off, nb, 10))
        lap = trimesh.smoothing.laplacian_calculation(m)
        t2, _ = best_of(lambda: trimesh.smoothing.filter_taubin(m.copy(), lamb=LAMBDA, nu=-MU, iterations=20,
                                                             laplacian_operator=lap))
        rows.append((f"taubin_cl 10 pairs, {len(m.vertices)} v", t * 1000, len(m.vertices), *[float("nan")] * 5))
        rows.append(("filter_taubin 10 pairs (L given)", t2 * 1000, len(m.vertices), *[float("nan")] * 5))

    print(f"{name}: {len(cams)} views, relax/taubin volume change relative to the refined mesh")
    head = ("step", "ms", "verts", "dVol", "rough deg", "mean IoU", "outside px", "not covered px")
    print(f"{head[0]:34s} {head[1]:>8s} {head[2]:>7s} {head[3]:>8s} {head[4]:>9s} {head[5]:>8s} {head[6]:>10s} {head[7]:>14s}")
    for r in rows:
        print(f"{r[0]:34s} {r[1]:8.1f} {r[2]:7d} {r[3]:+8.4f} {r[4]:9.2f} {r[5]:8.4f} {r[6]:10.0f} {r[7]:14.0f}")


if __name__ == "__main__":
    main(*sys.argv[1:])
