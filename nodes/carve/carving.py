"""Photo-consistency carving of a voxel volume (the visual hull) with images, masks and cameras.

    space_carving   Kutulakos & Seitz (IJCV 2000), multi-sweep: planes swept along +x -x +y -y +z -z; each
                    plane's surface voxels are tested in the cameras behind the plane, with visibility from
                    per-camera mark buffers that kept voxels of earlier planes fill; after the six sweeps one
                    pass over all surface voxels with exact visibility from per-camera item buffers (Culbertson
                    et al. 1999) tests each voxel in every camera that sees it; repeated until a pass removes
                    nothing (or max_passes).
    voxel_coloring  Seitz & Dyer (IJCV 1999): one pass over layers of increasing distance from the convex
                    hull of the camera centres (valid only when no voxel lies inside that hull: the ordinal
                    visibility constraint), every camera in every layer, marks as above.

Only surface voxels (an empty face neighbour) are tested; a voxel seen in fewer than ``min_views`` views is
kept. A voxel whose removal would leave the ray through its centre empty in a view whose silhouette holds
that centre is kept, so the result stays inside the input volume and keeps covering the masks. The
photo-consistency arithmetic is in photo.py; the kernels are kernels/carve.cl; reference.py is the NumPy
version of every kernel, run through the very same driver (``carve(..., method="numpy")``).

Colours: at the end one item-buffer pass gives every surface voxel the mean colour over the views that see
it (VoxelGrid.colors); surface voxels no view sees take the mean of coloured neighbours.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from kernels import source
from nodegraph import NodeError
from nodegraph.clrt import Runner
from nodes.common.cameras import Cameras
from nodes.common.silhouettes import check_masks, check_sizes
from nodes.common.types import VoxelGrid

from .photo import SPACES, camera_gains

AXES = "xyz"


@dataclass
class CarveParams:
    threshold: float = 30.0      # colour deviation limit, in units of `space`
    adaptive: float = 0.0        # ... plus this times the RMS spread of the pixels within a view
    space: str = "rgb"
    gain: bool = False           # per-camera gain normalisation
    min_views: int = 2           # a voxel seen in fewer views is kept untested
    footprint: float = 0.7       # sampled part of the voxel's projected half-size
    max_angle: float = 70.0      # views seeing a voxel at more than this from its normal are not used (degrees)
    max_passes: int = 500        # space carving: passes of (6 sweeps +) 1 item pass; 0 = colour only
    cone: float = 65.0           # sweeps: a camera tests a voxel when its ray is within this of the sweep axis
    sweep_fraction: float = 0.25  # sweep again while a pass removes more than this fraction of the surface voxels
    largest: bool = True         # keep only the largest 6-connected part (carving can cut off fragments)

    @property
    def cos_cone(self) -> float:
        return float(np.float32(np.cos(np.radians(self.cone))))

    @property
    def cos_min(self) -> float:
        return float(np.float32(np.cos(np.radians(self.max_angle))))


@dataclass
class Views:
    """What the kernels read of the cameras and images, for voxel centres relative to ``origin``."""

    cams: np.ndarray             # (V, 32) float32, Cameras.pack(origin)
    centres: np.ndarray          # (V, 4) float32, camera centres relative to origin
    gains: np.ndarray            # (V, 4) float32
    images: list[np.ndarray]     # (H, W, 4) uint8: r g b mask
    offsets: np.ndarray          # (V,) int64 first pixel of each view in the shared buffers

    @property
    def npixels(self) -> int:
        return int(self.offsets[-1] + self.images[-1].shape[0] * self.images[-1].shape[1])


@dataclass
class Grid:
    occ: np.ndarray              # (nx, ny, nz) uint8 0/1
    vs: np.ndarray               # (3,) float32 voxel size
    lists: dict = field(default_factory=dict)   # name -> (flat voxel indices uint32, plane offsets int64)

    @property
    def dims(self) -> tuple[int, int, int]:
        return tuple(int(d) for d in self.occ.shape)

    @property
    def vs4(self) -> np.ndarray:
        return np.array([*self.vs, 0], np.float32)


def make_views(images, masks, cameras: Cameras, origin, gain: bool) -> Views:
    f = np.float32
    cams = cameras.pack(origin=origin)
    centres = np.zeros((len(cameras), 4), f)
    centres[:, :3] = cameras.centers - np.asarray(origin, np.float64)
    gains = np.ones((len(cameras), 4), f)
    if gain:
        gains[:, :3] = camera_gains(images, masks)
    rgbm = [np.ascontiguousarray(np.concatenate([im, m[:, :, None]], axis=2)) for im, m in zip(images, masks)]
    sizes = np.array([im.shape[0] * im.shape[1] for im in rgbm], np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    if offsets[-1] + sizes[-1] >= 2**31:
        raise NodeError(f"carve: {len(images)} images are too large for 32-bit pixel offsets")
    return Views(cams, centres, gains, rgbm, offsets)


def axis_lists(occ: np.ndarray) -> dict:
    """Occupied voxels (flat indices into ``occ``) grouped by plane along each axis: name -> (indices,
    offsets (n + 1,)); the voxels of plane p along that axis are indices[offsets[p]:offsets[p + 1]]."""
    nx, ny, nz = occ.shape
    out = {}
    i, j, k = np.nonzero(occ)                                   # sorted by i
    out["x"] = _grouped(i, j, k, i, nx, occ.shape)
    jt, it, kt = np.nonzero(np.ascontiguousarray(occ.transpose(1, 0, 2)))   # sorted by j
    out["y"] = _grouped(it, jt, kt, jt, ny, occ.shape)
    kt, it, jt = np.nonzero(np.ascontiguousarray(occ.transpose(2, 0, 1)))   # sorted by k
    out["z"] = _grouped(it, jt, kt, kt, nz, occ.shape)
    return out


def _grouped(i, j, k, plane, n, shape) -> tuple[np.ndarray, np.ndarray]:
    flat = ((i.astype(np.int64) * shape[1] + j) * shape[2] + k).astype(np.uint32)
    offsets = np.concatenate([[0], np.cumsum(np.bincount(plane, minlength=n))]).astype(np.int64)
    return flat, offsets


def hull_distance(X: np.ndarray, centres: np.ndarray, vs, shape, node: str = "carve.voxel_coloring") -> np.ndarray:
    """g(X) for points (N, 3): the largest signed distance to the facet planes of the convex hull of the camera
    centres. g is convex and <= 0 at every camera, so along any ray from a camera it grows once it is positive:
    a near-to-far order for every camera at once (Seitz & Dyer's ordinal visibility) where g > 0."""
    from scipy.spatial import ConvexHull, QhullError

    C = np.asarray(centres, np.float64)[:, :3]
    scale = max(float(np.ptp(C, axis=0).max()), float(np.max(vs)) * max(shape))
    # a tiny tetrahedron at each camera makes the hull of a ring or of a single camera three-dimensional
    tet = scale * 1e-6 * np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], np.float64)
    pts = (C[:, None, :] + tet[None]).reshape(-1, 3)
    try:
        eq = ConvexHull(pts, qhull_options="QJ").equations
    except QhullError as exc:
        raise NodeError(f"{node}: no convex hull of the camera centres ({str(exc).splitlines()[0]})") from None
    X = np.asarray(X, np.float64)
    g = np.full(len(X), -np.inf)
    for n0, n1, n2, off in eq:
        g = np.maximum(g, X[:, 0] * n0 + X[:, 1] * n1 + X[:, 2] * n2 + off)
    return g


