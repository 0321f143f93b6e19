"""Carve on real captures: visual hull vs its photo hull (carve.space_carving, defaults) on the Middlebury
temple, the Oxford dino and the NeRF lego, at 128^3. Per dataset: connected components of the volume,
mask pixels the marching-cubes mesh does not cover (summed over views; a hole through the model would show
here), mask pixels the hull's voxel cubes cover and the carved voxel cubes do not (the guard's promise: 0),
mean silhouette IoU, mean colour variance over views of the surface voxels (rgb^2), and a picture: shaded
hull, shaded carved, carved with its voxel colours, from three of the dataset's cameras
(docs/carve_NAME.png).

    python bench/carve_realdata.py                      # all three, pictures into docs/
    python bench/carve_realdata.py --datasets oxford_dino --res 96 --no-pictures
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from nodegraph import clrt  # noqa: E402
from nodegraph.testing import run_node  # noqa: E402
from nodes.eval.silhouette import silhouette_report  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
TEMPLE_BOX = [-0.047606, -0.031878, -0.063887, 0.054817, 0.043303, 0.096277]


def capture(name: str, data: Path, res: int):
    """(images, masks, cameras, hull) with the recipe of graphs/datasets/NAME.yaml."""
    cap = run_node("capture", {}, {"path": str(data / name)})
    cams = cap["cameras"]
    if name == "middlebury_templeSR":
        masks = run_node("key.threshold", {"images": cap["images"]}, {"threshold": 0.19, "dilate": 10, "erode": 7})["masks"]
        hull = run_node("hull", {"masks": masks, "cameras": cams}, {"resolution": res, "bbox": TEMPLE_BOX})["volume"]
    else:
        if name == "oxford_dino":
            keyed = run_node("key.chroma", {"images": cap["images"]}, {"side": 0.0, "inner": -0.05, "outer": 0.05})["masks"]
            masks = run_node("key.cleanup", {"masks": keyed}, {"open": 1, "close": 0, "fill_holes": False})["masks"]
        else:
            masks = cap["masks"]
        box = run_node("bounds", {"masks": masks, "cameras": cams})["bounds"]
        hull = run_node("hull", {"masks": masks, "cameras": cams, "bounds": box}, {"resolution": res})["volume"]
    return cap["images"], masks, cams, hull


def cube_cover(vol, cameras) -> list:
    """Per view, the pixels the volume's voxel cubes cover (the surface voxels' cubes: a ray into the solid
    enters through one), by the z-buffer rasterizer."""
    import trimesh
    from scipy import ndimage

    from nodes.common import raster

    occ = vol.occupancy.astype(bool)
    surf = occ & ~ndimage.binary_erosion(occ, border_value=0)
    X = vol.centers()[surf]
    box = trimesh.creation.box(vol.voxel_size)
    V = (box.vertices[None] + X[:, None]).reshape(-1, 3)
    F = (box.faces[None] + 8 * np.arange(len(X))[:, None, None]).reshape(-1, 3)
    return [m > 0 for m in raster.silhouette(V, F, cameras)]


def components(occ) -> int:
    from scipy import ndimage

    return int(ndimage.label(occ)[1])


def pictures(meshes, cameras, path: Path, size: int = 300):
    """Rows: shaded hull, shaded carved, carved in its vertex colours; columns: three of the cameras (their
    own up direction)."""
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv

    views = [0, len(cameras) // 3, (2 * len(cameras)) // 3]
    rows = [(meshes[0], False), (meshes[1], False), (meshes[1], True)]
    p = pv.Plotter(off_screen=True, window_size=(size * len(views), size * len(rows)), shape=(len(rows), len(views)),
                   border=False)
    for r, (m, colour) in enumerate(rows):
        pm = pv.PolyData(np.asarray(m.vertices), np.hstack([np.full((len(m.faces), 1), 3), m.faces]).ravel())
        if colour:
            pm["rgb"] = np.asarray(m.visual.vertex_colors)[:, :3]
        for k, v in enumerate(views):
            p.subplot(r, k)
            if colour:
                p.add_mesh(pm, scalars="rgb", rgb=True, lighting=False)
            else:
                p.add_mesh(pm, color="#d9d2c3", smooth_shading=False)
            cam = cameras[v]
            C = cam.center
            centre = np.asarray(m.bounds).mean(axis=0)
            d = centre - C
            _, dirs = cameras.rays(v, [[cam.width / 2, 0], [cam.width / 2, cam.height]])   # image up
            up = dirs[0] - dirs[1]
            up -= d * (up @ d) / (d @ d)
            ext = float(np.ptp(m.bounds, axis=0).max())
            eye = centre - 2.6 * ext * d / np.linalg.norm(d)
            p.camera_position = [tuple(eye), tuple(centre), tuple(up / np.linalg.norm(up))]
            if k == 0:
                p.add_text(["visual hull", "space carving", "space carving, voxel colours"][r], font_size=9,
                           color="black")
    p.set_background("white")
    p.screenshot(str(path))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=os.environ.get("VOLCAP_DATA", str(ROOT.parent / "shared" / "data")))
    ap.add_argument("--datasets", nargs="+", default=["middlebury_templeSR", "oxford_dino", "nerf_lego"])
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--no-pictures", action="store_true")
    args = ap.parse_args()
    print(f"OpenCL: {clrt.device_name()}; load average {os.getloadavg()[0]:.2f}; hull at {args.res}^3, "
          "carve.space_carving defaults")
    print(f"{'dataset':20s} {'volume':14s} {'voxels':>8s} {'parts':>5s} {'not covered':>11s} {'cubes lost':>10s} "
          f"{'IoU':>7s} {'col var':>8s} {'s':>6s}")
    for name in args.datasets:
        images, masks, cams, hull = capture(name, Path(args.data), args.res)
        inputs = {"volume": hull, "images": images, "masks": masks, "cameras": cams}
        coloured = run_node("carve.space_carving", inputs, {"max_passes": 0})
        t = time.perf_counter()
        carved = run_node("carve.space_carving", inputs)
        secs = time.perf_counter() - t
        meshes = []
        hull_cubes = cube_cover(coloured["volume"], cams)
        for label, out in (("hull", coloured), ("carved", carved)):
            vol = out["volume"]
            mesh = run_node("mc", {"volume": vol}, {"largest": True})["mesh"]
            meshes.append(mesh)
            sil = silhouette_report(mesh.vertices, mesh.faces, cams, masks)
            cubes = hull_cubes if label == "hull" else cube_cover(vol, cams)
            lost = sum(int(((m > 127) & a & ~b).sum()) for m, a, b in zip(masks.masks, hull_cubes, cubes))
            print(f"{name:20s} {label:14s} {int(vol.occupancy.sum()):8d} {components(vol.occupancy):5d} "
                  f"{sil['mask_not_covered']:11d} {lost:10d} {sil['mean_iou']:7.4f} {out['report']['variance_out']:8.0f} "
                  f"{secs if label == 'carved' else 0.0:6.2f}")
        if not args.no_pictures:
            path = ROOT / "docs" / f"carve_{name}.png"
            pictures(meshes, cams, path)
            print(f"{'':20s} picture: {path.relative_to(ROOT)}")
    print(f"load average now {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
