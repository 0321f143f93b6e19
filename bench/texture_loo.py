"""Leave-one-camera-out PSNR of texturing (Waechter 2017 "virtual rephotography"): texture a mesh without
camera i, render it into camera i, compare with the real photo inside mask_i and the render.

    python3 bench/texture_loo.py [--datasets thu_wd_human,...] [--held 5] [--no-meshlab] [--picture docs/x.png]
                                 [--rows baselines,layers,in-sample,...] [--photo-search 0.01]

Meshes come from the dataset graphs (graphs/datasets/*.yaml; the synthetic scene: graphs/demo.yaml frame 0),
run through the CLI into a cache. The *_carved sets take the sparse sets' hull (as their textured graphs make it)
and carve it to its photo hull for each held-out camera from the other cameras alone (carving reads colours: the
held-out photo must not shape the mesh it is scored on; the hull itself, like every set's, is made from all
silhouettes). Methods, all on the same mesh and the same held-out cameras:
  vertex colours   per-vertex mean of the views that see the vertex (z-buffer) inside their mask
  cos^2 mean       the same weighted by cos^2 of the viewing angle (vertex normals), masks eroded by 2 px
  MeshLab          pymeshlab texture from registered rasters (masks given as alpha, alpha weight on), 2048^2
  ours             the texture node's defaults, 2048^2 atlas (and its vertex-colour mode)
  ours + photo     ours on the mesh moved by the photo node (nodes/mesh/photo.py, from the training views),
                   scored where both it and the unmoved mesh cover the held-out image, and ours again on
                   those pixels ("ours (photo's pixels)": the fair comparison)
  ours + layers    the same with `layers: 6`, rendered view-dependently at the held-out camera
                   (viewdep.render_layers: what a player does at that eye)
  photo mesh: ...  vertex colours, cos^2 mean and ours + layers on the photo-refined mesh, all three scored on
                   its own coverage (the same pixels): the layers on the refined mesh against the baselines on
                   the same mesh (``--photo-search``: the photo node's search range for these rows)
  in-sample        ours and ours + layers textured from every camera, the held-out one included (and with
                   `layers: 16`, the most the node keeps)
  oracle           the held-out camera's own photo alone through the same atlas (the geometry's ceiling)
PSNR and SSIM (skimage, on the mask's box, averaged inside the mask and the render). Also counted for ours:
texels whose surface point is background in every mask that sees it, and how many of those were painted from
an image (must be 0). ``--rows`` runs some of the methods only (groups: baselines, ours, photo, layers,
photo-layers, in-sample, oracle, vertex, meshlab); VOLCAP_ROOT=DIR scores another checkout's code with this bench.
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

ROOT = Path(os.environ.get("VOLCAP_ROOT") or Path(__file__).resolve().parents[1])
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from nodes.common.cameras import Cameras  # noqa: E402
from nodes.common.meshops import vertex_normals  # noqa: E402
from nodes.common.raster import rasterize, render_texture  # noqa: E402
from nodes.common.types import CameraSet, Images, ImageSet, Masks, MaskSet, Mesh, Volume  # noqa: E402
from nodes.mesh.photo import photo_offsets  # noqa: E402
from nodes.texture.quality import background_texels  # noqa: E402
from nodes.texture.texturing import Settings, texture_mesh  # noqa: E402
from nodes.texture.viewdep import render_layers  # noqa: E402

DATASETS = {  # graph, mesh node, masks node (port 'masks'), images node (port 'images'), cameras node[, hull node]
    "synthetic_figure": ("graphs/demo.yaml", "mesh", "stage", "stage", "stage"),
    "thu_wd_human": ("graphs/datasets/thu_wd_human.yaml", "relax", "capture", "capture", "capture"),
    "middlebury_templeSR": ("graphs/datasets/middlebury_templeSR.yaml", "mesh", "key", "capture", "capture"),
    "oxford_dino": ("graphs/datasets/oxford_dino.yaml", "mesh", "masks", "capture", "capture"),
    "nerf_lego": ("graphs/datasets/nerf_lego.yaml", "mesh", "capture", "capture", "capture"),
    "middlebury_dinoSR": ("graphs/datasets/middlebury_dinoSR.yaml", "mesh", "key", "capture", "capture"),
    # the geometry of the sparse sets' textured graphs (graphs/datasets/*_textured.yaml): the hull (the same key
    # and hull as the plain graphs here) carved to its photo hull (carve.space_carving, then mc). Carving reads
    # colours, so for each held-out camera the hull is carved again from the other cameras alone (the textured
    # graphs' carve params: the defaults); the held-out photo never shapes the mesh it is scored on
    "middlebury_templeSR_carved": ("graphs/datasets/middlebury_templeSR.yaml", "mesh", "key", "capture", "capture",
                                   "hull"),
    "nerf_lego_carved": ("graphs/datasets/nerf_lego.yaml", "mesh", "capture", "capture", "capture", "hull"),
    "middlebury_dinoSR_carved": ("graphs/datasets/middlebury_dinoSR.yaml", "mesh", "key", "capture", "capture",
                                 "hull"),
}


def load_dataset(name: str, cache: Path, hull: bool = False):
    """(mesh, images, masks, cameras) of the dataset's frame 0 from its graph run through the CLI; with ``hull``
    also the volume of its hull node (None where it has none)."""
    graph, mesh_node, mask_node, img_node, cam_node, *hull_node = DATASETS[name]
    out = Path(f"/tmp/volcap_texture_loo/{name}_{os.getpid()}")       # one per process: runs may overlap
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    # the demo's sequence nodes (track, rig) need its frames; the datasets are single frames
    frames = [] if graph == "graphs/demo.yaml" else ["--frames", "0:1"]
    r = subprocess.run([sys.executable, str(ROOT / "app.py"), "run", str(ROOT / graph), "--out", str(out), "--cache",
                        str(cache), *frames, "--jobs", "1", "--keep-all"], env=env, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{graph}: {r.stdout[-500:]} {r.stderr[-500:]}")
    recs = {rec["node"]: Path(rec["cache_dir"]) for rec in json.loads((out / "run.json").read_text())["items"]
            if rec.get("cache_dir") and rec.get("frame") in (0, None)}
    mesh = Mesh.load(recs[mesh_node] / "mesh")
    masks = Masks.load(recs[mask_node] / "masks")
    images = Images.load(recs[img_node] / "images")
    cams = CameraSet.load(recs[cam_node] / "cameras")
    if hull:
        return mesh, images, masks, cams, (Volume.load(recs[hull_node[0]] / "volume") if hull_node else None)
    return mesh, images, masks, cams


def carved_mesh(volume, images, masks, cams):
    """The hull carved to its photo hull from these views only (carve.space_carving's defaults, as the textured
    graphs run it), then mc's largest part: (vertices, faces)."""
    from nodegraph.testing import run_node

    carved = run_node("carve.space_carving", {"volume": volume, "images": ImageSet(images), "masks": MaskSet(masks),
                                              "cameras": cams})["volume"]
    m = run_node("mc", {"volume": carved}, {"largest": True})["mesh"]
    return np.asarray(m.vertices), np.asarray(m.faces)


