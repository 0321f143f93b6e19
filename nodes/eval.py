"""Quality metrics against ground truth: silhouette agreement per view, and surface distances."""
from __future__ import annotations

import numpy as np

from nodegraph import Node, NodeError, Param
from nodegraph.cameras import Cameras
from nodegraph.types import CameraSet, MaskSet, Masks, Mesh, Table

from . import raster


def silhouette_report(vertices, faces, cameras: Cameras, masks: MaskSet) -> dict:
    """Per view: IoU of the mesh's silhouette with the mask (> 127), mesh pixels outside the mask and mask
    pixels the mesh does not cover; plus mean / min IoU and the error sums over views."""
    if len(masks) != len(cameras):
        raise NodeError(f"eval.silhouette: {len(masks)} masks for {len(cameras)} cameras")
    for cam, m in zip(cameras, masks.masks):
        if m.shape != (cam.height, cam.width):
            raise NodeError(f"eval.silhouette: camera '{cam.name}' is {cam.width}x{cam.height} but its mask is "
                            f"{m.shape[1]}x{m.shape[0]}")
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


class EvalSilhouette(Node):
    """Silhouette agreement of a mesh with masks, per view: IoU, mesh pixels outside the mask, mask pixels
    not covered; means and sums over views."""

    type_name = "eval.silhouette"
    version = 1
    inputs = {"mesh": Mesh, "cameras": CameraSet, "masks": Masks}
    outputs = {"report": Table}
    kernels = [raster.KERNELS]
    uses = ["nodes.raster"]

    def run(self, mesh, cameras, masks):
        return {"report": silhouette_report(mesh.vertices, mesh.faces, cameras, masks)}


class EvalSurface(Node):
    """Surface distance of a mesh to a reference mesh: Chamfer and Hausdorff, both directions, absolute
    and relative to the reference's bounding-box diagonal."""

    type_name = "eval.surface"
    version = 1
    inputs = {"mesh": Mesh, "reference": Mesh}
    outputs = {"report": Table}
    params = {
        "samples": Param(int, 100_000, range=(100, 10_000_000), doc="points sampled on each surface"),
        "seed": Param(int, 0, range=(0, None), doc="sampling seed"),
    }

    def run(self, mesh, reference, *, samples, seed):
        return {"report": surface_report(mesh, reference, samples, seed)}
