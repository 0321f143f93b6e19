"""A tracked sequence with fewer faces and the same motion: each segment's keyframe is simplified once
(quadric edge collapses, fast-simplification) and the very same collapses are replayed on every frame of the
segment, so the result is again one connectivity per segment (a stream's lower rung, a mobile asset).

The replay puts each merged vertex at the optimum of its frame's quadric, solved whenever the quadric's
determinant is not exactly 0: a nearly singular one (a flat patch) gives a point far along the flat direction or,
when it cancels out, NaN (the demo's stage at 6 cameras: 2 vertices of frame 4; pose2sim_single's tracked frames 0-49:
59 vertices). NaN vertices crashed the closest-point kernel of the lower rung's texture (the worker died) and were
cast to garbage in the stream. Such a vertex (not finite, or farther from the mean of the vertices merged into it
than ``SPREAD`` times their spread plus an edge: the largest seen elsewhere on three sequences was 3.9) takes the
keyframe's place of it moved by the mean motion of those vertices since the keyframe (on the keyframe: their
mean). The report's ``vertices_replaced`` counts them per segment over its frames (a vertex refused on three frames
counts three times)."""
from __future__ import annotations

import numpy as np

from nodegraph import NodeError
from nodes.common.types import sequence_segments

SPREAD = 8.0     # a replayed vertex this many times (its merged vertices' spread + an edge) from their mean is refused


def _clusters(x: np.ndarray, mapping: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean, spread) per simplified vertex of the original vertices ``x`` merged into it (``mapping``: the replay's
    original -> simplified index, -1 for none): their centroid and their largest distance from it. (fast-simplification
    0.2.0 drops isolated points left by edge-only chains and shifts the indices after them, so a rare original vertex
    may count towards its neighbour's cluster: that moves a mean and a spread, not which vertices are replaced.)"""
    ok = mapping >= 0
    m, xs = mapping[ok], x[ok]
    n = np.maximum(np.bincount(m, minlength=count), 1)[:, None]
    mean = np.stack([np.bincount(m, xs[:, k], minlength=count) for k in range(3)], axis=1) / n
    spread = np.zeros(count)
    np.maximum.at(spread, m, np.linalg.norm(xs - mean[m], axis=1))
    return mean, spread


def _refused(p: np.ndarray, mean: np.ndarray, spread: np.ndarray, edge: float) -> np.ndarray:
    """Replayed vertices not to keep: not finite, or beyond SPREAD x (spread + edge) from their merged vertices' mean."""
    with np.errstate(invalid="ignore"):
        far = np.linalg.norm(p - mean, axis=1) > SPREAD * (spread + edge)
    return ~np.isfinite(p).all(axis=1) | far


def simplify_sequence(meshes, faces_fraction: float, node: str = "track.simplify") -> tuple[list, dict]:
    """(meshes, report): every segment's frames with ``faces_fraction`` of its faces (about), metadata kept."""
    import fast_simplification
    import trimesh

    out, report = [], {"segments": []}
    for s, (a, c) in enumerate(sequence_segments(meshes)):
        key = next((i for i in range(a, c) if meshes[i].metadata.get("frame") == meshes[a].metadata.get("keyframe")), a)
        faces = np.asarray(meshes[key].faces, np.int64)
        if len(faces) < 8:
            raise NodeError(f"{node}: segment {s} has {len(faces)} faces: nothing to simplify")
        xk = np.asarray(meshes[key].vertices, np.float64)
        _, kept, collapses = fast_simplification.simplify(xk, faces, target_reduction=1.0 - faces_fraction,
                                                          return_collapses=True)
        edge = float(np.median(np.linalg.norm(xk[faces[:, 0]] - xk[faces[:, 1]], axis=1)))
        pk, fk, mapping = fast_simplification.replay_simplification(xk, faces, collapses)
        key_mean, spread = _clusters(xk, mapping, len(pk))
        bad = _refused(pk, key_mean, spread, edge)
        pk[bad] = key_mean[bad]
        replaced = int(bad.sum())
        for i in range(a, c):
            if i == key:
                p, f = pk.copy(), fk
            else:
                x = np.asarray(meshes[i].vertices, np.float64)
                p, f, mapping_i = fast_simplification.replay_simplification(x, faces, collapses)
                mean, spread = _clusters(x, mapping_i, len(p))
                bad = _refused(p, mean, spread, edge)
                p[bad] = pk[bad] + mean[bad] - key_mean[bad]
                replaced += int(bad.sum())
            if i > a and not np.array_equal(f, out[a].faces):
                raise NodeError(f"{node}: frame {meshes[i].metadata.get('frame', i)}: the replayed collapses gave another "
                                "connectivity than the segment's first frame")
            m = trimesh.Trimesh(p, f, process=False)
            m.metadata.update(meshes[i].metadata)
            out.append(m)
        report["segments"].append({"segment": s, "faces_in": int(len(faces)), "faces_out": int(len(out[a].faces)),
                                   "vertices_out": int(len(out[a].vertices)), "vertices_replaced": replaced})
    return out, report
