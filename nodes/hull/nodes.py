"""Hull stage nodes: the automatic capture box and the visual hull (work in bounds.py, hull.py)."""
from __future__ import annotations

import numpy as np

from kernels import source
from nodegraph import Input, Node, NodeError, Output, Param
from nodes.common.silhouettes import POLICIES
from nodes.common.types import Bounds as BoundsType, CameraSet, Masks, Volume

from nodes.common.bounds import auto_bounds
from .hull import border_warning, visual_hull


class Bounds(Node):
    """Axis-aligned box around the captured object: automatic from silhouettes and cameras (coarse hull),
    or the explicit bbox param."""

    type_name = "bounds"
    version = 1
    inputs = {"masks": Input(Masks, optional=True), "cameras": Input(CameraSet, optional=True)}
    outputs = {"bounds": Output(BoundsType, "box [[xmin ymin zmin], [xmax ymax zmax]]")}
    params = {
        "bbox": Param(list, None, item=float, length=6, doc="explicit box [xmin ymin zmin xmax ymax zmax]"),
        "margin": Param(float, 0.05, range=(0.0, 1.0), doc="added on each side, as a fraction of the largest extent"),
        "resolution": Param(int, 64, range=(16, 256), doc="coarse hull voxels along the longest side"),
        "min_seen": Param(int, 0, range=(0, None), doc="coarse hull voxels need k views that see them (the box "
                          "never grows past what k views constrain); 0 = half the views, at least 2"),
    }

    def run(self, masks, cameras, *, bbox, margin, resolution, min_seen):
        if bbox is not None:
            box = np.array(bbox, dtype=np.float64).reshape(2, 3)
            if not np.all(box[1] > box[0]):
                raise NodeError(f"bounds: bbox {bbox} needs xmax > xmin, ymax > ymin, zmax > zmin")
            return {"bounds": box}
        if masks is None or cameras is None:
            raise NodeError("bounds: connect masks and cameras, or give the bbox param")
        return {"bounds": auto_bounds(masks.masks, cameras, resolution, margin, min_seen)}


class Hull(Node):
    """Volumetric visual hull: voxels whose centre falls inside the silhouettes (OpenCL, coarse-to-fine)."""

    type_name = "hull"
    version = 1
    inputs = {"masks": Masks, "cameras": CameraSet,
              "bounds": Input(BoundsType, optional=True, doc="box to carve when the bbox param is not given")}
    outputs = {"volume": Volume}
    params = {
        "resolution": Param(int, 128, range=(8, 1024), doc="voxels along the longest bbox side; others proportional"),
        "bbox": Param(list, None, item=float, length=6, doc="xmin ymin zmin xmax ymax zmax; default: the bounds input"),
        "min_views": Param(int, 0, range=(0, None), doc="0 = all views; k = inside at least k silhouettes"),
        "outside": Param(str, "carve", choices=POLICIES, doc="voxels projecting outside an image: carve, or ignore that view"),
        "min_seen": Param(int, 0, range=(0, None), doc="0 = off; k = keep a voxel only if at least k views see it "
                          "(in front, inside the image): for outside: ignore (carve needs every view)"),
        "method": Param(str, "sparse", choices=("sparse", "dense", "numpy"), doc="coarse-to-fine, every voxel, or NumPy"),
        "floor": Param(bool, False, doc="carve every voxel below the world frame's floor (centre z < 0): the hull's "
                       "ghost under the feet, which cameras above the floor cannot carve"),
    }
    kernels = [source("hull.cl")]

    def run(self, masks, cameras, bounds=None, *, resolution, bbox, min_views, outside, min_seen, method, floor):
        if bbox is not None:
            box = np.array(bbox, dtype=np.float64).reshape(2, 3)
            if not np.all(box[1] > box[0]):
                raise NodeError(f"hull: param 'bbox' {bbox} needs max > min on every axis (xmin ymin zmin xmax ymax zmax)")
        elif bounds is not None:
            box = np.asarray(bounds, dtype=np.float64)
        else:
            raise NodeError("hull: no box to carve: set param 'bbox' or connect the 'bounds' input")
        volume = visual_hull(masks, cameras, box, resolution, min_views, outside, method, min_seen)
        if floor:
            z = volume.bbox_min[2] + (np.arange(volume.occupancy.shape[2]) + 0.5) * volume.voxel_size[2]
            below = z < 0
            if below.any() and volume.occupancy[:, :, below].any():
                self.log.info("hull: %d voxels below the floor carved", int(np.count_nonzero(volume.occupancy[:, :, below])))
                volume.occupancy[:, :, below] = 0
        cut = border_warning(masks, cameras, outside)
        if cut:
            self.log.warning("%s", cut)
        if not volume.occupancy.any():
            self.log.warning("hull: no voxel is inside the silhouettes: the box %s misses the object, or the masks "
                             "and cameras disagree (the mesh will be empty)", np.round(box, 6).ravel().tolist())
        return {"volume": volume}
