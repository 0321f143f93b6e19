"""Synthetic scenes for the mesh-stage tests: unions of balls seen by look_at cameras, with exact masks (a pixel
is inside when its centre's ray meets a ball), optional soft alpha (a linear ramp across the true outline), the
visual hull (nodes.hull) and its marching-cubes mesh; real-data meshes at a resolution."""
from __future__ import annotations

import math

import numpy as np
import trimesh

from nodes.common.cameras import Cameras
from rig import sphere_rig
from nodes.common.types import MaskSet
from nodes.eval.silhouette import silhouette_report
from nodes.hull.hull import visual_hull
from nodes.mesh.mc import marching_cubes

FIGURE = [((0.0, 0.0, 0.0), 0.55), ((0.0, 0.0, 0.62), 0.32), ((0.45, 0.1, -0.35), 0.3), ((-0.4, -0.2, -0.4), 0.28)]
FIGURE_BOX = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.1]]


def rig(count: int, size: int, center=(0, 0, 0), distance: float = 4.0, fov: float = 40.0) -> Cameras:
    """``count`` cameras spread evenly over a sphere (Fibonacci), all looking at ``center`` (tests/rig.py)."""
    return sphere_rig(count, size, center=center, distance=distance, fov=fov)


def ball_masks(balls, cameras: Cameras, ramp: float = 4.0) -> MaskSet:
    """Exact binary silhouettes of a union of balls, and soft alpha falling linearly over ``ramp`` pixels."""
    masks, alphas = [], []
    for cam in cameras:
        v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float64)
        rays = np.stack([(u - cam.K[0, 2]) / cam.K[0, 0], (v - cam.K[1, 2]) / cam.K[1, 1], np.ones_like(u)], -1)
        rays = rays @ cam.Rt[:, :3]  # camera -> world directions (R^T d)
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        signed = np.full(u.shape, np.inf)
        for c, r in balls:
            to_c = np.asarray(c, float) - cam.center
            dist = np.linalg.norm(to_c)
            angle = np.arccos(np.clip(rays @ (to_c / dist), -1, 1))
            signed = np.minimum(signed, (angle - math.asin(r / dist)) * cam.K[0, 0])  # pixels outside the outline
        masks.append(np.where(signed <= 0, 255, 0).astype(np.uint8))
        alphas.append(np.clip(0.5 - signed / ramp, 0, 1).astype(np.float32))
    return MaskSet(masks, alphas, cameras.names)


def plain_mc(volume) -> trimesh.Trimesh:
    """The mc node's surface: vertices on edges between voxel centres."""
    return trimesh.Trimesh(*marching_cubes(volume), process=False)


def figure_case(resolution: int, count: int = 6, size: int = 160, soft: bool = False):
    """(cameras, masks, volume, mc mesh) of the four-ball figure."""
    cams = rig(count, size)
    masks = ball_masks(FIGURE, cams)
    if not soft:
        masks = MaskSet(masks.masks, None, masks.names)
    vol = visual_hull(masks, cams, np.array(FIGURE_BOX), resolution)
    return cams, masks, vol, plain_mc(vol)


def silhouette_errors(mesh, masks: MaskSet, cameras: Cameras) -> tuple[np.ndarray, int, int]:
    """(IoU per view, mesh pixels outside the masks, mask pixels not covered), from eval.silhouette."""
    r = silhouette_report(mesh.vertices, mesh.faces, cameras, masks)
    return np.array([v["iou"] for v in r["views"]]), r["mesh_outside_mask"], r["mask_not_covered"]


def real_meshes(data_dir, name, resolution):
    """(masks, cameras, volume, largest component of the mc mesh) of a real data set."""
    from nodes.capture.load import load_capture
    from nodes.common.meshops import largest_component
    from nodes.common.bounds import auto_bounds

    cap = load_capture(data_dir / name)
    masks, cams = cap["masks"], cap["cameras"]
    vol = visual_hull(masks, cams, auto_bounds(masks.masks, cams), resolution)
    return masks, cams, vol, trimesh.Trimesh(*largest_component(*marching_cubes(vol)), process=False)
