"""Mesh health: what a look-dev review sees in a shaded render, as numbers.

    folded edges     interior edges whose two faces' normals are more than ``fold_deg`` (150) degrees apart:
                     a crease folded back onto itself, a black streak in a shaded render
    minimum angles   distribution of each triangle's smallest angle (slivers shade badly and break later
                     stages: texturing, skinning, simulation)
    roughness        mean dihedral angle (angle between adjacent face normals), degrees
    normal error     with a reference surface (synthetic scenes): area-weighted mean angle between each face's
                     normal and the reference's normal at the nearest reference point, over the faces whose
                     centroid lies within ``band`` of the reference (one voxel: concavities the visual hull
                     cannot see are the hull's error, not the mesh's)

    report = mesh_health(mesh, reference=truth, band=voxel)
"""
from __future__ import annotations

import numpy as np

from nodes.common.meshops import FOLD_DEG

SLIVER_DEG = 5.0
# k-d trees built without median balancing or node compaction: the same nearest neighbours (exact either way), built
# ~2x faster on surface samples (500k points: 1.6 -> 0.93 s with the query, 2-core AMD EPYC, load 4)
KD_FLAT = {"balanced_tree": False, "compact_nodes": False}


def triangle_min_angles(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Smallest interior angle of each triangle, degrees (0 for a degenerate triangle)."""
    p = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64).reshape(-1, 3)]
    angles = []
    for k in range(3):
        a = p[:, (k + 1) % 3] - p[:, k]
        b = p[:, (k + 2) % 3] - p[:, k]
        na, nb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cos = np.einsum("ij,ij->i", a, b) / (na * nb)
        angles.append(np.degrees(np.arccos(np.clip(np.nan_to_num(cos, nan=1.0), -1, 1))))
    return np.min(angles, axis=0)


def dihedral_angles(mesh) -> np.ndarray:
    """Angle between the normals of every pair of faces sharing an edge, degrees (trimesh face adjacency)."""
    if len(mesh.faces) == 0:
        return np.zeros(0)
    return np.degrees(np.asarray(mesh.face_adjacency_angles, np.float64))


def normal_error(mesh, reference, band: float, samples: int = 500_000, seed: int = 0) -> dict:
    """Area-weighted mean / median angle (degrees) between the face normals of ``mesh`` and the normal of the
    ``reference`` face nearest to each face centroid, over faces whose centroid lies within ``band`` of the
    reference; plus the fraction of the mesh area that lies within the band. The nearest reference point is
    found among ``samples`` area-uniform points of the reference (scipy cKDTree), so distances are exact to
    about the sample spacing. 500,000 (was 2,000,000): on the demo figure at 128^3 (band one voxel) the mean
    error moves by 0.004 degrees and the area within the band by 0.0003, in 0.43 s instead of 3.4 s."""
    import trimesh
    from scipy.spatial import cKDTree

    count = int(min(samples, max(10_000, reference.area / (0.05 * band) ** 2)))
    points, face_id = trimesh.sample.sample_surface(reference, count, seed=seed)
    dist, nearest = cKDTree(points, **KD_FLAT).query(mesh.triangles_center, workers=-1)
    near = dist <= band
    area = mesh.area_faces
    if not near.any():
        return {"normal_error_mean_deg": float("nan"), "normal_error_median_deg": float("nan"),
                "area_within_band": 0.0}
    true_n = reference.face_normals[face_id[nearest[near]]]
    cos = np.einsum("ij,ij->i", mesh.face_normals[near], true_n)
    err = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    w = area[near]
    order = np.argsort(err, kind="stable")
    cum = np.cumsum(w[order])
    median = float(err[order][np.searchsorted(cum, 0.5 * cum[-1])])
    return {"normal_error_mean_deg": float(np.sum(err * w) / np.sum(w)), "normal_error_median_deg": median,
            "area_within_band": float(w.sum() / area.sum())}


def mesh_health(mesh, reference=None, band: float = 0.0, fold_deg: float = FOLD_DEG,
                sliver_deg: float = SLIVER_DEG) -> dict:
    """Folded edges, triangle minimum angles, roughness, watertightness; with a reference and band > 0 the
    normal error (see the module docstring)."""
    faces = np.asarray(mesh.faces)
    dihedral = dihedral_angles(mesh)
    min_angles = triangle_min_angles(mesh.vertices, faces)
    n = max(len(faces), 1)
    out = {
        "vertices": int(len(mesh.vertices)), "faces": int(len(faces)),
        "watertight": bool(mesh.is_watertight) if len(faces) else False,
        "folded_edges": int((dihedral > fold_deg).sum()),
        "folded_fraction": float((dihedral > fold_deg).sum() / max(len(dihedral), 1)),
        "roughness_deg": float(dihedral.mean()) if len(dihedral) else 0.0,
        "min_angle_below_5": float((min_angles < 5).sum() / n),
        f"min_angle_below_{sliver_deg:g}": float((min_angles < sliver_deg).sum() / n),
        "min_angle_below_10": float((min_angles < 10).sum() / n),
        "min_angle_below_20": float((min_angles < 20).sum() / n),
        "min_angle_median_deg": float(np.median(min_angles)) if len(faces) else 0.0,
        "min_angle_histogram": np.histogram(min_angles, bins=12, range=(0, 60))[0].tolist(),
    }
    if reference is not None and band > 0 and len(faces):
        out.update(normal_error(mesh, reference, band))
    return out
