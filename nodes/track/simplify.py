"""A tracked sequence with fewer faces and the same motion: each segment's keyframe is simplified once
(quadric edge collapses, fast-simplification) and the very same collapses are replayed on every frame of the
segment, so the result is again one connectivity per segment (a stream's lower rung, a mobile asset)."""
from __future__ import annotations

import numpy as np

from nodegraph import NodeError
from nodes.common.types import sequence_segments


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
        _, kept, collapses = fast_simplification.simplify(np.asarray(meshes[key].vertices, np.float64), faces,
                                                          target_reduction=1.0 - faces_fraction, return_collapses=True)
        for i in range(a, c):
            p, f, _ = fast_simplification.replay_simplification(np.asarray(meshes[i].vertices, np.float64), faces,
                                                                collapses)
            if i > a and not np.array_equal(f, out[a].faces):
                raise NodeError(f"{node}: frame {meshes[i].metadata.get('frame', i)}: the replayed collapses gave another "
                                "connectivity than the segment's first frame")
            m = trimesh.Trimesh(p, f, process=False)
            m.metadata.update(meshes[i].metadata)
            out.append(m)
        report["segments"].append({"segment": s, "faces_in": int(len(faces)), "faces_out": int(len(out[a].faces)),
                                   "vertices_out": int(len(out[a].vertices))})
    return out, report
