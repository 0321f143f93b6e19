"""Volumetric visual hull: voxels whose centre projects inside the silhouettes.

Two OpenCL methods give identical voxels (kernels/hull.cl):
  dense   every voxel centre is tested against every view;
  sparse  coarse-to-fine after Loop, Zhang & Zhang (HPG 2013): cells of 2^L voxels are classified from the
          rectangle bounding their projection, looked up in a summed-area table of the mask (8x8 pixel
          blocks); only cells that are neither certainly inside nor certainly outside are split, and the
          last level decides voxel by voxel with the very same centre test as the dense method.
``hull_reference`` is the NumPy version of the centre test (same float32 arithmetic, same vote rule).
Both methods read the silhouettes as ``SilhouetteBits`` on the device (bits + block tables): packed here
from host masks, or written straight from the camera images by the chroma key (the fused, device-resident
path of bench/e2e.py); see nodes.common.silhouettes.
"""
from __future__ import annotations

import math

import numpy as np

from kernels import source
from nodegraph import NodeError, clrt
from nodes.common.cameras import PACK_FLOATS, Cameras
from nodes.common.silhouettes import (POLICIES, SilhouetteBits, border_views, centre_states, check_masks,
                                      check_silhouettes, vote)
from nodes.common.types import VoxelGrid

COARSE_CELLS = 16  # the first sparse level has at most this many cells along the longest side


# ---------------------------------------------------------------- grid and checks
def hull_grid(box: np.ndarray, resolution: int) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int]]:
    """Cubic voxels over ``box`` (2, 3): ``resolution`` along the longest side, the others proportional.
    The box grows symmetrically to a whole number of voxels. Returns (bbox_min, bbox_max, dims)."""
    box = np.asarray(box, dtype=np.float64).reshape(2, 3)
    ext = box[1] - box[0]
    size = ext.max() / resolution
    dims = np.maximum(1, np.ceil(ext / size - 1e-6)).astype(int)
    grow = (dims * size - ext) / 2
    return box[0] - grow, box[1] + grow, tuple(int(d) for d in dims)


