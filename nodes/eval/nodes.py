"""Eval stage nodes: silhouette agreement, surface distances, mesh health (work in silhouette.py, surface.py, health.py)."""
from __future__ import annotations

from kernels import source
from nodegraph import Input, Node, NodeError, Param, Table
from nodes.common.types import CameraSet, Masks, Mesh, Volume

from .health import FOLD_DEG, SLIVER_DEG, mesh_health
from .silhouette import silhouette_report
from .surface import surface_report


class EvalSilhouette(Node):
    """Silhouette agreement of a mesh with masks, per view: IoU, mesh pixels outside the mask, mask pixels
    not covered; means and sums over views."""

    type_name = "eval.silhouette"
    version = 1
    publishes = True     # the report goes to OUT/tables/ (JSON per frame, CSV per node)
    summary = ("mean_iou", "min_iou")
    inputs = {"mesh": Mesh, "cameras": CameraSet, "masks": Masks}
    outputs = {"report": Table}
    kernels = [source("raster.cl")]

    def run(self, mesh, cameras, masks):
        return {"report": silhouette_report(mesh.vertices, mesh.faces, cameras, masks)}


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


class EvalMesh(Node):
    """Mesh health: folded edges (adjacent face normals more than fold_deg apart), the distribution of the
    triangles' minimum angles, roughness (mean dihedral angle); with a reference surface (synthetic scenes) the
    area-weighted mean angle between the mesh's face normals and the reference's, over the faces within
    `band` of it (default: one voxel of the volume input)."""

    type_name = "eval.mesh"
    version = 1
    publishes = True     # the report goes to OUT/tables/ (JSON per frame, CSV per node)
    summary = ("folded_edges", "min_angle_below_5", "roughness_deg")
    inputs = {"mesh": Mesh,
              "reference": Input(Mesh, optional=True, doc="true surface (synthetic scenes): enables the normal error"),
              "volume": Input(Volume, optional=True, doc="its voxel size is the default band of the normal error")}
    outputs = {"report": Table}
    params = {
        "band": Param(float, 0.0, range=(0.0, None), doc="normal error over faces within this distance of the reference; "
                      "0 = one voxel of the volume input"),
        "fold_deg": Param(float, FOLD_DEG, range=(90.0, 180.0), doc="an edge is folded when its faces' normals are "
                          "more than this many degrees apart"),
        "sliver_deg": Param(float, SLIVER_DEG, range=(0.0, 60.0), doc="report the share of triangles whose minimum "
                            "angle is below this"),
    }

    def run(self, mesh, reference=None, volume=None, *, band, fold_deg, sliver_deg):
        if reference is not None and band <= 0:
            if volume is None:
                raise NodeError("eval.mesh: the normal error needs a band: connect 'volume' (one voxel) or set band > 0")
            band = float(max(volume.voxel_size))
        return {"report": mesh_health(mesh, reference, band, fold_deg, sliver_deg)}
