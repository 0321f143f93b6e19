"""The seed's refine and relax (volcap before issue 13), frozen here as the benchmark's "today" baseline:
Liang & Wong bisection against every silhouette through the signed-distance outline (bench/legacy_hulltest.py,
kernels/refine.cl), two rounds of conforming edge splits where chords stray more than 0.25 px (host NumPy
projection), then Taubin lambda|mu smoothing (trimesh.smoothing.filter_taubin: the seed's OpenCL kernel gave the
same vertices within 1e-5) fitted back to the hull. Not part of the product; run by bench/refine_relax.py.
"""
from __future__ import annotations

import numpy as np
import trimesh

from nodes.common.cameras import Cameras
from nodes.common.meshops import split_edges, unique_edges
from nodes.common.silhouettes import Silhouettes

from legacy_hulltest import hull_test

LAMBDA, MU = 0.6307, -0.6732


def lattice_edges(vertices, volume):
    from nodes.mesh.refine import lattice_edges as edges  # unchanged by issue 13

    return edges(vertices, volume)


def onto_hull(points, directions, reach, test, steps: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Points moved along +-``directions`` (unit, outward) onto the hull boundary: an inside point searches
    out to ``reach`` (scalar or per point), an outside point back in as far. Returns (points, found);
    points with no boundary within reach stay where they are."""
    p = np.asarray(points, np.float32).reshape(-1, 3)
    step = np.broadcast_to(np.asarray(reach, np.float32).reshape(-1, 1), (len(p), 1)) * np.asarray(directions, np.float32)
    inside = test.inside(p)
    a = np.where(inside[:, None], p, p - step)
    b = np.where(inside[:, None], p + step, p)
    ends = test.inside(np.vstack([a, b]))
    found = ends[: len(p)] & ~ends[len(p):]
    out = p.copy()
    if found.any():
        out[found] = test.exit(a[found], b[found], steps)
    return out.astype(np.float64), found


def push_out(points, directions, reach, test, steps: int = 16) -> np.ndarray:
    """Inside points moved outwards along ``directions`` by up to ``reach`` (per point), stopping at the hull
    boundary; outside points and points with reach 0 stay."""
    p = np.asarray(points, np.float32).reshape(-1, 3)
    reach = np.asarray(reach, np.float32).reshape(-1)
    go = np.flatnonzero(reach > 0)
    go = go[test.inside(p[go])]
    b = p[go] + reach[go, None] * np.asarray(directions, np.float32)[go]
    stop = ~test.inside(b)
    out = p.copy()
    out[go[~stop]] = b[~stop]
    if stop.any():
        out[go[stop]] = test.clamp(p[go[stop]], b[stop], steps)
    return out.astype(np.float64)


def refine_vertices(vertices, faces, volume, test, steps: int = 16) -> tuple[np.ndarray, int, int]:
    """Vertices moved onto the hull boundary: along their grid edge where its inside end passes the point
    test and its outside end fails it, else along the vertex normal within one voxel.
    Returns (vertices, moved along edges, moved along normals); the rest stay."""
    vertices = np.asarray(vertices, np.float64)
    a, b, ok = lattice_edges(vertices, volume)
    ends = test.inside(np.vstack([a, b]))
    on_edge = ok & ends[: len(a)] & ~ends[len(a):]
    out = vertices.copy()
    out[on_edge] = test.exit(a[on_edge], b[on_edge], steps)
    rest = np.flatnonzero(~on_edge)
    found = np.zeros(0, bool)
    if len(rest):
        normals = trimesh.Trimesh(vertices, faces, process=False).vertex_normals[rest]
        out[rest], found = onto_hull(vertices[rest], normals, float(np.max(volume.voxel_size)), test, steps)
    return out, int(on_edge.sum()), int(found.sum())


def chord_shift(points, moved, cameras: Cameras) -> np.ndarray:
    """Largest image distance (pixels, over all views) between each point and its moved twin."""
    shift = np.zeros(len(points))
    for v in range(len(cameras)):
        shift = np.maximum(shift, np.linalg.norm(cameras.project(points, v)[0] - cameras.project(moved, v)[0], axis=1))
    return np.nan_to_num(shift, nan=np.inf)


def split_towards_hull(vertices, faces, test, cameras: Cameras, reach: float, px: float = 0.25, rounds: int = 2,
                       steps: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """``rounds`` of conforming edge splits: an edge whose midpoint, moved onto the hull along the mean normal
    of its ends (within ``reach``, halved every round), moves more than ``px`` pixels in some view is split
    at that hull point. Returns (vertices, faces)."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    for _ in range(rounds):
        edges, face_edges = unique_edges(f)
        normals = trimesh.Trimesh(v, f, process=False).vertex_normals
        mid = 0.5 * (v[edges[:, 0]] + v[edges[:, 1]])
        n = normals[edges[:, 0]] + normals[edges[:, 1]]
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        on_hull, found = onto_hull(mid, n, reach, test, steps)
        split = found & (chord_shift(mid, on_hull, cameras) > px)
        if not split.any():
            break
        v, f = split_edges(v, f, edges, face_edges, split, on_hull)
        reach /= 2
    return v, f




def legacy_refine(mesh, volume, masks, cameras):
    """The seed's refine node with its defaults (steps 16, 2 split rounds at 0.25 px, distance outline)."""
    views = Silhouettes.from_inputs(masks, cameras).distance_outline()
    test = hull_test(views, "opencl")
    faces = np.asarray(mesh.faces)
    v, _, _ = refine_vertices(mesh.vertices, faces, volume, test, 16)
    v, f = split_towards_hull(v, faces, test, cameras, float(np.max(volume.voxel_size)), 0.25, 2, 16)
    return trimesh.Trimesh(v, f, process=False)


def legacy_relax(mesh, masks, cameras, iterations: int = 10, steps: int = 10):
    """The seed's relax node with its defaults (10 lambda|mu pairs, keep_silhouettes, outline_sigma 0.7)."""
    views = Silhouettes.from_inputs(masks, cameras).distance_outline(0.7)
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    out = trimesh.smoothing.filter_taubin(mesh.copy(), lamb=LAMBDA, nu=-MU, iterations=2 * iterations).vertices
    reach = float(mesh.edges_unique_length.mean()) if len(faces) else 0.0
    test = hull_test(views, "opencl")
    normals = trimesh.Trimesh(out, faces, process=False).vertex_normals
    out = test.clamp(vertices, out, steps, normals, reach)
    inwards = np.einsum("ij,ij->i", vertices - out, normals)
    return trimesh.Trimesh(push_out(out, normals, np.maximum(inwards, 0), test, steps), faces, process=False)
