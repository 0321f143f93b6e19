"""Surface distances between a mesh and a reference mesh (Chamfer, Hausdorff; accuracy and completeness)."""
from __future__ import annotations

import numpy as np

from nodegraph import Node, NodeError, Param, Table
from nodes.common.types import Mesh


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


class EvalSurface(Node):
    """Surface distance of a mesh to a reference mesh: Chamfer and Hausdorff, both directions, absolute
    and relative to the reference's bounding-box diagonal."""

    type_name = "eval.surface"
    version = 1
    publishes = True     # the report goes to OUT/tables/ (JSON per frame, CSV per node)
    summary = ("chamfer", "hausdorff", "hausdorff_rel")
    inputs = {"mesh": Mesh, "reference": Mesh}
    outputs = {"report": Table}
    params = {
        "samples": Param(int, 100_000, range=(100, 10_000_000), doc="points sampled on each surface"),
        "seed": Param(int, 0, range=(0, None), doc="sampling seed"),
    }

    def run(self, mesh, reference, *, samples, seed):
        return {"report": surface_report(mesh, reference, samples, seed)}