def layer_list(occ: np.ndarray, vs: np.ndarray, centres: np.ndarray, node: str = "carve.voxel_coloring"):
    """Voxel colouring's layers: occupied voxels sorted by hull_distance(centre) // min(vs) (indices, offsets per
    layer). A NodeError when a voxel is not outside the cameras' convex hull by half a voxel."""
    flat = np.flatnonzero(occ)
    X = (np.stack(np.unravel_index(flat, occ.shape), axis=1) + 0.5) * vs.astype(np.float64)
    g = hull_distance(X, centres, vs, occ.shape, node)
    inside = g <= 0.5 * float(np.min(vs))
    if inside.any():
        raise NodeError(f"{node}: {int(inside.sum())} of {len(X)} voxels lie inside (or within half a voxel of) the "
                        "convex hull of the camera centres, so no near-to-far order exists for every camera (Seitz "
                        "& Dyer's ordinal visibility constraint); use carve.space_carving for cameras around the object")
    layer = np.floor(g / float(np.min(vs))).astype(np.int64)
    layer -= layer.min()
    order = np.argsort(g, kind="stable")
    offsets = np.concatenate([[0], np.cumsum(np.bincount(layer, minlength=int(layer.max()) + 1))]).astype(np.int64)
    return flat[order].astype(np.uint32), offsets


