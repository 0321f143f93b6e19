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

    for label, m in (("mesh", mesh), ("reference", reference)):
        if len(m.faces) == 0 or m.area <= 0:
            raise NodeError(f"eval.surface: input '{label}' has no surface (0 faces or zero area)")
    pa, _ = trimesh.sample.sample_surface(mesh, samples, seed=seed)
    pb, _ = trimesh.sample.sample_surface(reference, samples, seed=seed)
    d_ab = cKDTree(pb).query(pa)[0]
    d_ba = cKDTree(pa).query(pb)[0]
    diag = float(np.linalg.norm(reference.bounds[1] - reference.bounds[0]))
    out = {
        "accuracy_mean": float(d_ab.mean()), "accuracy_max": float(d_ab.max()),
        "completeness_mean": float(d_ba.mean()), "completeness_max": float(d_ba.max()),
        "chamfer": float((d_ab.mean() + d_ba.mean()) / 2), "hausdorff": float(max(d_ab.max(), d_ba.max())),
    }
    out.update({f"{k}_rel": v / diag for k, v in list(out.items())})
    out.update({"reference_bbox_diagonal": diag, "samples": samples})
    return out
