"""Carve quality on synthetic scenes with ground truth: visual hull vs its photo hull (carve.space_carving,
carve.voxel_coloring where the cameras allow it), from the synth node's renders.

    python bench/carve_quality.py                       # cup, bowl, figure; dome of 16 cameras, 96^3
    python bench/carve_quality.py --scenes cup --res 64

Per scene and method: volume error |V - V_true| / V_true (voxel count x voxel volume), Chamfer distance to
the true surface relative to its bounding-box diagonal (all of it, and in the concave regions only: true
surface points more than 2 voxels from the surface of the truth's convex hull; there the error counts both
ways: completeness from the truth points of the region to the mesh, accuracy from the mesh points whose
nearest truth point is in the region or that lie off the truth inside its convex hull, such as a lid),
silhouette IoU with the masks and with the hull mesh's own silhouettes (mean and min over views), and the
mean colour variance over views of the surface voxels (rgb^2).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from nodegraph import NodeError, clrt  # noqa: E402
from nodegraph.testing import run_node  # noqa: E402
from nodes.common import raster  # noqa: E402


def concave_chamfer(mesh, truth, region_margin: float, samples: int = 60000) -> tuple[float, float]:
    """(Chamfer over the whole surface, Chamfer in the concave regions, its accuracy and completeness parts), all
    relative to the truth's bounding-box diagonal."""
    import trimesh
    from scipy.spatial import ConvexHull, cKDTree

    pt, _ = trimesh.sample.sample_surface(truth, samples, seed=0)
    pm, _ = trimesh.sample.sample_surface(mesh, samples, seed=0)
    eq = ConvexHull(truth.vertices).equations            # n . x + b <= 0 inside, |n| = 1
    d_hull = -(pt @ eq[:, :3].T + eq[:, 3]).max(axis=1)  # distance to the convex hull's surface (inside points)
    concave = d_hull > region_margin
    d_tm, _ = cKDTree(pm).query(pt)
    d_mt, nearest = cKDTree(pt).query(pm)
    diag = float(np.linalg.norm(np.ptp(truth.bounds, axis=0)))
    whole = 0.5 * (d_tm.mean() + d_mt.mean()) / diag
    # mesh points of the region: nearest to a concave truth point, or off the truth inside its convex hull (a lid)
    m_hull = -(pm @ eq[:, :3].T + eq[:, 3]).max(axis=1)
    in_region = concave[nearest] | ((d_mt > region_margin) & (m_hull >= -region_margin))
    comp = d_tm[concave].mean() / diag
    acc = (d_mt[in_region].mean() if in_region.any() else 0.0) / diag
    return float(whole), float(0.5 * (comp + acc)), float(acc), float(comp)


def bowl_scene():
    """A checkered hemispherical bowl (outer radius 0.4 m, wall 0.04 m), opening up: a concavity whose inside
    is textured (the synth cup's floor is one plain colour, so part of its inside is truly ambiguous)."""
    import trimesh

    from nodes.synth import scenes

    R, t = 0.4, 0.04
    th = np.linspace(0, np.pi / 2, 40)
    outer = np.stack([R * np.sin(th), R - R * np.cos(th)], 1)
    inner = np.stack([(R - t) * np.sin(th), R - (R - t) * np.cos(th)], 1)[::-1]
    mesh = trimesh.creation.revolve(np.vstack([outer, inner]), sections=96)
    mesh.merge_vertices()
    if mesh.volume < 0:
        mesh.invert()
    mats = np.array([scenes.material((0.85, 0.3, 0.2), (0.9, 0.85, 0.6), 1.0, 0.07)])   # 1.0: checker
    return scenes.Scene(mesh, mesh.vertices.copy(), np.zeros(len(mesh.faces), np.int32), mats,
                        np.array([0.0, 0.0, 0.2]), 0.45)


def synth_capture(scene: str, cameras: int, width: int, height: int) -> dict:
    """What the synth node gives (images, masks, cameras, mesh, bounds) for a synth scene or "bowl" (built here
    and rendered by the synth stage's own renderer)."""
    if scene != "bowl":
        return run_node("synth", {}, {"scene": scene, "rig": "dome", "cameras": cameras, "width": width, "height": height})
    from nodes.common.types import ImageSet, MaskSet
    from nodes.synth.render import render_scene, ring_rig

    sc = bowl_scene()
    cams = ring_rig(cameras, sc.center, sc.radius, 50.0, width, height, dome=True)
    images, masks = render_scene(sc, cams, "green", True)
    lo, hi = sc.mesh.bounds
    pad = 0.05 * np.linalg.norm(hi - lo)
    return {"images": ImageSet(images, cams.names), "masks": MaskSet(masks, names=cams.names), "cameras": cams,
            "mesh": sc.mesh, "bounds": np.array([lo - pad, hi + pad])}


