"""Surface distances between a mesh and a reference mesh (Chamfer, Hausdorff; accuracy and completeness)."""
from __future__ import annotations

import numpy as np

from nodegraph import NodeError


def surface_report(mesh, reference, samples: int = 100_000, seed: int = 0) -> dict:
    """Chamfer and Hausdorff distances between two surfaces, from ``samples`` area-uniform points on each
    (trimesh.sample) matched to the nearest points sampled on the other (scipy cKDTree).

    accuracy = mesh -> reference, completeness = reference -> mesh (DTU / Middlebury style);
    chamfer = their mean; every distance also relative to the reference's bounding-box diagonal."""
    import trimesh
    from scipy.spatial import cKDTree

    from nodes.eval.health import KD_FLAT

    for label, m in (("mesh", mesh), ("reference", reference)):
        if len(m.faces) == 0 or m.area <= 0:
            raise NodeError(f"eval.surface: input '{label}' has no surface (0 faces or zero area)")
    pa, _ = trimesh.sample.sample_surface(mesh, samples, seed=seed)
    pb, _ = trimesh.sample.sample_surface(reference, samples, seed=seed)
    d_ab = cKDTree(pb, **KD_FLAT).query(pa, workers=-1)[0]
    d_ba = cKDTree(pa, **KD_FLAT).query(pb, workers=-1)[0]
    diag = float(np.linalg.norm(reference.bounds[1] - reference.bounds[0]))
    out = {
        "accuracy_mean": float(d_ab.mean()), "accuracy_max": float(d_ab.max()),
        "completeness_mean": float(d_ba.mean()), "completeness_max": float(d_ba.max()),
        "chamfer": float((d_ab.mean() + d_ba.mean()) / 2), "hausdorff": float(max(d_ab.max(), d_ba.max())),
    }
    out.update({f"{k}_rel": v / diag for k, v in list(out.items())})
    out.update({"reference_bbox_diagonal": diag, "samples": samples})
    return out


def sliding(tracked, faces, truth, rest, key: int = 0, candidates: int = 8) -> np.ndarray:
    """How far tracked vertices slide over the true surface (the motion of a texture-fixed point relative to the
    surface, which IoU and surface distances cannot see): ``tracked`` (T, V, 3) one connectivity's vertices per
    frame (``faces`` its triangles), ``truth`` T true meshes of one topology with ``rest`` (N, 3) the rest-pose
    position of each true vertex (where a texture is fixed). In every frame each tracked vertex is taken to the
    closest true point that faces the same way (normals at under 90 degrees: where a hand lies on a hip, a point of
    the hand's outside is not taken to the hip); returns (T, V) the rest-pose distance (metres along the body)
    between that point and the one it had at frame ``key`` (0 there). An offset along the normal (a fatter
    reconstruction) does not count."""
    import trimesh
    from scipy.spatial import cKDTree

    rest = np.asarray(rest, np.float64)
    coords = []
    for x, m in zip(tracked, truth):
        x = np.asarray(x, np.float64)
        own = trimesh.Trimesh(x, faces, process=False).vertex_normals
        tf = np.asarray(m.faces)
        vf = m.vertex_faces                                       # (N, k) incident faces, -1 padded
        near = cKDTree(np.asarray(m.vertices)).query(x, k=candidates)[1]
        cand = vf[near].reshape(len(x), -1)                       # (V, C) candidate faces
        ok = cand >= 0
        c = np.where(ok, cand, 0)
        tri = np.asarray(m.triangles)[c.ravel()]
        pts = trimesh.triangles.closest_point(tri, np.repeat(x, c.shape[1], axis=0)).reshape(c.shape + (3,))
        dist = np.linalg.norm(pts - x[:, None], axis=2)
        facing = np.einsum("vcd,vd->vc", np.asarray(m.face_normals)[c], own) > 0
        score = np.where(ok & facing, dist, np.where(ok, dist + 1e3, np.inf))   # none facing: the closest anyway
        best = np.argmin(score, axis=1)
        rows = np.arange(len(x))
        f, p = c[rows, best], pts[rows, best]
        bary = trimesh.triangles.points_to_barycentric(np.asarray(m.triangles)[f], p)
        coords.append(np.einsum("vk,vkc->vc", bary, rest[tf[f]]))
    coords = np.stack(coords)
    return np.linalg.norm(coords - coords[key][None], axis=2)


def contacts(truth_vertices, rest, points, radius: float = 0.03, apart: float = 0.15) -> np.ndarray:
    """(P,) bool: surface points (P, 3) of a frame where another part of the body touches: a true vertex within
    ``radius`` (metres) whose rest-pose position is more than ``apart`` from the rest position of the point's
    nearest true vertex (a hand against the hip, not the arm's own neighbourhood). ``truth_vertices`` (N, 3)
    that frame's true vertices, ``rest`` (N, 3) theirs at rest."""
    from scipy.spatial import cKDTree

    tree = cKDTree(np.asarray(truth_vertices, np.float64))
    rest = np.asarray(rest, np.float64)
    own = tree.query(np.asarray(points, np.float64))[1]
    out = np.zeros(len(points), bool)
    for i, near in enumerate(tree.query_ball_point(np.asarray(points, np.float64), radius)):
        if near:
            out[i] = np.any(np.linalg.norm(rest[near] - rest[own[i]], axis=1) > apart)
    return out
