"""Shaded renders of plain marching cubes, refine, relax (and the seed's refine + relax) side by side, 128^3,
written to docs/surface_<scene>.png (pyvista off-screen, smooth shading, seen from one of the scene's cameras).

    python bench/render_surfaces.py [synth_figure crease_robot thu_wd_human inria_dancer]
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import trimesh

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from legacy_surface import legacy_refine, legacy_relax  # noqa: E402
from refine_relax import mc_mesh, scene  # noqa: E402

from nodegraph.testing import run_node  # noqa: E402
from nodes.eval.health import mesh_health  # noqa: E402


def shot(mesh, cam, size, zoom_box):
    import pyvista as pv

    faces = np.hstack([np.full((len(mesh.faces), 1), 3), mesh.faces]).ravel()
    poly = pv.PolyData(np.asarray(mesh.vertices), faces)
    p = pv.Plotter(off_screen=True, window_size=size)
    p.add_mesh(poly, color=(0.82, 0.80, 0.76), smooth_shading=True, specular=0.25, specular_power=20)
    lo, hi = zoom_box
    centre = 0.5 * (lo + hi)
    eye = cam.center
    direction = (centre - eye) / np.linalg.norm(centre - eye)
    up = -cam.Rt[1, :3]
    dist = 1.1 * np.linalg.norm(hi - lo) / (2 * np.tan(np.radians(15)))
    p.camera.position = tuple(centre - dist * direction)
    p.camera.focal_point = tuple(centre)
    p.camera.up = tuple(up)
    p.camera.view_angle = 30
    p.add_light(pv.Light(position=tuple(centre - dist * direction + 0.5 * dist * up), focal_point=tuple(centre)))
    img = p.screenshot(return_img=True)
    p.close()
    return img


def main(names):
    import cv2

    out_dir = ROOT / "docs"
    for name in names:
        masks, cams, box, truth = scene(name.replace("_", " ") if name in ("synth_figure", "crease_robot") else name)
        vol, mesh = mc_mesh(masks, cams, box, 128)
        args = {"mesh": mesh, "volume": vol, "masks": masks, "cameras": cams}
        ref = run_node("refine", args)["mesh"]
        rel = run_node("relax", {"mesh": ref, "masks": masks, "cameras": cams})["mesh"]
        old = legacy_relax(legacy_refine(mesh, vol, masks, cams), masks, cams)
        cam = cams[{"synth_figure": 3, "crease_robot": 2}.get(name, 1) % len(cams)]
        lo, hi = rel.bounds
        panels = []
        for label, m in (("plain mc", mesh), ("refine", ref), ("relax", rel), ("seed: refine + relax", old)):
            h = mesh_health(m)
            img = shot(trimesh.Trimesh(m.vertices, m.faces, process=False), cam, (520, 700), (lo, hi))
            img = np.ascontiguousarray(img[:, :, ::-1])
            cv2.putText(img, label, (12, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (20, 20, 20), 2)
            cv2.putText(img, f"{len(m.faces)} faces, {h['folded_edges']} folded", (12, 58), cv2.FONT_HERSHEY_SIMPLEX,
                        0.55, (20, 20, 20), 1)
            cv2.putText(img, f"<5 deg {100 * h['min_angle_below_5']:.2f} %, rough {h['roughness_deg']:.1f} deg",
                        (12, 80), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (20, 20, 20), 1)
            panels.append(img)
        path = out_dir / f"surface_{name}.png"
        cv2.imwrite(str(path), np.hstack(panels))
        print(path)


if __name__ == "__main__":
    from machine import describe

    print(describe())
    main(sys.argv[1:] or ["synth_figure", "crease_robot", "thu_wd_human", "inria_dancer"])
