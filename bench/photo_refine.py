"""The `photo` node (nodes/mesh/photo.py): photo-consistent refinement of the relaxed mesh, against the unmoved
mesh and a uniform shrink by the same median offset (the control: is it where it moves, or only that it moves
in?), in the same run.

    python3 bench/photo_refine.py [--held 15] [--picture docs/photo_refine_thu.jpg]

1. Synthetic figure (graphs/demo.yaml frame 0, the truth known): Chamfer distance to the true surface and mean
   silhouette IoU, before / photo / shrink; seconds.
2. thu_wd_human, one held-out camera: the refinement and the texture from the other 19 views, rendered into the
   held-out one; PSNR on the pixels all three meshes cover; a picture: photo | ours | ours on the refined mesh.
Meshes and images come from bench/texture_loo.py's dataset runs (its cache).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from texture_loo import load_dataset, psnr, subset  # noqa: E402

from nodes.common.meshops import vertex_normals  # noqa: E402
from nodes.common.raster import render_texture  # noqa: E402
from nodes.common.types import Mesh  # noqa: E402
from nodes.eval.silhouette import silhouette_report  # noqa: E402
from nodes.eval.surface import surface_report  # noqa: E402
from nodes.mesh.photo import photo_offsets  # noqa: E402
from nodes.texture.texturing import Settings, texture_mesh  # noqa: E402


def synthetic(cache: Path):
    import trimesh

    mesh, images, masks, cams = load_dataset("synthetic_figure", cache)
    runs = json.loads((Path("/tmp/volcap_texture_loo/synthetic_figure") / "run.json").read_text())["items"]
    stage = next(Path(r["cache_dir"]) for r in runs if r["node"] == "stage" and r.get("frame") in (0, None))
    truth = Mesh.load(stage / "mesh")
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    t = time.perf_counter()
    r = photo_offsets(V, F, images.images, masks.masks, cams)
    sec = time.perf_counter() - t
    n = vertex_normals(V, F)
    print(f"synthetic figure: {len(V)} vertices, {len(cams)} views, photo {sec:.2f} s; {int(r.pinned.sum())} vertices "
          f"kept for the outlines; offsets median {np.median(r.offsets) * 1000:.2f} mm")
    print("| mesh | Chamfer to the truth, mm | accuracy / completeness, mm | mean IoU |")
    print("|---|---|---|---|")
    for name, VV in (("relaxed (input)", V), ("photo", V + r.offsets[:, None] * n),
                     ("uniform shrink by the median offset", V + np.median(r.offsets) * n)):
        rep = surface_report(trimesh.Trimesh(VV, F, process=False), truth)
        iou = silhouette_report(VV, F, cams, masks)["mean_iou"]
        print(f"| {name} | {rep['chamfer'] * 1000:.2f} | {rep['accuracy_mean'] * 1000:.2f} / "
              f"{rep['completeness_mean'] * 1000:.2f} | {iou:.4f} |")


def held_out(cache: Path, i: int, picture):
    import cv2

    mesh, images, masks, cams = load_dataset("thu_wd_human", cache)
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    keep = [j for j in range(len(cams)) if j != i]
    imgs, msk, sub = [images.images[j] for j in keep], [masks.masks[j] for j in keep], subset(cams, keep)
    t = time.perf_counter()
    r = photo_offsets(V, F, imgs, msk, sub)
    sec = time.perf_counter() - t
    n = vertex_normals(V, F)
    meshes = {"ours": V, "ours + photo": V + r.offsets[:, None] * n, "ours + shrink": V + np.median(r.offsets) * n}
    renders = {}
    t_tex = []
    for name, VV in meshes.items():
        t = time.perf_counter()
        res = texture_mesh(VV, F, imgs, msk, sub, Settings(size=2048))
        t_tex.append(time.perf_counter() - t)
        renders[name] = render_texture(VV, F, res.atlas.uv01(), res.texture, cams, i)
    common = np.logical_and.reduce([h for _, h in renders.values()])
    photo, mask = images.images[i], masks.masks[i]
    print(f"\nthu_wd_human held-out {cams[i].name}: {len(V)} vertices, photo {sec:.2f} s (texture {np.median(t_tex):.2f} s); "
          f"PSNR on the {int((common & (mask > 127)).sum())} pixels all three cover: " +
          ", ".join(f"{k} {psnr(rr, common, photo, mask):.2f} dB" for k, (rr, _) in renders.items()))
    if picture:
        ys, xs = np.nonzero(mask > 127)
        y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
        h = y1 - y0
        top = max(y0, y0 + h // 8)                    # the head and shoulders: where the detail is
        crop = lambda im: np.ascontiguousarray(im[top: top + h // 3, x0:x1])  # noqa: E731
        tiles = []
        for label, im in (("held-out photo", photo), ("ours", renders["ours"][0]),
                          ("ours + photo", renders["ours + photo"][0])):
            c = crop(im)
            c = cv2.resize(c, (int(c.shape[1] * 480 / c.shape[0]), 480), interpolation=cv2.INTER_CUBIC)
            cv2.putText(c, label, (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 0), 1, cv2.LINE_AA)
            tiles.append(c)
        Path(picture).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(picture), np.hstack(tiles)[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 88])
        print(f"picture: {picture}")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--held", type=int, default=15)
    ap.add_argument("--cache", default="/tmp/volcap_texture_loo/cache")
    ap.add_argument("--picture", default=None)
    args = ap.parse_args()
    from machine import describe, load_average

    print(describe())
    synthetic(Path(args.cache))
    held_out(Path(args.cache), args.held, args.picture)
    print(f"load {load_average()}")


if __name__ == "__main__":
    main()
