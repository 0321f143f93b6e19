"""Synthetic capture: procedural scenes (scenes.py) rendered from a configurable camera rig, with
the ground truth every stage can be checked against (masks, mesh, skeleton, clean plate, bounds)."""
from __future__ import annotations

import math

from typing import TYPE_CHECKING

import numpy as np

from nodes.common import raster
from nodes.common.cameras import Cameras, look_at
from nodes.common.raster import CHECKER, STRIPES

if TYPE_CHECKING:
    import trimesh

from . import scenes

LIGHT = (0.35, -0.55, 0.75)   # towards the light (world)
AMBIENT = 0.35
GREEN = (0.12, 0.62, 0.22)


def ring_rig(count: int, center, radius: float, fov: float, width: int, height: int, k1: float = 0.0,
             seed: int = 0, dome: bool = False) -> Cameras:
    """Cameras looking at ``center`` from distance ``radius / sin(half the narrower fov)``: evenly round a
    horizontal ring, or spread over a dome (elevations 10..70 degrees, golden-angle azimuths). ``seed``
    jitters azimuths and distances a little (seed 0: none)."""
    center = np.asarray(center, float)
    hfov = math.radians(fov)
    vfov = 2 * math.atan(math.tan(hfov / 2) * height / width)
    dist = radius / math.sin(min(hfov, vfov) / 2) * 1.05
    rng = np.random.default_rng(seed)
    jitter = seed != 0
    cams = []
    for i in range(count):
        if dome:
            elev = math.radians(10 + 60 * (i + 0.5) / count)
            azim = i * math.pi * (3 - math.sqrt(5))
        else:
            elev, azim = 0.0, 2 * math.pi * i / count
        if jitter:
            azim += rng.uniform(-0.15, 0.15) * 2 * math.pi / count
        d = dist * (1 + (rng.uniform(-0.05, 0.05) if jitter else 0.0))
        eye = center + d * np.array([math.cos(elev) * math.cos(azim), math.cos(elev) * math.sin(azim), math.sin(elev)])
        cam = look_at(eye, center, (0, 0, 1), fov, width, height, name=f"cam{i:03d}")
        cam.dist[0] = k1
        cams.append(cam)
    return Cameras(cams)


def room(half: float, height: float, backdrop: str, cells: float = 0.25) -> tuple[trimesh.Trimesh, np.ndarray, np.ndarray]:
    """Floor, four walls and ceiling of a room, faces pointing inwards, cut into small cells (per-vertex lens
    distortion needs small triangles). Returns (mesh, face material index (0 floor, 1 walls), materials).
    ``backdrop`` "green": uniform chroma green everywhere; "plate": tiled floor, striped walls."""
    import trimesh

    parts = []
    n = max(2, int(math.ceil(2 * half / cells)))
    m = max(2, int(math.ceil(height / cells)))

    def grid(origin, du, dv, nu, nv, flip):
        u, v = np.meshgrid(np.arange(nu + 1) / nu, np.arange(nv + 1) / nv, indexing="ij")
        verts = origin + u.reshape(-1, 1) * du + v.reshape(-1, 1) * dv
        idx = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
        a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
        faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
        return trimesh.Trimesh(verts, faces[:, ::-1] if flip else faces, process=False)

    h2 = 2 * half
    parts.append(grid(np.array([-half, -half, 0.0]), [h2, 0, 0], [0, h2, 0], n, n, False))           # floor, up
    parts.append(grid(np.array([-half, -half, 0.0]), [h2, 0, 0], [0, 0, height], n, m, False))       # y = -half
    parts.append(grid(np.array([-half, half, 0.0]), [h2, 0, 0], [0, 0, height], n, m, True))         # y = +half
    parts.append(grid(np.array([-half, -half, 0.0]), [0, h2, 0], [0, 0, height], n, m, True))        # x = -half
    parts.append(grid(np.array([half, -half, 0.0]), [0, h2, 0], [0, 0, height], n, m, False))        # x = +half
    parts.append(grid(np.array([-half, -half, height]), [h2, 0, 0], [0, h2, 0], n, n, True))         # ceiling
    mesh = trimesh.util.concatenate(parts)
    face_material = np.concatenate([np.zeros(len(parts[0].faces), np.int32),
                                    np.ones(sum(len(p.faces) for p in parts[1:]), np.int32)])
    if backdrop == "green":
        mats = [scenes.material(GREEN, lit=False, shadow=True)] * 2
    else:
        mats = [scenes.material((0.55, 0.55, 0.52), (0.75, 0.74, 0.7), CHECKER, 0.5, lit=False, shadow=True),
                scenes.material((0.72, 0.62, 0.48), (0.6, 0.5, 0.4), STRIPES, 0.3, lit=False, shadow=False)]
    return mesh, face_material, np.array(mats)


def render_scene(scene: scenes.Scene, cameras: Cameras, backdrop: str, shadow: bool, with_object: bool = True):
    """(images, masks) of ``scene`` inside its room, as seen by ``cameras``."""
    import trimesh

    centers = cameras.centers
    half = max(3.0, 1.3 * float(np.abs(centers[:, :2]).max()))
    height = max(3.0, 1.3 * float(centers[:, 2].max()))
    walls, wall_mat, wall_mats = room(half, height, backdrop)
    obj = scene.mesh if with_object else trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int), process=False)
    n_obj = len(obj.faces)
    verts = np.vstack([obj.vertices, walls.vertices])
    faces = np.vstack([obj.faces, walls.faces + len(obj.vertices)]).astype(np.int32)
    normals = np.vstack([obj.vertex_normals if n_obj else np.zeros((0, 3)), np.zeros_like(walls.vertices)])
    texcoords = np.vstack([scene.texcoords if with_object else np.zeros((0, 3)), walls.vertices])
    face_material = np.concatenate([scene.face_material if with_object else np.zeros(0, np.int32),
                                    wall_mat + len(scene.materials)])
    materials = np.vstack([scene.materials, wall_mats])
    blob = (scene.center[0], scene.center[1], 0.45 * scene.radius, 0.45 if shadow else 0.0)
    return raster.render(verts, faces, normals, texcoords, face_material, materials, cameras, n_object=n_obj,
                         light=LIGHT, ambient=AMBIENT, shadow=blob)


def surface_truth(scene: scenes.Scene, points, shadow: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """What the renderer paints at surface points (N, 3) of ``scene`` (each taken to its closest point on the
    true surface): (colour (N, 3) float64 in 0..255 before rounding, distance (N,) in metres along the surface
    pattern to its nearest colour edge: inf on plain materials). The truth of a texture measure."""
    import trimesh

    mesh = scene.mesh
    near, _, tri = trimesh.proximity.closest_point(mesh, np.asarray(points, np.float64))
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], near)
    blob = (scene.center[0], scene.center[1], 0.45 * scene.radius, 0.45 if shadow else 0.0)
    rgb = raster.shade_colours(tri, bary, mesh.faces, mesh.vertex_normals, scene.texcoords, scene.face_material,
                               scene.materials, LIGHT, AMBIENT, blob)
    t = np.einsum("nk,nkc->nc", bary, scene.texcoords[mesh.faces[tri]])
    m = scene.materials[scene.face_material[tri]]
    period = m[:, 7:8]
    frac = t / period - np.floor(t / period)
    edge = np.minimum(frac, 1 - frac) * period
    dist = np.where(m[:, 6] == raster.CHECKER, edge.min(axis=1),
                    np.where(m[:, 6] == raster.STRIPES, edge[:, 2], np.inf))
    return rgb, dist
