"""Leave-one-camera-out PSNR of texturing (Waechter 2017 "virtual rephotography"): texture a mesh without
camera i, render it into camera i, compare with the real photo inside mask_i and the render.

    python3 bench/texture_loo.py [--datasets thu_wd_human,...] [--held 5] [--no-meshlab] [--picture docs/x.png]

Meshes come from the dataset graphs (graphs/datasets/*.yaml; the synthetic scene: graphs/demo.yaml frame 0),
run through the CLI into a cache. Methods, all on the same mesh and the same held-out cameras:
  vertex colours   per-vertex mean of the views that see the vertex (z-buffer) inside their mask
  MeshLab          pymeshlab texture from registered rasters (masks given as alpha, alpha weight on), 2048^2
  ours             the texture node's defaults, 2048^2 atlas (and its vertex-colour mode)
Also counted for ours: texels whose surface point is background in every mask that sees it, and how many of
those were painted from an image (must be 0).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from nodes.common.cameras import Cameras  # noqa: E402
from nodes.common.raster import rasterize, render_texture  # noqa: E402
from nodes.common.types import CameraSet, Images, Masks, Mesh  # noqa: E402
from nodes.texture.quality import background_texels  # noqa: E402
from nodes.texture.texturing import Settings, texture_mesh  # noqa: E402

DATASETS = {  # graph, mesh node, masks node (port 'masks'), images node (port 'images'), cameras node
    "synthetic_figure": ("graphs/demo.yaml", "mesh", "stage", "stage", "stage"),
    "thu_wd_human": ("graphs/datasets/thu_wd_human.yaml", "relax", "capture", "capture", "capture"),
    "middlebury_templeSR": ("graphs/datasets/middlebury_templeSR.yaml", "mesh", "key", "capture", "capture"),
    "oxford_dino": ("graphs/datasets/oxford_dino.yaml", "mesh", "masks", "capture", "capture"),
    "nerf_lego": ("graphs/datasets/nerf_lego.yaml", "mesh", "capture", "capture", "capture"),
}


def load_dataset(name: str, cache: Path):
    graph, mesh_node, mask_node, img_node, cam_node = DATASETS[name]
    out = Path(f"/tmp/volcap_texture_loo/{name}")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, str(ROOT / "app.py"), "run", str(ROOT / graph), "--out", str(out), "--cache",
                        str(cache), "--frames", "0:1", "--jobs", "1", "--keep-all"], env=env, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{graph}: {r.stdout[-500:]} {r.stderr[-500:]}")
    recs = {rec["node"]: Path(rec["cache_dir"]) for rec in json.loads((out / "run.json").read_text())["items"]
            if rec.get("cache_dir")}
    mesh = Mesh.load(recs[mesh_node] / "mesh")
    masks = Masks.load(recs[mask_node] / "masks")
    images = Images.load(recs[img_node] / "images")
    cams = CameraSet.load(recs[cam_node] / "cameras")
    return mesh, images, masks, cams


def subset(cams: Cameras, keep):
    return Cameras([cams[i] for i in keep])


def psnr(render, hit, photo, mask):
    sel = hit & (mask > 127)
    if not np.any(sel):
        return float("nan")
    d = render[sel].astype(np.float64) - photo[sel].astype(np.float64)
    mse = float(np.mean(d * d))
    return 10 * np.log10(255.0 ** 2 / max(mse, 1e-12))


def vertex_colour_baseline(vertices, faces, images, masks, cams, tol_frac=0.01):
    """Per-vertex mean colour over the views where the vertex passes the z-buffer test and is in the mask."""
    v = np.asarray(vertices, np.float64)
    tol = tol_frac * np.linalg.norm(np.ptp(v, axis=0))
    acc = np.zeros((len(v), 3))
    cnt = np.zeros(len(v))
    for i in range(len(cams)):
        _, depth, _ = rasterize(v, faces, cams, i)
        uv, z = cams.project(v, i)
        h, w = depth.shape
        x, y = np.round(uv[:, 0]).astype(np.int64), np.round(uv[:, 1]).astype(np.int64)
        ok = (x >= 0) & (y >= 0) & (x < w) & (y < h) & (z > 0)
        xs, ys = np.where(ok, x, 0), np.where(ok, y, 0)
        ok &= (z <= depth[ys, xs] + tol) & (masks[i][ys, xs] > 127)
        acc[ok] += images[i][ys[ok], xs[ok]]
        cnt[ok] += 1
    col = np.where(cnt[:, None] > 0, acc / np.maximum(cnt, 1)[:, None], 128)
    return col.astype(np.float32)


def evaluate(name, cache, held_n, use_meshlab, size, picture=None):
    mesh, images, masks, cams = load_dataset(name, cache)
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    n = len(cams)
    held = sorted(set(np.linspace(0, n - 1, held_n + 1)[:-1].round().astype(int).tolist()))
    rows = {k: [] for k in ("vertex colours", "MeshLab", "ours (vertex)", "ours")}
    extra = {"faces": len(F), "views": n, "held": held, "bg_texels": 0, "bg_painted": 0, "ours_s": [], "meshlab_s": []}
    tiles = []
    for i in held:
        keep = [j for j in range(n) if j != i]
        ci = cams
        imgs = [images.images[j] for j in keep]
        msk = [masks.masks[j] for j in keep]
        sub = subset(cams, keep)
        photo, mask_i = images.images[i], masks.masks[i]
        col = vertex_colour_baseline(V, F, imgs, msk, sub)
        r_vc, hit = render_texture(V, F, None, None, ci, i, face_colours=col[F])
        rows["vertex colours"].append(psnr(r_vc, hit, photo, mask_i))
        t = time.perf_counter()
        res = texture_mesh(V, F, imgs, msk, sub, Settings(size=size))
        extra["ours_s"].append(time.perf_counter() - t)
        r_ours, hit = render_texture(V, F, res.atlas.uv01(), res.texture, ci, i)
        rows["ours"].append(psnr(r_ours, hit, photo, mask_i))
        bg, painted = background_texels(res, V, F, msk, sub)
        extra["bg_texels"] += bg
        extra["bg_painted"] += painted
        resv = texture_mesh(V, F, imgs, msk, sub, Settings(size=size), mode="vertex")
        r_ov, hit = render_texture(V, F, None, None, ci, i, face_colours=resv.vertex_colours.astype(np.float32)[F])
        rows["ours (vertex)"].append(psnr(r_ov, hit, photo, mask_i))
        r_ml = None
        if use_meshlab:
            from meshlab_peer import meshlab_texture

            try:
                ml, sec = meshlab_texture(V, F, imgs, sub, size=size, masks=msk)
                extra["meshlab_s"].append(sec)
                tex = np.asarray(ml.visual.material.image.convert("RGB"))
                r_ml, hit = render_texture(ml.vertices, ml.faces, np.asarray(ml.visual.uv)[ml.faces], tex, ci, i)
                rows["MeshLab"].append(psnr(r_ml, hit, photo, mask_i))
            except Exception as exc:  # reported in the table, not hidden
                print(f"  {name} cam {i}: MeshLab failed: {exc}", file=sys.stderr)
                rows["MeshLab"].append(float("nan"))
        if picture is not None and len(tiles) < 2:
            tiles.append((photo, r_vc, r_ml, r_ours, mask_i))
        print(f"  {name} held-out {cams[i].name}: " + ", ".join(f"{k} {v[-1]:.2f}" for k, v in rows.items() if v), flush=True)
    if picture is not None and tiles:
        save_picture(picture, tiles, name)
    return rows, extra


def save_picture(path, tiles, name):
    import cv2

    out = []
    for photo, vc, ml, ours, mask in tiles:
        ys, xs = np.nonzero(mask > 127)
        pad = 10
        y0, y1 = max(ys.min() - pad, 0), min(ys.max() + pad, mask.shape[0])
        x0, x1 = max(xs.min() - pad, 0), min(xs.max() + pad, mask.shape[1])
        row = [photo, vc] + ([ml] if ml is not None else []) + [ours]
        labels = ["held-out photo", "vertex colours"] + (["MeshLab"] if ml is not None else []) + ["ours"]
        crops = []
        for im, lab in zip(row, labels):
            c = np.ascontiguousarray(im[y0:y1, x0:x1])
            scale = 360 / c.shape[0]
            c = cv2.resize(c, (int(c.shape[1] * scale), 360), interpolation=cv2.INTER_AREA)
            cv2.putText(c, lab, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 0), 1, cv2.LINE_AA)
            crops.append(c)
        out.append(np.hstack(crops))
    w = max(o.shape[1] for o in out)
    out = [np.pad(o, ((0, 0), (0, w - o.shape[1]), (0, 0))) for o in out]
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.vstack(out)[:, :, ::-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--datasets", default=",".join(DATASETS))
    ap.add_argument("--held", type=int, default=5)
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--no-meshlab", action="store_true")
    ap.add_argument("--cache", default="/tmp/volcap_texture_loo/cache")
    ap.add_argument("--pictures", default=None, help="folder for held-out comparison pictures")
    args = ap.parse_args()
    from machine import describe, load_average

    print(describe())
    table = []
    for name in args.datasets.split(","):
        pic = None if args.pictures is None else Path(args.pictures) / f"texture_loo_{name}.png"
        rows, extra = evaluate(name, Path(args.cache), args.held, not args.no_meshlab, args.size, pic)
        table.append((name, rows, extra))
    print(f"\nleave-one-camera-out PSNR (dB) inside mask and render, median over held-out cameras; load {load_average()}")
    print("| dataset | faces | views | vertex colours | MeshLab | ours (vertex mode) | **ours** | bg texels (painted) | ours s/frame | MeshLab s/frame |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, rows, ex in table:
        med = {k: (np.nanmedian(v) if v and not np.all(np.isnan(v)) else float("nan")) for k, v in rows.items()}
        print(f"| {name} | {ex['faces']} | {ex['views']} | {med['vertex colours']:.2f} | {med['MeshLab']:.2f} | "
              f"{med['ours (vertex)']:.2f} | **{med['ours']:.2f}** | {ex['bg_texels']} ({ex['bg_painted']}) | "
              f"{np.median(ex['ours_s']):.2f} | {np.median(ex['meshlab_s']) if ex['meshlab_s'] else float('nan'):.2f} |")


if __name__ == "__main__":
    main()
