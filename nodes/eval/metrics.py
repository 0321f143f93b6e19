"""Quality metrics against ground truth: silhouette agreement per view, and surface distances."""
from __future__ import annotations

import numpy as np

from nodegraph import NodeError
from nodes.common import raster
from nodes.common.cameras import Cameras
from nodes.common.silhouettes import check_sizes
from nodes.common.types import MaskSet


def silhouette_report(vertices, faces, cameras: Cameras, masks: MaskSet) -> dict:
    """Per view: IoU of the mesh's silhouette with the mask (> 127), mesh pixels outside the mask and mask
    pixels the mesh does not cover; plus mean / min IoU and the error sums over views."""
    check_sizes(masks.masks, cameras, "eval.silhouette")
    views = []
    for cam, sil, m in zip(cameras, raster.silhouette(vertices, faces, cameras), masks.masks):
        a, b = sil > 0, m > 127
        union = int(np.logical_or(a, b).sum())
        views.append({
            "name": cam.name,
            "iou": 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union),
            "mesh_outside_mask": int((a & ~b).sum()),
            "mask_not_covered": int((b & ~a).sum()),
        })
    ious = [v["iou"] for v in views]
    return {
        "views": views,
        "mean_iou": float(np.mean(ious)), "min_iou": float(np.min(ious)),
        "mesh_outside_mask": sum(v["mesh_outside_mask"] for v in views),
        "mask_not_covered": sum(v["mask_not_covered"] for v in views),
        "mean_mesh_outside_mask": float(np.mean([v["mesh_outside_mask"] for v in views])),
        "mean_mask_not_covered": float(np.mean([v["mask_not_covered"] for v in views])),
    }


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