def check_in_front(cameras: Cameras, box: np.ndarray):
    """A NodeError naming each camera that has the whole box behind it (all 8 corners at depth <= 0; depth
    is linear, so then every voxel is): with outside='carve' it would carve everything."""
    corners = np.array([[box[i, 0], box[j, 1], box[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    behind = [f"{v} '{cam.name}'" for v, cam in enumerate(cameras) if np.all(cameras.project(corners, v)[1] <= 0)]
    if behind:
        raise NodeError(f"hull: the box {np.round(box, 6).ravel().tolist()} lies entirely behind camera(s) "
                        f"{', '.join(behind)}: check their R|t (world -> camera) or the box, or set outside: ignore")


def border_warning(masks, cameras: Cameras, policy: str) -> str | None:
    """With policy "carve", a warning when the silhouettes touch the image border in most views (more than
    half): the object is cut there, and carve drops every voxel projecting outside an image, losing what lies
    beyond the border; "ignore" keeps it. None otherwise. ``masks``: a MaskSet, host arrays or SilhouetteBits."""
    if policy != "carve" or len(cameras) < 2:
        return None
    if getattr(masks, "device", None) is not None:
        masks = masks.device
    views = border_views(masks if isinstance(masks, SilhouetteBits) else getattr(masks, "masks", masks))
    if 2 * len(views) <= len(cameras):
        return None
    names = ", ".join(cameras[v].name for v in views[:8]) + (f" and {len(views) - 8} more" if len(views) > 8 else "")
    return (f"hull: the silhouettes touch the image border in {len(views)} of the {len(cameras)} views ({names}): "
            "the object is cut by the image border there, and outside: carve removes every voxel that projects "
            "outside an image, so what lies beyond the border is lost; set outside: ignore to keep it")


# ---------------------------------------------------------------- NumPy reference
def hull_reference(masks: list[np.ndarray], cameras: Cameras, bbox_min, voxel_size, dims, min_views=0,
                   policy="carve", min_seen=0) -> np.ndarray:
    """Dense visual hull in NumPy (uint8 0/1, shape dims): the definition the kernels must reproduce."""
    f = np.float32
    bmin, vs = np.asarray(bbox_min, f), np.asarray(voxel_size, f)
    axes = [bmin[a] + (np.arange(n, dtype=f) + f(0.5)) * vs[a] for a, n in enumerate(dims)]
    X = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    packed = cameras.pack()
    n_in = np.zeros(len(X), np.int32)
    n_out = np.zeros(len(X), np.int32)
    for v, m in enumerate(masks):
        s = centre_states(m, packed[v], X)
        n_in += s == 1
        n_out += s == 2
    return vote(n_in, n_out, len(masks), min_views, policy, min_seen).astype(np.uint8).reshape(dims)


class HullCL(clrt.Runner):
    """The hull kernels (kernels/hull.cl); buffers and coarse cell lists kept between frames."""

    source = source("hull.cl")
    GROUP = 64  # whole work-groups: PoCL runs odd sizes as tiny groups

    def __init__(self):
        super().__init__()
        self.coarse: dict[tuple, np.ndarray] = {}
        self.silhouettes: SilhouetteBits | None = None  # what hull() packs host masks into, reused between frames

    def hull(self, masks, cameras: Cameras, bbox_min, voxel_size, dims, min_views=0, policy="carve",
             method="sparse", min_seen=0) -> np.ndarray:
        """Hull of host masks (list of uint8 (H, W)): packed to device bits, then ``carve``."""
        self.silhouettes = SilhouetteBits.from_masks(masks, out=self.silhouettes)
        return self.carve(self.silhouettes, cameras, bbox_min, voxel_size, dims, min_views, policy, method, min_seen)

    def carve(self, sil: SilhouetteBits, cameras: Cameras, bbox_min, voxel_size, dims, min_views=0, policy="carve",
              method="sparse", min_seen=0) -> np.ndarray:
        """Occupancy (uint8 0/1, shape dims) of the voxel grid from device silhouettes."""
        import pyopencl as cl

        packed = cameras.pack()
        if packed.shape[1] != PACK_FLOATS:
            raise NodeError("hull: unexpected camera packing")
        cams = self.upload("cams", packed)
        bits, boff, sat, soff = sil.bits, sil.bit_off_buf, sil.sat, sil.sat_off_buf
        nx, ny, nz = dims
        f4 = lambda a: np.array([*np.asarray(a, np.float32), 0], np.float32)  # noqa: E731
        common = (np.int32(nx), np.int32(ny), np.int32(nz), np.int32(min_views), np.int32(POLICIES.index(policy)),
                  np.int32(min_seen))
        geo = (f4(bbox_min), f4(voxel_size))
        vol = self.buffer("vol", nx * ny * nz)
        nviews = np.int32(len(sil))
        if method == "dense":
            self.launch("hull_dense", (nz, ny, nx), None, cams, nviews, bits, boff, *geo, *common, vol)
        else:
            cl.enqueue_fill_buffer(self.queue, vol, np.uint8(0), 0, nx * ny * nz)
            level = max(1, math.ceil(math.log2(max(dims) / COARSE_CELLS))) if max(dims) > 1 else 1
            cells = self.coarse_cells(dims, level)
            src = self.upload("cells_a", cells)
            count = len(cells)
            cbuf = self.buffer("counter", 4)
            names = ["cells_a", "cells_b"]  # ping-pong: read the one, append children to the other
            while count:
                names.reverse()
                dst = self.buffer(names[0], 8 * count * 4)
                cl.enqueue_copy(self.queue, cbuf, np.zeros(1, np.int32), is_blocking=False)
                self.launch("hull_cells", count, self.GROUP, cams, nviews, bits, boff, sat, soff, *geo, *common,
                            np.int32(level), src, np.int32(count), dst, cbuf, vol)
                if level == 1:
                    break
                count, src, level = int(self.read(cbuf, 1, np.int32)[0]), dst, level - 1
        return self.read(vol, dims, np.uint8)

    def coarse_cells(self, dims, level) -> np.ndarray:
        key = (*dims, level)
        if key not in self.coarse:
            n = [(d + (1 << level) - 1) >> level for d in dims]
            i, j, k = np.meshgrid(*[np.arange(a, dtype=np.uint32) for a in n], indexing="ij")
            self.coarse[key] = (i | (j << 10) | (k << 20)).ravel()
        return self.coarse[key]


def visual_hull(masks, cameras: Cameras, box, resolution=128, min_views=0, policy="carve", method="sparse",
                min_seen=0) -> VoxelGrid:
    """Visual hull over ``box`` (2, 3) as a VoxelGrid of uint8 0/1, from ``masks``: a MaskSet, or SilhouetteBits
    already on the device (from the chroma key, as such or as the ``device`` of its MaskSet: no host round trip).
    ``min_seen`` k > 0: a voxel also needs k views that see it (policy "ignore"; "carve" needs all of them)."""
    if getattr(masks, "device", None) is not None and method != "numpy":
        masks = masks.device
    on_device = isinstance(masks, SilhouetteBits)
    if on_device:
        check_silhouettes(masks, cameras)
    else:
        arrays = check_masks(masks, cameras, "hull")
    if min_views > len(cameras):
        raise NodeError(f"hull: min_views {min_views} is more than the {len(cameras)} cameras")
    if min_seen > len(cameras):
        raise NodeError(f"hull: min_seen {min_seen} is more than the {len(cameras)} cameras")
    box = np.asarray(box, dtype=np.float64).reshape(2, 3)
    with np.errstate(over="ignore", invalid="ignore"):
        ext32 = box[1].astype(np.float32) - box[0].astype(np.float32)     # the kernels' arithmetic
    if not (np.all(np.isfinite(box.astype(np.float32))) and np.all(np.isfinite(ext32)) and np.all(ext32 > 0)):
        raise NodeError(f"hull: box {box.ravel().tolist()} must be finite (within float32 range) with max > min on every axis")
    if policy == "carve":
        check_in_front(cameras, box)
    bmin, bmax, dims = hull_grid(box, resolution)
    vs = (bmax - bmin) / np.array(dims)
    if method == "numpy":
        occ = hull_reference(masks.masks() if on_device else arrays, cameras, bmin, vs, dims, min_views, policy,
                             min_seen)
    elif on_device:
        occ = HullCL.get().carve(masks, cameras, bmin, vs, dims, min_views, policy, method, min_seen)
    else:
        occ = HullCL.get().hull(arrays, cameras, bmin, vs, dims, min_views, policy, method, min_seen)
    return VoxelGrid(occ, bmin, bmax)
