"""MeshLab (pymeshlab) as the texturing peer, run in its own process under Xvfb (its raster filters need an
OpenGL context and Qt platform plugins; see docs/REFERENCES "Driving the peers here").

    xvfb-run -a python3 bench/meshlab_peer.py SPEC.json        (bench/texture*.py call meshlab_texture())

SPEC: {"mesh": PLY, "images": [PNG...], "cameras": [{K, R, t, width, height}...], "out": DIR, "size": 2048,
"mode": "atlas" | "vertex"}. Writes DIR/meshlab.obj (+ .mtl + texture) or DIR/meshlab.ply (vertex colours)
and DIR/meshlab.json with the filter's wall time. Setup (bench only, not the product): apt-get install xvfb
libxcb-icccm4 libxcb-keysyms1 libxcb-xinerama0 libgl1-mesa-dri; pip install pymeshlab pyqt5-qt5==5.15.2.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def mlp_camera(K, R, t, width, height) -> str:
    """A VCGCamera element from OpenCV K, R, t (MeshLab: y up, z backwards, centre in pixels from the bottom)."""
    K, R, t = np.asarray(K, float), np.asarray(R, float), np.asarray(t, float).reshape(3)
    C = -R.T @ t
    Rm = np.diag([1.0, -1.0, -1.0]) @ R
    rot = " ".join(f"{x:.12g}" for x in np.vstack([np.hstack([Rm, np.zeros((3, 1))]), [0, 0, 0, 1]]).ravel())
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    return (f'<VCGCamera TranslationVector="{-C[0]:.12g} {-C[1]:.12g} {-C[2]:.12g} 1" LensDistortion="0 0" '
            f'ViewportPx="{width} {height}" PixelSizeMm="1 {fx / fy:.12g}" CenterPx="{cx:.12g} {height - cy:.12g}" '
            f'FocalMm="{fx:.12g}" RotationMatrix="{rot}" CameraType="0"/>')


def write_project(spec: dict, path: Path):
    rasters = []
    for img, cam in zip(spec["images"], spec["cameras"]):
        rasters.append(f'  <MLRaster label="{Path(img).name}">\n   {mlp_camera(cam["K"], cam["R"], cam["t"], cam["width"], cam["height"])}\n'
                       f'   <Plane semantic="1" fileName="{img}"/>\n  </MLRaster>')
    path.write_text('<!DOCTYPE MeshLabDocument>\n<MeshLabProject>\n <MeshGroup>\n'
                    f'  <MLMesh label="mesh" filename="{spec["mesh"]}">\n   <MLMatrix44>\n1 0 0 0 \n0 1 0 0 \n0 0 1 0 \n0 0 0 1 \n</MLMatrix44>\n  </MLMesh>\n'
                    ' </MeshGroup>\n <RasterGroup>\n' + "\n".join(rasters) + '\n </RasterGroup>\n</MeshLabProject>\n')


def run(spec: dict):
    import pymeshlab

    out = Path(spec["out"])
    out.mkdir(parents=True, exist_ok=True)
    mlp = out / "project.mlp"
    write_project(spec, mlp)
    ms = pymeshlab.MeshSet()
    ms.load_project(str(mlp))
    t = time.perf_counter()
    if spec.get("mode", "atlas") == "atlas":
        ms.compute_texcoord_parametrization_and_texture_from_registered_rasters(
            texturesize=int(spec.get("size", 2048)), texturename="meshlab_texture.png",
            usealphaweight=bool(spec.get("alpha", False)))
        seconds = time.perf_counter() - t
        os.chdir(out)
        ms.save_current_mesh(str(out / "meshlab.obj"))
    else:
        ms.compute_color_from_active_rasters_projection()
        seconds = time.perf_counter() - t
        ms.save_current_mesh(str(out / "meshlab.ply"))
    (out / "meshlab.json").write_text(json.dumps({"seconds": seconds}))


def meshlab_texture(vertices, faces, images, cameras, *, size=2048, mode="atlas", masks=None, timeout=900):
    """Run the peer on a mesh and camera images (OpenCV cameras). Returns (trimesh mesh, seconds) or raises
    RuntimeError with MeshLab's message. With ``masks``, images get them as alpha and MeshLab's alpha weight
    is on (so it can avoid the background too)."""
    import cv2
    import trimesh

    # a bare-P camera set in a mirrored frame (Oxford dino) has no rotation matrix: hand MeshLab the mirror
    # image (z -> -z, winding flipped) and mirror its result back
    mirror = any(not c.metric and np.linalg.det(c.Rt[:, :3]) * c.depth_sign < 0 for c in cameras)
    S = np.diag([1.0, 1.0, -1.0]) if mirror else np.eye(3)
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        fm = np.asarray(faces)[:, ::-1] if mirror else faces
        trimesh.Trimesh(np.asarray(vertices) @ S, fm, process=False).export(d / "mesh.ply")
        paths, cams = [], []
        for i, (img, cam) in enumerate(zip(images, cameras)):
            p = d / f"view{i:03d}.png"
            bgr = img[:, :, ::-1]
            if masks is not None:
                bgr = np.dstack([bgr, masks[i]])
            cv2.imwrite(str(p), bgr)
            paths.append(str(p))
            K, R, t = decompose(cam, S)
            cams.append({"K": K.tolist(), "R": R.tolist(), "t": t.tolist(), "width": cam.width, "height": cam.height})
        spec = {"mesh": str(d / "mesh.ply"), "images": paths, "cameras": cams, "out": str(d / "out"), "size": size,
                "mode": mode, "alpha": masks is not None}
        (d / "spec.json").write_text(json.dumps(spec))
        import PyQt5

        plugins = Path(list(PyQt5.__path__)[0]) / "Qt5" / "plugins"
        env = {**os.environ, "QT_QPA_PLATFORM_PLUGIN_PATH": str(plugins / "platforms"), "QT_PLUGIN_PATH": str(plugins)}
        r = subprocess.run(["xvfb-run", "-a", sys.executable, __file__, str(d / "spec.json")], env=env,
                           capture_output=True, text=True, timeout=timeout)
        if r.returncode != 0:
            raise RuntimeError(f"MeshLab failed ({r.returncode}): {(r.stderr or r.stdout)[-800:]}")
        seconds = json.loads((d / "out" / "meshlab.json").read_text())["seconds"]
        name = "meshlab.obj" if mode == "atlas" else "meshlab.ply"
        mesh = trimesh.load(d / "out" / name, process=False, force="mesh")
        if mirror:
            mesh.vertices = np.asarray(mesh.vertices) @ S
        if mode == "atlas":
            tex = mesh.visual.material.image
            mesh.visual.material.image = tex.copy()       # read before the folder goes
        return mesh, seconds


def decompose(cam, S=np.eye(3)):
    """OpenCV K, R, t of a camera for points S X (a bare-P camera is decomposed; its skew is dropped later:
    MeshLab's camera cannot hold it)."""
    import cv2

    if cam.metric:
        return cam.K, cam.Rt[:, :3] @ S, cam.Rt[:, 3]
    P = cam.Rt.copy()
    P[:, :3] = P[:, :3] @ S
    P = P * cam.depth_sign                       # third row: positive depth in front
    if np.linalg.det(P[:, :3]) < 0:
        raise RuntimeError(f"camera {cam.name}: mirrored frame, no rotation matrix")
    K, R, c = cv2.decomposeProjectionMatrix(P)[:3]
    K = K / K[2, 2]
    C = (c[:3] / c[3]).ravel()
    return K, R, -R @ C


if __name__ == "__main__":
    run(json.loads(Path(sys.argv[1]).read_text()))
