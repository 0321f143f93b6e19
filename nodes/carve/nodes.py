"""Nodes of the carve stage: the visual hull carved to its photo hull, with voxel colours (work: carving.py)."""
from __future__ import annotations

from kernels import source
from nodegraph import Node, NodeError, Output, Param, Table
from nodes.common.types import CameraSet, Images, Masks, Volume

from .carving import CarveParams, carve
from .photo import SPACES

CONSISTENCY = {
    "threshold": Param(float, 30.0, range=(0.0, 1000.0), doc="colour deviation limit: RMS distance of the per-view "
                       "mean colours from their mean, in units of `space` (rgb 0..255; lab: delta E)"),
    "adaptive": Param(float, 0.0, range=(0.0, 10.0), doc="add this times the RMS colour spread within a view's "
                      "footprint to the limit (Slabaugh et al. 2004: more tolerance over texture)"),
    "contrast": Param(float, 0.0, range=(0.0, 100.0), doc="carve only when the colour deviation between views also "
                      "exceeds this times the RMS colour spread within the views: refuses to carve on weak evidence "
                      "(texture about as fine as the voxels, whose footprints differ from view to view); 1.2 keeps a "
                      "tight hull over fine texture (the synth figure) as it is"),
    "space": Param(str, "rgb", choices=SPACES, doc="colour space of the test: sRGB values, or CIE L*a*b* (D65)"),
    "gain": Param(bool, False, doc="per-camera, per-channel gains matching each view's mean colour inside its mask"),
    "min_views": Param(int, 2, range=(2, 256), doc="a voxel seen in fewer views is kept untested"),
    "footprint": Param(float, 0.7, range=(0.1, 1.0), doc="sampled part of the voxel's projected cube (1 = all of it)"),
    "max_angle": Param(float, 70.0, range=(10.0, 90.0), doc="views seeing a voxel more than this many degrees off its "
                       "normal are not used (grazing views)"),
    "largest": Param(bool, True, doc="carve only the largest 6-connected part of the input (its specks go); nothing "
                     "is dropped after carving: a part the carving cut off stays when silhouettes need it"),
    "method": Param(str, "opencl", choices=("opencl", "numpy"), doc="OpenCL kernels or the NumPy reference (small grids)"),
}
INPUTS = {"volume": Volume, "images": Images, "masks": Masks, "cameras": CameraSet}
OUTPUTS = {"volume": Output(Volume, "the carved volume, voxel colours on its surface"),
           "report": Output(Table, "voxels in/out, removals per pass, mean colour variance over views (wall times are in the log)")}


def _params(node: str, kw: dict) -> CarveParams:
    p = CarveParams(**{k: v for k, v in kw.items() if k != "method"})
    if p.min_views < 2:
        raise NodeError(f"{node}: min_views must be at least 2 (a colour deviation needs two views)")
    return p


class SpaceCarving(Node):
    """Space carving (Kutulakos & Seitz 2000) of the visual hull: plane sweeps along +-x +-y +-z test each
    plane's surface voxels in the cameras behind it (visibility from per-camera marks of the voxels kept so
    far), then one pass over all surface voxels with item buffers tests each in every view that sees it;
    repeated until nothing is removed. Never carves through a silhouette; output coloured."""

    type_name = "carve.space_carving"
    version = 1
    inputs = INPUTS
    outputs = OUTPUTS
    params = {
        **CONSISTENCY,
        "cone": Param(float, 65.0, range=(10.0, 89.0), doc="sweeps: a camera tests a voxel when its ray is within "
                      "this many degrees of the sweep axis"),
        "max_passes": Param(int, 500, range=(0, 10000), doc="at most this many passes (0: colour the input only)"),
        "sweep_fraction": Param(float, 0.1, range=(0.0, 1.0), doc="sweep again while the last round of sweeps removed "
                                "more than this fraction of the voxels it began with (then item-buffer passes only)"),
    }
    kernels = [source("carve.cl")]

    def run(self, volume, images, masks, cameras, *, method, **kw):
        res = carve(volume, images, masks, cameras, _params(self.type_name, kw), "space_carving", method,
                    self.type_name)
        self.log.info("%s: %d of %d voxels kept after %d passes (%.2f s)", self.type_name, res.stats["voxels_out"],
                      res.stats["voxels_in"], len(res.stats["passes"]), res.stats["seconds_total"])
        return {"volume": res.volume, "report": _report(res.stats)}


def _report(stats: dict) -> dict:
    """The carve's outcome without its wall times (they are in the log and run.json): a cached value is what
    the node computes, the same on every run."""
    out = {k: v for k, v in stats.items() if not k.startswith("seconds")}
    if "passes" in out:
        out["passes"] = [{k: v for k, v in p.items() if k != "seconds"} for p in out["passes"]]
    return out


class VoxelColoring(Node):
    """Voxel colouring (Seitz & Dyer 1999): one pass over layers of increasing distance from the convex hull
    of the camera centres, each surface voxel tested in every view where no kept voxel of an earlier layer
    hides it. Needs the ordinal visibility constraint (no voxel inside the cameras' convex hull: cameras on
    one side, e.g. all above); otherwise a NodeError says to use carve.space_carving. Output coloured."""

    type_name = "carve.voxel_coloring"
    version = 1
    inputs = INPUTS
    outputs = OUTPUTS
    params = dict(CONSISTENCY)
    kernels = [source("carve.cl")]

    def run(self, volume, images, masks, cameras, *, method, **kw):
        res = carve(volume, images, masks, cameras, _params(self.type_name, kw), "voxel_coloring", method,
                    self.type_name)
        self.log.info("%s: %d of %d voxels kept (%.2f s)", self.type_name, res.stats["voxels_out"],
                      res.stats["voxels_in"], res.stats["seconds_total"])
        return {"volume": res.volume, "report": _report(res.stats)}
