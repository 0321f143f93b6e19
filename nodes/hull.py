"""Volumetric visual hull: voxels whose centre projects inside the silhouettes.

Two OpenCL methods give identical voxels (kernels/hull.cl):
  dense   every voxel centre is tested against every view;
  sparse  coarse-to-fine after Loop, Zhang & Zhang (HPG 2013): cells of 2^L voxels are classified from the
          rectangle bounding their projection, looked up in a summed-area table of the mask (8x8 pixel
          blocks); only cells that are neither certainly inside nor certainly outside are split, and the
          last level decides voxel by voxel with the very same centre test as the dense method.
``hull_reference`` is the NumPy version of the centre test (same float32 arithmetic, same vote rule).
Both methods read the silhouettes as ``SilhouetteBits`` on the device (bits + block tables): packed here
from host masks, or written straight from the camera images by ``nodes.key.chroma_key_bits`` (the fused,
device-resident path of bench/e2e.py).
"""
from __future__ import annotations

import math

import numpy as np

from nodegraph import Bounds, CameraSet, Input, Masks, Node, NodeError, Param, Volume, VoxelGrid
from nodegraph.cameras import PACK_FLOATS, Cameras, project_packed_f32
from nodegraph.devbuffers import DeviceBuffers

POLICIES = ("carve", "ignore")
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


def check_views(masks, cameras: Cameras) -> list[np.ndarray]:
    """The masks as contiguous uint8 (H, W) arrays, one per camera, or a NodeError naming the camera."""
    if len(masks.masks) != len(cameras):
        raise NodeError(f"hull: {len(masks.masks)} masks for {len(cameras)} cameras")
    out = []
    for m, cam in zip(masks.masks, cameras):
        m = np.asarray(m)
        if m.dtype != np.uint8 or m.ndim != 2:
            raise NodeError(f"hull: mask of camera '{cam.name}' must be an (H, W) uint8 array, got {m.dtype} {m.shape}")
        if m.shape != (cam.height, cam.width):
            raise NodeError(f"hull: mask of camera '{cam.name}' is {m.shape[1]}x{m.shape[0]} but the camera is {cam.width}x{cam.height}")
        out.append(np.ascontiguousarray(m))
    return out