def subset(cams: Cameras, keep):
    return Cameras([cams[i] for i in keep])


def psnr(render, hit, photo, mask):
    sel = hit & (mask > 127)
    if not np.any(sel):
        return float("nan")
    d = render[sel].astype(np.float64) - photo[sel].astype(np.float64)
    mse = float(np.mean(d * d))
    return 10 * np.log10(255.0 ** 2 / max(mse, 1e-12))


def ssim(render, hit, photo, mask):
    from skimage.metrics import structural_similarity

    sel = hit & (mask > 127)
    if not np.any(sel):
        return float("nan")
    ys, xs = np.nonzero(sel)
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    _, smap = structural_similarity(render[y0:y1, x0:x1], photo[y0:y1, x0:x1], channel_axis=2, data_range=255,
                                    full=True)
    return float(np.mean(smap.mean(axis=2)[sel[y0:y1, x0:x1]]))


def vertex_colour_baseline(vertices, faces, images, masks, cams, tol_frac=0.01, power=0.0, erode=0):
    """Per-vertex mean colour over the views where the vertex passes the z-buffer test and is in the mask
    (``erode`` pixels in from its border); ``power`` > 0 weights each view by cos^power of the angle between
    the vertex normal and the ray to the camera."""
    import cv2

    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    tol = tol_frac * np.linalg.norm(np.ptp(v, axis=0))
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    vn = np.zeros_like(v)
    for k in range(3):
        np.add.at(vn, f[:, k], fn)
    vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)
    acc = np.zeros((len(v), 3))
    cnt = np.zeros(len(v))
    for i in range(len(cams)):
        _, depth, _ = rasterize(v, faces, cams, i)
        uv, z = cams.project(v, i)
        h, w = depth.shape
        x, y = np.round(uv[:, 0]).astype(np.int64), np.round(uv[:, 1]).astype(np.int64)
        ok = (x >= 0) & (y >= 0) & (x < w) & (y < h) & (z > 0)
        xs, ys = np.where(ok, x, 0), np.where(ok, y, 0)
        m = (masks[i] > 127).astype(np.uint8)
        if erode:
            m = cv2.erode(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * erode + 1,) * 2))
        ok &= (z <= depth[ys, xs] + tol) & (m[ys, xs] > 0)
        wgt = np.ones(len(v))
        if power > 0:
            ray = cams.centers[i] - v
            ray /= np.linalg.norm(ray, axis=1, keepdims=True)
            wgt = np.clip(np.einsum("ij,ij->i", vn, ray), 0, 1) ** power
            ok &= wgt > 0
        acc[ok] += wgt[ok, None] * images[i][ys[ok], xs[ok]]
        cnt[ok] += wgt[ok]
    col = np.where(cnt[:, None] > 0, acc / np.maximum(cnt, 1e-12)[:, None], 128)
    return col.astype(np.float32)