def silhouettes(mesh, cameras):
    return [s > 0 for s in raster.silhouette(mesh.vertices, mesh.faces, cameras)]


def iou(a, b) -> list[float]:
    return [float((x & y).sum() / max(1, (x | y).sum())) for x, y in zip(a, b)]


def evaluate(scene: str, res: int, cameras: int, width: int, height: int, params: dict) -> list[dict]:
    s = synth_capture(scene, cameras, width, height)
    truth, cams = s["mesh"], s["cameras"]
    hull = run_node("hull", {"masks": s["masks"], "cameras": cams, "bounds": s["bounds"]}, {"resolution": res})["volume"]
    vox = float(np.prod(hull.voxel_size))
    masks = [m > 127 for m in s["masks"].masks]
    rows = []
    hull_sil = None
    colour = run_node("carve.space_carving", {"volume": hull, "images": s["images"], "masks": s["masks"], "cameras": cams},
                      {"max_passes": 0})["report"]
    for name in ("hull", "carve.space_carving", "carve.voxel_coloring"):
        t = time.perf_counter()
        if name == "hull":
            vol, var = hull, colour["variance_out"]
        else:
            try:
                out = run_node(name, {"volume": hull, "images": s["images"], "masks": s["masks"], "cameras": cams}, params)
            except NodeError as exc:
                rows.append({"scene": scene, "method": name, "note": str(exc)[:90]})
                continue
            vol, var = out["volume"], out["report"]["variance_out"]
        secs = time.perf_counter() - t
        mesh = run_node("mc", {"volume": vol}, {})["mesh"]
        sil = silhouettes(mesh, cams)
        if hull_sil is None:
            hull_sil = sil
        whole, region, acc, comp = concave_chamfer(mesh, truth, 2 * float(hull.voxel_size.max()))
        rows.append({
            "scene": scene, "method": name, "voxels": int(vol.occupancy.sum()),
            "vol_err": abs(vol.occupancy.sum() * vox - truth.volume) / truth.volume,
            "chamfer": whole, "chamfer_concave": region, "acc_concave": acc, "comp_concave": comp,
            "iou_masks": float(np.mean(iou(sil, masks))), "iou_masks_min": float(np.min(iou(sil, masks))),
            "iou_hull": float(np.mean(iou(sil, hull_sil))), "iou_hull_min": float(np.min(iou(sil, hull_sil))),
            "variance": var, "seconds": secs if name != "hull" else 0.0,
        })
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=["cup", "bowl", "figure"], help="synth scenes, or bowl")
    ap.add_argument("--res", type=int, default=96)
    ap.add_argument("--cameras", type=int, default=16)
    ap.add_argument("--size", type=int, nargs=2, default=[320, 240])
    ap.add_argument("--threshold", type=float, default=None)
    ap.add_argument("--set", nargs="*", default=[], help="more node params, NAME=VALUE")
    args = ap.parse_args()
    params = {} if args.threshold is None else {"threshold": args.threshold}
    for kv in args.set:
        k, v = kv.split("=")
        params[k] = float(v) if "." in v else int(v)
    print(f"OpenCL: {clrt.device_name()}; load average {os.getloadavg()[0]:.2f}")
    print(f"dome of {args.cameras} cameras, {args.size[0]}x{args.size[1]}, hull at {args.res}^3, params {params or 'defaults'}")
    head = f"{'scene':8s} {'method':22s} {'voxels':>8s} {'vol err':>8s} {'chamfer':>8s} {'concave':>8s} " \
           f"{'IoU mask':>9s} {'(min)':>6s} {'IoU hull':>9s} {'(min)':>6s} {'col var':>8s} {'s':>6s}"
    print(head)
    for scene in args.scenes:
        rows = evaluate(scene, args.res, args.cameras, *args.size, params)
        base = rows[0]
        for r in rows:
            if "note" in r:
                print(f"{r['scene']:8s} {r['method']:22s} {r['note']}")
                continue
            print(f"{r['scene']:8s} {r['method']:22s} {r['voxels']:8d} {r['vol_err']:8.3f} {r['chamfer']:8.4f} "
                  f"{r['chamfer_concave']:8.4f} {r['iou_masks']:9.4f} {r['iou_masks_min']:6.3f} {r['iou_hull']:9.4f} "
                  f"{r['iou_hull_min']:6.3f} {r['variance']:8.0f} {r['seconds']:6.2f}   (concave: accuracy "
                  f"{r['acc_concave']:.4f}, completeness {r['comp_concave']:.4f})")
            if r is not base:
                print(f"{'':31s} vs hull: volume error x{r['vol_err'] / base['vol_err']:.2f}, concave Chamfer "
                      f"{100 * (r['chamfer_concave'] / base['chamfer_concave'] - 1):+.0f} %, colour variance "
                      f"x{r['variance'] / max(base['variance'], 1e-9):.2f}")
    print(f"load average now {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