# ---------------------------------------------------------------- OpenCL backend
class CarveCL(Runner):
    """kernels/carve.cl on the device: occupancy, stamps, marks, item buffers, views; one step per call."""

    source = source("carve.cl")
    GROUP = 64

    def setup(self, grid: Grid, views: Views, params: CarveParams):
        import pyopencl as cl

        self.grid, self.views, self.params = grid, views, params
        self.nviews = np.int32(len(views.cams))
        nvox = grid.occ.size
        self.occ = self.buffer("occ", nvox)
        cl.enqueue_copy(self.queue, self.occ, np.ascontiguousarray(grid.occ).ravel(), is_blocking=False)
        self.stamp = self.buffer("stamp", 4 * nvox)
        cl.enqueue_fill_buffer(self.queue, self.stamp, np.int32(-1), 0, 4 * nvox)
        self.cams = self.upload("cams", views.cams)
        self.centres = self.upload("centres", views.centres)
        self.gains = self.upload("gains", views.gains)
        self.pix_off = self.upload("pix_off", views.offsets.astype(np.int32))
        npix = views.npixels
        self.images = self.buffer("images", 4 * npix)
        for off, im in zip(views.offsets, views.images):
            cl.enqueue_copy(self.queue, self.images, im, dst_offset=int(4 * off), is_blocking=False)
        self.marks = self.buffer("marks", npix)
        self.items = self.buffer("items", 8 * npix)
        self.npix = npix
        self.counter = self.buffer("removed", 4)
        cl.enqueue_fill_buffer(self.queue, self.counter, np.int32(0), 0, 4)
        self.fresh = self.buffer("fresh", nvox)
        cl.enqueue_fill_buffer(self.queue, self.fresh, np.uint8(0), 0, nvox)
        self.fresh_counter = self.buffer("fresh_counter", 4)
        self.nlist = len(grid.lists["x"][0])
        self.lists = {name: self.upload(f"list_{name}", idx) for name, (idx, _) in grid.lists.items()}
        self.lists["fresh"] = self.buffer("list_fresh", 4 * max(1, len(grid.lists["x"][0])))
        self.dims = tuple(np.int32(d) for d in grid.dims)

        self.colors = self.buffer("colors", 4)
        self.variance = self.buffer("variance", 4)
        p = params
        # static arguments are set once; a step sets only the first seven (list .. sign, use_items/do_marks) and step
        self.k_test = self.kernel("carve_test")
        self.k_test.set_args(self.lists["x"], np.int32(0), np.int32(0), np.int32(-1), np.float32(0), np.float32(0),
                             np.int32(0), self.occ, self.stamp, np.int32(0), *self.dims, grid.vs4, self.cams,
                             self.centres, self.gains, self.nviews, self.pix_off, self.images, self.marks, self.items,
                             np.float32(p.footprint), np.float32(p.cos_cone), np.float32(p.cos_min),
                             np.int32(p.min_views), np.float32(p.threshold), np.float32(p.adaptive),
                             np.int32(SPACES.index(p.space)), np.int32(0), self.colors, self.variance)
        self.k_commit = self.kernel("carve_commit")
        self.k_commit.set_args(self.lists["x"], np.int32(0), np.int32(0), np.int32(-1), np.float32(0), np.float32(0),
                               np.int32(0), self.occ, self.stamp, np.int32(0), *self.dims, grid.vs4, self.cams,
                               self.centres, self.nviews, self.pix_off, self.images, self.marks, self.counter,
                               self.items, self.fresh)

    def _step(self, k, name, first, count, axis, plane, sign, flag, step):
        import pyopencl as cl

        for i, a in enumerate((self.lists[name], np.int32(first), np.int32(count), np.int32(axis), np.float32(plane),
                               np.float32(sign), np.int32(flag))):
            k.set_arg(i, a)
        k.set_arg(9, np.int32(step))
        cl.enqueue_nd_range_kernel(self.queue, k, (max(self.GROUP, -(-count // self.GROUP) * self.GROUP),),
                                   (self.GROUP,))

    def reset_marks(self):
        self.launch("carve_reset_marks", self.npix, self.GROUP, self.images, np.int32(self.npix), self.marks)

    def reset_items(self):
        import pyopencl as cl

        cl.enqueue_fill_buffer(self.queue, self.items, np.uint64(0xFFFFFFFFFFFFFFFF), 0, 8 * self.npix)

    def splat(self, name, first, count):
        self.launch("carve_splat", count, self.GROUP, self.lists[name], np.int32(first), np.int32(count), self.occ,
                    *self.dims, self.grid.vs4, self.cams, self.centres, self.nviews, self.pix_off, self.images,
                    self.items)

    def test(self, name, first, count, axis, plane, sign, use_items, step, write_colors=False):
        if write_colors:
            import pyopencl as cl

            self.colors = self.buffer("colors", 4 * max(count, 1))
            self.variance = self.buffer("variance", 4 * max(count, 1))
            cl.enqueue_fill_buffer(self.queue, self.colors, np.uint8(0), 0, 4 * count)
            cl.enqueue_fill_buffer(self.queue, self.variance, np.float32(-1), 0, 4 * count)
            self.k_test.set_arg(29, np.int32(1))
            self.k_test.set_arg(30, self.colors)
            self.k_test.set_arg(31, self.variance)
        self._step(self.k_test, name, first, count, axis, plane, sign, use_items, step)
        if write_colors:
            self.k_test.set_arg(29, np.int32(0))

    def commit(self, name, first, count, axis, plane, sign, do_marks, step):
        self._step(self.k_commit, name, first, count, axis, plane, sign, do_marks, step)

    def compact(self) -> int:
        """List the flagged surface voxels (list "fresh"); returns their number."""
        import pyopencl as cl

        cl.enqueue_fill_buffer(self.queue, self.fresh_counter, np.int32(0), 0, 4)
        self.launch("carve_compact", self.nlist, self.GROUP, self.lists["x"], np.int32(self.nlist), self.occ, self.fresh,
                    *self.dims, self.lists["fresh"], self.fresh_counter)
        return int(self.read(self.fresh_counter, 1, np.int32)[0])

    def removed(self) -> int:
        import pyopencl as cl

        n = self.read(self.counter, 1, np.int32)
        cl.enqueue_fill_buffer(self.queue, self.counter, np.int32(0), 0, 4)
        return int(n[0])

    def occupancy(self) -> np.ndarray:
        return self.read(self.occ, self.grid.dims, np.uint8) & np.uint8(1)

    def set_occupancy(self, occ: np.ndarray):
        import pyopencl as cl

        cl.enqueue_copy(self.queue, self.occ, np.ascontiguousarray(occ, np.uint8).ravel(), is_blocking=True)

    def colours(self, count) -> tuple[np.ndarray, np.ndarray]:
        return self.read(self.colors, (count, 4), np.uint8), self.read(self.variance, count, np.float32)


# ---------------------------------------------------------------- the driver
class Carver:
    """The steps of both algorithms over a backend (CarveCL or reference.CarveNumPy)."""

    def __init__(self, backend, grid: Grid, params: CarveParams):
        self.b, self.grid, self.p = backend, grid, params
        self.step = 0
        self.log: list[dict] = []

    def sweep(self, axis: int, sign: int) -> None:
        """One plane sweep along +axis (sign 1) or -axis (sign -1): each plane tested in the cameras behind it."""
        name = AXES[axis]
        _, offsets = self.grid.lists[name]
        planes = range(len(offsets) - 1)
        self.b.reset_marks()
        for p in (planes if sign > 0 else reversed(planes)):
            first, count = int(offsets[p]), int(offsets[p + 1] - offsets[p])
            if count == 0:
                continue
            plane = float(np.float32(p if sign > 0 else p + 1) * self.grid.vs[axis])
            self.step += 1
            self.b.test(name, first, count, axis, plane, sign, 0, self.step)
            self.b.commit(name, first, count, axis, plane, sign, 1, self.step)

    def item_pass(self, incremental: bool = False) -> str:
        """Surface voxels tested in every camera, visibility from item buffers. Full: the buffers are rebuilt
        from every surface voxel and all are tested. Incremental: only the surface voxels flagged by the last
        item pass's removals are splatted into the buffers (which gave back the removed voxels' pixels) and
        tested; none flagged means a full pass. Returns "full" or "incremental"."""
        n = self.b.compact() if incremental else 0
        self.step += 1
        if n:
            self.b.splat("fresh", 0, n)
            self.b.test("fresh", 0, n, -1, 0.0, 0, 1, self.step)
            self.b.commit("fresh", 0, n, -1, 0.0, 0, 0, self.step)
            return "incremental"
        n = len(self.grid.lists["x"][0])
        self.b.reset_items()
        self.b.splat("x", 0, n)
        self.b.test("x", 0, n, -1, 0.0, 0, 1, self.step)
        self.b.commit("x", 0, n, -1, 0.0, 0, 0, self.step)
        return "full"

    def space_carving(self) -> int:
        """Passes until a full item pass removes nothing. A pass: 6 sweeps (the first pass, and again while a
        pass removes more than ``sweep_fraction`` of the surface voxels: they carve deep at once), then one item
        pass (exact visibility, every view): full after sweeps, else incremental (only what the last removals
        exposed), full again when nothing is left to test. At the end every surface voxel is photo-consistent
        in all the views that see it, or protected, or seen in fewer than min_views."""
        total, sweeps, full = 0, True, True
        surface = max(1, surface_count(self.grid.occ))
        for k in range(self.p.max_passes):
            t = time.perf_counter()
            by_sweeps = 0
            if sweeps:
                for axis in range(3):
                    for sign in (1, -1):
                        self.sweep(axis, sign)
                by_sweeps = self.b.removed()
            kind = self.item_pass(incremental=not (sweeps or full))
            by_items = self.b.removed()
            total += by_sweeps + by_items
            self.log.append({"pass": k + 1, "sweeps": sweeps, "items": kind, "removed": by_sweeps + by_items,
                             "seconds": round(time.perf_counter() - t, 4)})
            if kind == "full" and by_items == 0 and by_sweeps == 0:
                break
            full = False
            sweeps = by_sweeps + by_items > self.p.sweep_fraction * surface
        return total

    def voxel_coloring(self) -> int:
        _, offsets = self.grid.lists["layers"]
        self.b.reset_marks()
        for layer in range(len(offsets) - 1):
            first, count = int(offsets[layer]), int(offsets[layer + 1] - offsets[layer])
            if count:
                self.step += 1
                self.b.test("layers", first, count, -1, 0.0, 0, 0, self.step)
                self.b.commit("layers", first, count, -1, 0.0, 0, 1, self.step)
        removed = self.b.removed()
        self.log.append({"pass": 1, "removed": removed})
        return removed

    def colours(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(colors (nx, ny, nz, 3) uint8, views (nx, ny, nz) uint8, variance per surface voxel seen in >= 2 views)
        of the current volume, from one item-buffer pass."""
        idx = self.grid.lists["x"][0]
        n = len(idx)
        self.b.reset_items()
        self.b.splat("x", 0, n)
        self.b.test("x", 0, n, -1, 0.0, 0, 1, 0, write_colors=True)
        col, var = self.b.colours(n)
        colors = np.zeros((*self.grid.dims, 3), np.uint8)
        views = np.zeros(self.grid.dims, np.uint8)
        colors.reshape(-1, 3)[idx] = col[:, :3]
        views.reshape(-1)[idx] = col[:, 3]
        return colors, views, var[var >= 0]


def largest_part(occ: np.ndarray) -> tuple[np.ndarray, int]:
    """(occupancy of the largest 6-connected part, number of other parts dropped)."""
    from scipy import ndimage

    labels, n = ndimage.label(occ)
    if n <= 1:
        return occ, 0
    keep = np.argmax(np.bincount(labels.ravel())[1:]) + 1
    return (labels == keep).astype(np.uint8), n - 1


def surface_count(occ: np.ndarray) -> int:
    """Number of occupied voxels with an empty face neighbour (outside the grid counts as empty)."""
    o = np.pad(occ.astype(bool), 1)
    inner = o[1:-1, 1:-1, 1:-1]
    full = inner.copy()
    for a in range(3):
        for s in (0, 2):
            sl = [slice(1, -1)] * 3
            sl[a] = slice(s, s + inner.shape[a])
            full &= o[tuple(sl)]
    return int((inner & ~full).sum())


def fill_colours(occ: np.ndarray, colors: np.ndarray, views: np.ndarray, rounds: int = 8) -> np.ndarray:
    """Surface voxels no view sees (views == 0) take the mean colour of their coloured 26-neighbours, repeated
    ``rounds`` times outwards from the coloured ones; what is still uncoloured stays mid-grey."""
    from scipy import ndimage

    occ = occ.astype(bool)
    surface = occ & ~ndimage.binary_erosion(occ, border_value=0)
    known = views > 0
    todo = surface & ~known
    colors = colors.copy()
    colors[todo] = 128
    if not todo.any() or not known.any():
        return colors
    acc = colors.astype(np.float64) * known[..., None]
    for _ in range(rounds):
        idx = np.argwhere(todo)
        if len(idx) == 0:
            break
        s = np.zeros((len(idx), 3))
        n = np.zeros(len(idx))
        for off in np.argwhere(np.ones((3, 3, 3), bool)) - 1:
            q = idx + off
            ok = np.all((q >= 0) & (q < occ.shape), axis=1)
            qq = q[ok]
            hit = known[qq[:, 0], qq[:, 1], qq[:, 2]]
            rows = np.flatnonzero(ok)[hit]
            s[rows] += acc[qq[hit, 0], qq[hit, 1], qq[hit, 2]]
            n[rows] += 1
        got = n > 0
        if not got.any():
            break
        sel = idx[got]
        mean = s[got] / n[got, None]
        colors[sel[:, 0], sel[:, 1], sel[:, 2]] = np.rint(mean).astype(np.uint8)
        acc[sel[:, 0], sel[:, 1], sel[:, 2]] = mean
        known[sel[:, 0], sel[:, 1], sel[:, 2]] = True
        todo[sel[:, 0], sel[:, 1], sel[:, 2]] = False
    return colors


# ---------------------------------------------------------------- entry point
def check_inputs(volume: VoxelGrid, images, masks, cameras: Cameras, params: CarveParams, node: str):
    """Host arrays (occupancy uint8 0/1, images, masks) or a NodeError naming the problem."""
    occ = np.asarray(volume.occupancy)
    if occ.ndim != 3 or min(occ.shape) < 1:
        raise NodeError(f"{node}: volume occupancy must be a non-empty 3-D array, got shape {occ.shape}")
    if max(occ.shape) > 1024 or occ.size >= 2**31:
        raise NodeError(f"{node}: volume {occ.shape} is too large (at most 1024 voxels per side)")
    occ = (occ > 0.5 if occ.dtype.kind == "f" else occ > 0).astype(np.uint8)
    vs = volume.voxel_size
    if not (np.all(np.isfinite(vs)) and np.all(vs > 0) and np.all(np.isfinite(volume.bbox_min))):
        raise NodeError(f"{node}: volume box {volume.bbox_min.tolist()} .. {volume.bbox_max.tolist()} must be finite with max > min")
    if images is None or masks is None or cameras is None:
        raise NodeError(f"{node}: needs the 'images', 'masks' and 'cameras' inputs")
    ims = [np.asarray(im) for im in images.images]
    for im, cam in zip(ims, cameras):
        if im.dtype != np.uint8 or im.ndim != 3 or im.shape[2] != 3:
            raise NodeError(f"{node}: image of camera '{cam.name}' must be an (H, W, 3) uint8 array, got {im.dtype} {im.shape}")
    check_sizes(ims, cameras, node, "image")
    mks = check_masks(masks, cameras, node)
    if params.space not in SPACES:
        raise NodeError(f"{node}: space must be one of {', '.join(SPACES)}, got {params.space!r}")
    if params.min_views > len(cameras):
        raise NodeError(f"{node}: min_views {params.min_views} is more than the {len(cameras)} cameras")
    return occ, ims, mks


@dataclass
class CarveResult:
    volume: VoxelGrid
    stats: dict


def carve(volume: VoxelGrid, images, masks, cameras: Cameras, params: CarveParams | None = None,
          algorithm: str = "space_carving", method: str = "opencl", node: str | None = None,
          measure_input: bool = False) -> CarveResult:
    """Carve ``volume`` (the visual hull) to its photo hull: algorithm "space_carving" or "voxel_coloring";
    method "opencl" or "numpy" (the reference; small grids only). Returns the coloured volume and stats
    (voxels before/after, passes, colour variance over views of the surface voxels after, and before when
    ``measure_input``: one more item-buffer pass)."""
    params = params or CarveParams()
    node = node or f"carve.{algorithm}"
    occ, ims, mks = check_inputs(volume, images, masks, cameras, params, node)
    t0 = time.perf_counter()
    vs = volume.voxel_size.astype(np.float32)
    views = make_views(ims, mks, cameras, volume.bbox_min, params.gain)
    grid = Grid(occ, vs, axis_lists(occ))
    if algorithm == "voxel_coloring":
        grid.lists["layers"] = layer_list(occ, vs, views.centres, node)
    if method == "opencl":
        backend = CarveCL.get()
    else:
        from .reference import CarveNumPy
        backend = CarveNumPy()
    backend.setup(grid, views, params)
    carver = Carver(backend, grid, params)
    var_before = carver.colours()[2] if measure_input else None
    t1 = time.perf_counter()
    if algorithm == "voxel_coloring":
        removed = carver.voxel_coloring()
    else:
        removed = carver.space_carving()
    out = backend.occupancy()
    parts = 0
    if params.largest and out.any():
        out, parts = largest_part(out)
        backend.set_occupancy(out)
    t2 = time.perf_counter()
    colors, seen, var_after = carver.colours()
    colors = fill_colours(out, colors, seen)
    stats = {
        "algorithm": algorithm, "voxels_in": int(occ.sum()), "voxels_out": int(out.sum()), "removed": removed,
        "fragments_dropped": parts,
        "passes": carver.log, "space": params.space, "threshold": params.threshold,
        "surface_voxels_seen_out": int(len(var_after)),
        "variance_out": float(var_after.mean()) if len(var_after) else 0.0,
        "seconds_carve": round(t2 - t1, 4), "seconds_total": round(time.perf_counter() - t0, 4),
    }
    if var_before is not None:
        stats["surface_voxels_seen_in"] = int(len(var_before))
        stats["variance_in"] = float(var_before.mean()) if len(var_before) else 0.0
    return CarveResult(VoxelGrid(out, volume.bbox_min, volume.bbox_max, colors), stats)