def check_in_front(cameras: Cameras, box: np.ndarray):
    """A NodeError naming each camera that has the whole box behind it (all 8 corners at depth <= 0; depth
    is linear, so then every voxel is): with outside='carve' it would carve everything."""
    corners = np.array([[box[i, 0], box[j, 1], box[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    behind = [f"{v} '{cam.name}'" for v, cam in enumerate(cameras) if np.all(cameras.project(corners, v)[1] <= 0)]
    if behind:
        raise NodeError(f"hull: the box {np.round(box, 6).ravel().tolist()} lies entirely behind camera(s) "
                        f"{', '.join(behind)}: check their R|t (world -> camera) or the box, or set outside: ignore")


# ---------------------------------------------------------------- NumPy reference
def centre_states(mask: np.ndarray, cam_row: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Per point (N, 3 float32): 1 = inside the silhouette, 2 = background, 3 = behind / outside the image.
    ``cam_row`` is one row of Cameras.pack(); float32 operations in the order of kernels/camera.h."""
    c = cam_row.astype(np.float32)
    u, v, front = project_packed_f32(c, X)
    with np.errstate(invalid="ignore"):
        fu, fv = u + np.float32(0.5), v + np.float32(0.5)
        seen = front & (fu >= 0) & (fu < c[22]) & (fv >= 0) & (fv < c[23])
    state = np.full(len(X), 3, np.uint8)
    px, py = fu[seen].astype(np.int64), fv[seen].astype(np.int64)
    state[seen] = np.where(mask[py, px] > 127, 1, 2)
    return state


def vote(n_in: np.ndarray, n_out: np.ndarray, nviews: int, min_views: int, policy: str) -> np.ndarray:
    """The hull's vote rule: min_views > 0: at least that many views see the voxel inside; otherwise
    carve: every view does; ignore: no view sees it on background and at least one inside."""
    if min_views > 0:
        return n_in >= min_views
    if policy == "carve":
        return n_in == nviews
    return (n_out == 0) & (n_in > 0)


def hull_reference(masks: list[np.ndarray], cameras: Cameras, bbox_min, voxel_size, dims, min_views=0,
                   policy="carve") -> np.ndarray:
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
    return vote(n_in, n_out, len(masks), min_views, policy).astype(np.uint8).reshape(dims)


# ---------------------------------------------------------------- OpenCL
class SilhouetteBits:
    """Silhouettes on the OpenCL device, in the layout the hull kernels read (kernels/hull.cl), one per view:
    one bit per pixel (rows of Wb = ceil(W/8) bytes, pixel x in bit x % 8 of byte x // 8) and the
    (Hb+1) x (Wb+1) int32 summed-area table of its 8x8 pixel block counts (zero first row and column).

    Written from host masks (``HullCL.prepare``) or straight from the camera images by a key kernel
    (``nodes.key.chroma_key_bits``): both write the bits and the block counts prefixed along rows, then
    ``prefix_columns`` completes the tables. Allocated once per list of image sizes; hand it back as ``out=``
    to the next frame's producer to reuse its buffers (its contents are then overwritten)."""

    def __init__(self, sizes: list[tuple[int, int]]):
        import pyopencl as cl

        from nodegraph import clrt

        self.sizes = [(int(w), int(h)) for w, h in sizes]
        wb = [(w + 7) // 8 for w, _ in self.sizes]
        hb = [(h + 7) // 8 for _, h in self.sizes]
        self.bit_off = np.concatenate([[0], np.cumsum([b * h for b, (_, h) in zip(wb, self.sizes)])]).astype(np.int64)
        self.sat_off = np.concatenate([[0], np.cumsum([(a + 1) * (b + 1) for a, b in zip(wb, hb)])]).astype(np.int64)
        if self.bit_off[-1] >= 2**31 or self.sat_off[-1] >= 2**31:
            raise NodeError(f"hull: {len(sizes)} silhouettes are too large for 32-bit offsets")
        ctx, _ = clrt.context()
        rw = cl.mem_flags.READ_WRITE
        self.bits = cl.Buffer(ctx, rw, max(int(self.bit_off[-1]), 4))
        self.sat = cl.Buffer(ctx, rw, max(int(self.sat_off[-1]) * 4, 4))
        self.bit_off_buf = clrt.to_device(self.bit_off[:-1].astype(np.int32))
        self.sat_off_buf = clrt.to_device(self.sat_off[:-1].astype(np.int32))
        self.sizes_buf = clrt.to_device(np.array(self.sizes, np.int32).reshape(-1, 2))

    def __len__(self) -> int:
        return len(self.sizes)

    @classmethod
    def reuse(cls, out: "SilhouetteBits | None", sizes) -> "SilhouetteBits":
        """``out`` when it was made for these image sizes, else a new one."""
        sizes = [(int(w), int(h)) for w, h in sizes]
        return out if out is not None and out.sizes == sizes else cls(sizes)

    def prefix_columns(self):
        """Enqueue the column prefix that turns the row-prefixed block counts into summed-area tables."""
        from nodegraph import clrt

        wb = max(w for w, _ in self.sizes) // 8 + 2
        clrt.kernel("hull.cl", "block_cols")(clrt.queue(), (wb, len(self)), None, self.sat, self.sat_off_buf,
                                             self.sizes_buf)

    def masks(self) -> list[np.ndarray]:
        """The silhouettes back on the host as uint8 (H, W) 0/255 masks (for checks; a read-back)."""
        import pyopencl as cl

        from nodegraph import clrt

        raw = np.empty(int(self.bit_off[-1]), np.uint8)
        cl.enqueue_copy(clrt.queue(), raw, self.bits)
        out = []
        for v, (w, h) in enumerate(self.sizes):
            rows = raw[self.bit_off[v]:self.bit_off[v + 1]].reshape(h, -1)
            out.append(np.unpackbits(rows, axis=1, bitorder="little")[:, :w] * np.uint8(255))
        return out

    def block_tables(self) -> list[np.ndarray]:
        """The (Hb+1, Wb+1) int32 summed-area tables back on the host (for checks; a read-back)."""
        import pyopencl as cl

        from nodegraph import clrt

        raw = np.empty(int(self.sat_off[-1]), np.int32)
        cl.enqueue_copy(clrt.queue(), raw, self.sat)
        return [raw[self.sat_off[v]:self.sat_off[v + 1]].reshape((h + 7) // 8 + 1, (w + 7) // 8 + 1)
                for v, (w, h) in enumerate(self.sizes)]


def block_table_reference(mask: np.ndarray) -> np.ndarray:
    """Summed-area table (Hb+1, Wb+1) int32 of the 8x8 pixel block counts of (mask > 127)."""
    h, w = mask.shape
    m = np.zeros((-(-h // 8) * 8, -(-w // 8) * 8), np.int32)
    m[:h, :w] = mask > 127
    counts = m.reshape(m.shape[0] // 8, 8, m.shape[1] // 8, 8).sum(axis=(1, 3))
    return np.pad(counts.cumsum(0).cumsum(1), ((1, 0), (1, 0))).astype(np.int32)


def check_silhouettes(sil: SilhouetteBits, cameras: Cameras):
    """A NodeError naming the camera when the device silhouettes do not fit the cameras."""
    if len(sil) != len(cameras):
        raise NodeError(f"hull: {len(sil)} silhouettes for {len(cameras)} cameras")
    for (w, h), cam in zip(sil.sizes, cameras):
        if (w, h) != (cam.width, cam.height):
            raise NodeError(f"hull: silhouette of camera '{cam.name}' is {w}x{h} but the camera is "
                            f"{cam.width}x{cam.height}")


class HullCL:
    """Device buffers and kernels of the hull, kept between frames (one per process)."""

    def __init__(self):
        from nodegraph import clrt

        self.ctx, self.queue = clrt.context()
        self.k = {name: clrt.kernel("hull.cl", name) for name in ("pack_block_rows", "hull_dense", "hull_cells")}
        self.buffers = DeviceBuffers(self.ctx)
        self.coarse: dict[tuple, np.ndarray] = {}
        self.silhouettes: SilhouetteBits | None = None  # what prepare() fills, reused between frames

    def upload(self, name: str, arr: np.ndarray):
        import pyopencl as cl

        buf = self.buffers.get(name, arr.nbytes)
        cl.enqueue_copy(self.queue, buf, np.ascontiguousarray(arr), is_blocking=False)
        return buf

    def prepare(self, masks: list[np.ndarray], out: SilhouetteBits | None = None) -> SilhouetteBits:
        """Host uint8 masks to device silhouettes: bits and 8x8-block summed-area tables (into ``out`` when it
        fits, else into buffers kept here)."""
        import pyopencl as cl

        sizes = [(m.shape[1], m.shape[0]) for m in masks]
        sil = SilhouetteBits.reuse(out if out is not None else self.silhouettes, sizes)
        if out is None:
            self.silhouettes = sil
        mf = cl.mem_flags
        host = []  # keep the zero-copy host buffers alive until the queue is done
        for v, m in enumerate(masks):
            src = cl.Buffer(self.ctx, mf.READ_ONLY | mf.USE_HOST_PTR, hostbuf=m)
            host.append(src)
            rows = (m.shape[0] + 7) // 8 + 1  # work items: rows of the block table, in groups of 8 (PoCL's own
            # choice ran them on one thread)
            self.k["pack_block_rows"](self.queue, (-(-rows // 8) * 8,), (8,), src, np.int32(m.shape[1]),
                                      np.int32(m.shape[0]), sil.bits, np.int32(sil.bit_off[v]), sil.sat,
                                      np.int32(sil.sat_off[v]))
        sil.prefix_columns()
        self.queue.finish()
        return sil

    def hull(self, masks, cameras: Cameras, bbox_min, voxel_size, dims, min_views=0, policy="carve",
             method="sparse") -> np.ndarray:
        """Hull of host masks (list of uint8 (H, W)): ``prepare`` then ``carve``."""
        return self.carve(self.prepare(masks), cameras, bbox_min, voxel_size, dims, min_views, policy, method)

    def carve(self, sil: SilhouetteBits, cameras: Cameras, bbox_min, voxel_size, dims, min_views=0, policy="carve",
              method="sparse") -> np.ndarray:
        """Occupancy (uint8 0/1, shape dims) of the voxel grid from device silhouettes."""
        import pyopencl as cl

        packed = cameras.pack()
        if packed.shape[1] != PACK_FLOATS:
            raise NodeError("hull: unexpected camera packing")
        cams = self.upload("cams", packed)
        bits, boff, sat, soff = sil.bits, sil.bit_off_buf, sil.sat, sil.sat_off_buf
        nx, ny, nz = dims
        f4 = lambda a: np.array([*np.asarray(a, np.float32), 0], np.float32)  # noqa: E731
        common = (np.int32(nx), np.int32(ny), np.int32(nz), np.int32(min_views), np.int32(POLICIES.index(policy)))
        geo = (f4(bbox_min), f4(voxel_size))
        vol = self.buffers.get("vol", nx * ny * nz)
        nviews = np.int32(len(sil))
        if method == "dense":
            self.k["hull_dense"](self.queue, (nz, ny, nx), None, cams, nviews, bits, boff, *geo, *common, vol)
        else:
            cl.enqueue_fill_buffer(self.queue, vol, np.uint8(0), 0, nx * ny * nz)
            level = max(1, math.ceil(math.log2(max(dims) / COARSE_CELLS))) if max(dims) > 1 else 1
            cells = self.coarse_cells(dims, level)
            src = self.upload("cells_a", cells)
            count = len(cells)
            counter = np.zeros(1, np.int32)
            cbuf = self.buffers.get("counter", 4)
            names = ["cells_a", "cells_b"]  # ping-pong: read the one, append children to the other
            while count:
                names.reverse()
                dst = self.buffers.get(names[0], 8 * count * 4)
                cl.enqueue_copy(self.queue, cbuf, np.zeros(1, np.int32), is_blocking=False)
                groups = -(-count // 64) * 64  # whole work-groups: PoCL runs odd sizes as tiny groups
                self.k["hull_cells"](self.queue, (groups,), (64,), cams, nviews, bits, boff, sat, soff, *geo, *common,
                                     np.int32(level), src, np.int32(count), dst, cbuf, vol)
                if level == 1:
                    break
                cl.enqueue_copy(self.queue, counter, cbuf)
                count, src, level = int(counter[0]), dst, level - 1
        out = np.empty(dims, np.uint8)
        cl.enqueue_copy(self.queue, out, vol, is_blocking=True)
        return out

    def coarse_cells(self, dims, level) -> np.ndarray:
        key = (*dims, level)
        if key not in self.coarse:
            n = [(d + (1 << level) - 1) >> level for d in dims]
            i, j, k = np.meshgrid(*[np.arange(a, dtype=np.uint32) for a in n], indexing="ij")
            self.coarse[key] = (i | (j << 10) | (k << 20)).ravel()
        return self.coarse[key]


_HULL_CL: HullCL | None = None


def hull_cl() -> HullCL:
    global _HULL_CL
    if _HULL_CL is None:
        _HULL_CL = HullCL()
    return _HULL_CL


def visual_hull(masks, cameras: Cameras, box, resolution=128, min_views=0, policy="carve", method="sparse") -> VoxelGrid:
    """Visual hull over ``box`` (2, 3) as a VoxelGrid of uint8 0/1, from ``masks``: a MaskSet, or
    SilhouetteBits already on the device (e.g. from nodes.key.chroma_key_bits; no host round trip)."""
    on_device = isinstance(masks, SilhouetteBits)
    if on_device:
        check_silhouettes(masks, cameras)
    else:
        arrays = check_views(masks, cameras)
    if min_views > len(cameras):
        raise NodeError(f"hull: min_views {min_views} is more than the {len(cameras)} cameras")
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
        occ = hull_reference(masks.masks() if on_device else arrays, cameras, bmin, vs, dims, min_views, policy)
    elif on_device:
        occ = hull_cl().carve(masks, cameras, bmin, vs, dims, min_views, policy, method)
    else:
        occ = hull_cl().hull(arrays, cameras, bmin, vs, dims, min_views, policy, method)
    return VoxelGrid(occ, bmin, bmax)


class Hull(Node):
    """Volumetric visual hull: voxels whose centre falls inside the silhouettes (OpenCL, coarse-to-fine)."""

    type_name = "hull"
    version = 1
    inputs = {"masks": Masks, "cameras": CameraSet,
              "bounds": Input(Bounds, optional=True, doc="box to carve when the bbox param is not given")}
    outputs = {"volume": Volume}
    params = {
        "resolution": Param(int, 128, range=(8, 1024), doc="voxels along the longest bbox side; others proportional"),
        "bbox": Param(list, None, item=float, length=6, doc="xmin ymin zmin xmax ymax zmax; default: the bounds input"),
        "min_views": Param(int, 0, range=(0, None), doc="0 = all views; k = inside at least k silhouettes"),
        "outside": Param(str, "carve", choices=POLICIES, doc="voxels projecting outside an image: carve, or ignore that view"),
        "method": Param(str, "sparse", choices=("sparse", "dense", "numpy"), doc="coarse-to-fine, every voxel, or NumPy"),
    }
    kernels = ["hull.cl"]

    def run(self, masks, cameras, bounds=None, *, resolution, bbox, min_views, outside, method):
        if bbox is not None:
            box = np.array(bbox, dtype=np.float64).reshape(2, 3)
            if not np.all(box[1] > box[0]):
                raise NodeError(f"hull: param 'bbox' {bbox} needs max > min on every axis (xmin ymin zmin xmax ymax zmax)")
        elif bounds is not None:
            box = np.asarray(bounds, dtype=np.float64)
        else:
            raise NodeError("hull: no box to carve: set param 'bbox' or connect the 'bounds' input")
        volume = visual_hull(masks, cameras, box, resolution, min_views, outside, method)
        if not volume.occupancy.any():
            self.log.warning("hull: no voxel is inside the silhouettes: the box %s misses the object, or the masks "
                             "and cameras disagree (the mesh will be empty)", np.round(box, 6).ravel().tolist())
        return {"volume": volume}
