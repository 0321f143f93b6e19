"""Nodes of the eval stage: quality metrics against ground truth (the work is in metrics.py)."""
from __future__ import annotations

from nodegraph import Node, Param, Table
from nodes.common import raster
from nodes.common.types import CameraSet, Masks, Mesh

from .metrics import silhouette_report, surface_report


class EvalSilhouette(Node):
    """Silhouette agreement of a mesh with masks, per view: IoU, mesh pixels outside the mask, mask pixels
    not covered; means and sums over views."""

    type_name = "eval.silhouette"
    version = 1
    inputs = {"mesh": Mesh, "cameras": CameraSet, "masks": Masks}
    outputs = {"report": Table}
    kernels = [raster.KERNELS]

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