ROW_GROUPS = ("baselines", "ours", "photo", "layers", "photo-layers", "in-sample", "oracle", "vertex", "meshlab")


def evaluate(name, cache, held_n, use_meshlab, size, picture=None, groups=ROW_GROUPS, photo_search=0.01):
    mesh, images, masks, cams, hull = load_dataset(name, cache, hull=True)
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    n = len(cams)
    held = sorted(set(np.linspace(0, n - 1, held_n + 1)[:-1].round().astype(int).tolist()))
    rows = {k: [] for k in ("vertex colours", "cos^2 mean", "MeshLab", "ours (vertex)", "ours", "ours (photo's pixels)", "ours + photo", "ours + layers",
                            "photo mesh: vertex colours", "photo mesh: cos^2 mean", "photo mesh: ours + layers",
                            "in-sample ours", "in-sample + layers", "in-sample + 16 layers", "oracle")}
    use_meshlab = use_meshlab and "meshlab" in groups
    ssims = {k: [] for k in rows}
    extra = {"faces": len(F), "views": n, "held": held, "bg_texels": 0, "bg_painted": 0, "ours_s": [], "meshlab_s": []}
    tiles = []
    for i in held:
        keep = [j for j in range(n) if j != i]
        ci = cams
        imgs = [images.images[j] for j in keep]
        msk = [masks.masks[j] for j in keep]
        sub = subset(cams, keep)
        photo, mask_i = images.images[i], masks.masks[i]
        if hull is not None:                        # carved without the held-out camera (DATASETS)
            V, F = carved_mesh(hull, imgs, msk, sub)
            extra.setdefault("carved_faces", []).append(len(F))

        def score(key, render, hit):
            rows[key].append(psnr(render, hit, photo, mask_i))
            ssims[key].append(ssim(render, hit, photo, mask_i))

        r_vc = r_ours = r_vd = None
        if "baselines" in groups:
            col = vertex_colour_baseline(V, F, imgs, msk, sub)
            r_vc, hit = render_texture(V, F, None, None, ci, i, face_colours=col[F])
            score("vertex colours", r_vc, hit)
            col2 = vertex_colour_baseline(V, F, imgs, msk, sub, power=2.0, erode=2)
            score("cos^2 mean", *render_texture(V, F, None, None, ci, i, face_colours=col2[F]))
        if "ours" in groups or "photo" in groups:
            t = time.perf_counter()
            res = texture_mesh(V, F, imgs, msk, sub, Settings(size=size))
            extra["ours_s"].append(time.perf_counter() - t)
            r_ours, hit = render_texture(V, F, res.atlas.uv01(), res.texture, ci, i)
            score("ours", r_ours, hit)
            bg, painted = background_texels(res, V, F, msk, sub)
            extra["bg_texels"] += bg
            extra["bg_painted"] += painted
        if "photo" in groups or "photo-layers" in groups:
            # the photo node's refinement from the training views, then ours; scored where both meshes cover (the
            # refined one moves inward: on its own coverage it would drop rim pixels and look better than it is)
            t = time.perf_counter()
            ph = photo_offsets(V, F, imgs, msk, sub, search=photo_search)
            Vp = V + ph.offsets[:, None] * vertex_normals(V, F)
            extra.setdefault("refine_s", []).append(time.perf_counter() - t)
        if "photo" in groups:
            t = time.perf_counter()
            rp = texture_mesh(Vp, F, imgs, msk, sub, Settings(size=size))
            extra.setdefault("photo_s", []).append(time.perf_counter() - t + extra["refine_s"][-1])
            r_ph, hit_ph = render_texture(Vp, F, rp.atlas.uv01(), rp.texture, ci, i)
            _, hit = render_texture(V, F, None, None, ci, i, face_colours=np.zeros((len(F), 3, 3), np.float32))
            score("ours + photo", r_ph, hit_ph & hit)
            score("ours (photo's pixels)", r_ours, hit_ph & hit)
        if "photo-layers" in groups:
            # the layers on the refined mesh, and the baselines on that same mesh (its own coverage for all three)
            cp = vertex_colour_baseline(Vp, F, imgs, msk, sub)
            score("photo mesh: vertex colours", *render_texture(Vp, F, None, None, ci, i, face_colours=cp[F]))
            cp2 = vertex_colour_baseline(Vp, F, imgs, msk, sub, power=2.0, erode=2)
            score("photo mesh: cos^2 mean", *render_texture(Vp, F, None, None, ci, i, face_colours=cp2[F]))
            rpl = texture_mesh(Vp, F, imgs, msk, sub, Settings(size=size, layers=6))
            score("photo mesh: ours + layers", *render_layers(Vp, F, rpl.atlas.uv01(), rpl.texture, rpl.views, ci, i))
        if "layers" in groups:
            t = time.perf_counter()
            rl = texture_mesh(V, F, imgs, msk, sub, Settings(size=size, layers=6))
            extra.setdefault("layers_s", []).append(time.perf_counter() - t)
            r_vd, hit = render_layers(V, F, rl.atlas.uv01(), rl.texture, rl.views, ci, i)
            score("ours + layers", r_vd, hit)
        if "in-sample" in groups:
            ri = texture_mesh(V, F, images.images, masks.masks, cams, Settings(size=size, layers=6))
            score("in-sample ours", *render_texture(V, F, ri.atlas.uv01(), ri.texture, ci, i))
            score("in-sample + layers", *render_layers(V, F, ri.atlas.uv01(), ri.texture, ri.views, ci, i))
            r16 = texture_mesh(V, F, images.images, masks.masks, cams, Settings(size=size, layers=16))
            score("in-sample + 16 layers", *render_layers(V, F, r16.atlas.uv01(), r16.texture, r16.views, ci, i))
        if "oracle" in groups:
            ro = texture_mesh(V, F, [photo], [mask_i], subset(cams, [i]), Settings(size=size))
            score("oracle", *render_texture(V, F, ro.atlas.uv01(), ro.texture, ci, i))
        if "vertex" in groups:
            resv = texture_mesh(V, F, imgs, msk, sub, Settings(size=size), mode="vertex")
            r_ov, hit = render_texture(V, F, None, None, ci, i, face_colours=resv.vertex_colours.astype(np.float32)[F])
            score("ours (vertex)", r_ov, hit)
        r_ml = None
        if use_meshlab:
            from meshlab_peer import meshlab_texture

            try:
                ml, sec = meshlab_texture(V, F, imgs, sub, size=size, masks=msk)
                extra["meshlab_s"].append(sec)
                tex = np.asarray(ml.visual.material.image.convert("RGB"))
                r_ml, hit = render_texture(ml.vertices, ml.faces, np.asarray(ml.visual.uv)[ml.faces], tex, ci, i)
                score("MeshLab", r_ml, hit)
            except Exception as exc:  # reported in the table, not hidden
                print(f"  {name} cam {i}: MeshLab failed: {exc}", file=sys.stderr)
                rows["MeshLab"].append(float("nan"))
                ssims["MeshLab"].append(float("nan"))
        if picture is not None and r_vc is not None and r_ours is not None and r_vd is not None:
            tiles.append((rows["ours + layers"][-1], (photo, r_vc, r_ml, r_ours, r_vd, mask_i)))
        print(f"  {name} held-out {cams[i].name}: " + ", ".join(f"{k} {v[-1]:.2f}" for k, v in rows.items() if v), flush=True)
    if picture is not None and tiles:
        tiles.sort(key=lambda t: t[0])                     # the worst held-out view (for the layers) first
        save_picture(picture, [t[1] for t in tiles[:2]], name)
    extra["ssim"] = ssims
    return rows, extra


def photo_gain(rows) -> float:
    """Median over held-out cameras of ours + photo minus ours on the same pixels, dB."""
    return float(np.nanmedian(np.subtract(rows["ours + photo"], rows["ours (photo's pixels)"])))


def save_picture(path, tiles, name):
    import cv2

    out = []
    for photo, vc, ml, ours, vd, mask in tiles:
        ys, xs = np.nonzero(mask > 127)
        pad = 10
        y0, y1 = max(ys.min() - pad, 0), min(ys.max() + pad, mask.shape[0])
        x0, x1 = max(xs.min() - pad, 0), min(xs.max() + pad, mask.shape[1])
        row = [photo, vc] + ([ml] if ml is not None else []) + [ours, vd]
        labels = ["held-out photo", "vertex colours"] + (["MeshLab"] if ml is not None else []) + ["ours", "ours + layers"]
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
    ap.add_argument("--rows", default=",".join(ROW_GROUPS), help="method groups to run: " + ", ".join(ROW_GROUPS))
    ap.add_argument("--photo-search", type=float, default=0.01,
                    help="the photo node's search range (fraction of the diagonal) for the photo rows")
    ap.add_argument("--cache", default="/tmp/volcap_texture_loo/cache")
    ap.add_argument("--pictures", default=None, help="folder for held-out comparison pictures")
    args = ap.parse_args()
    from machine import describe, load_average

    groups = tuple(args.rows.split(","))
    bad = [g for g in groups if g not in ROW_GROUPS]
    if bad:
        ap.error(f"unknown --rows {bad}; choose from {', '.join(ROW_GROUPS)}")
    print(describe())
    print(f"code: {ROOT}; photo search {args.photo_search}")
    table = []
    for name in args.datasets.split(","):
        pic = None if args.pictures is None else Path(args.pictures) / f"texture_loo_{name}.jpg"
        rows, extra = evaluate(name, Path(args.cache), args.held, not args.no_meshlab, args.size, pic, groups,
                               args.photo_search)
        table.append((name, rows, extra))
    print("\n" + describe())                               # again beside the figures: the run is long
    print(f"leave-one-camera-out PSNR (dB) / SSIM inside mask and render: median (worst) over held-out cameras; "
          f"load {load_average()}")
    keys = [k for k in table[0][1] if any(rows[k] for _, rows, _ in table)]

    def med(x):
        return float(np.median(x)) if len(x) else float("nan")

    def mdb(rows, k):
        v = rows.get(k, [])
        return float(np.nanmedian(v)) if len(v) and not np.all(np.isnan(v)) else float("nan")

    print("| dataset | faces | views | " + " | ".join(keys) + " | bg texels (painted) | ours s/frame | + layers s/frame |")
    print("|---|---|---|" + "---|" * (len(keys) + 3))
    for name, rows, ex in table:
        cells = []
        for k in keys:
            v, q = np.asarray(rows[k], float), np.asarray(ex["ssim"][k], float)
            cells.append("n/a" if not len(v) or np.all(np.isnan(v)) else
                         f"{np.nanmedian(v):.2f} ({np.nanmin(v):.2f}) / {np.nanmedian(q):.3f}")
        faces = int(np.median(ex["carved_faces"])) if ex.get("carved_faces") else ex["faces"]
        print(f"| {name} | {faces} | {ex['views']} | " + " | ".join(cells) +
              f" | {ex['bg_texels']} ({ex['bg_painted']}) | {med(ex['ours_s']):.2f} | {med(ex.get('layers_s', [])):.2f} |")
    print("\ngain of ours + layers over the best baseline (vertex colours, cos^2 mean, MeshLab), median dB:")
    for name, rows, ex in table:
        best = max([mdb(rows, k) for k in ("vertex colours", "cos^2 mean", "MeshLab") if rows[k]] or [np.nan])
        line = f"  {name}: {mdb(rows, 'ours + layers') - best:+.2f} dB (static ours {mdb(rows, 'ours') - best:+.2f}"
        if rows["ours + photo"]:
            line += (f", + photo {mdb(rows, 'ours + photo') - best:+.2f} (over ours on its pixels "
                     f"{photo_gain(rows):+.2f}), photo + texture {med(ex['photo_s']):.1f} s")
        line += ")"
        if rows["photo mesh: ours + layers"]:
            pbest = max(mdb(rows, "photo mesh: vertex colours"), mdb(rows, "photo mesh: cos^2 mean"))
            pcam = np.subtract(rows["photo mesh: ours + layers"], np.fmax(rows["photo mesh: vertex colours"],
                                                                         rows["photo mesh: cos^2 mean"]))
            line += (f"; on the photo-refined mesh ours + layers {mdb(rows, 'photo mesh: ours + layers'):.2f}: "
                     f"{mdb(rows, 'photo mesh: ours + layers') - pbest:+.2f} over the best baseline on that mesh, "
                     f"{mdb(rows, 'photo mesh: ours + layers') - best:+.2f} over the best on the unrefined one; per "
                     f"camera over that camera's best baseline on the refined mesh, median (worst) "
                     f"{np.nanmedian(pcam):+.2f} ({np.nanmin(pcam):+.2f})")
        if rows["in-sample + layers"]:
            line += (f"; in-sample + 6 / 16 layers {mdb(rows, 'in-sample + layers'):.2f} / "
                     f"{mdb(rows, 'in-sample + 16 layers'):.2f} vs oracle {mdb(rows, 'oracle'):.2f}")
        print(line)
    print("\nat the end: " + describe())                    # the machine beside the gains too (the s/frame columns)


if __name__ == "__main__":
    main()
