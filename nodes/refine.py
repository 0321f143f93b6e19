"""Exact visual-hull surface from a marching-cubes mesh: vertices onto the hull, then edge splits where flat
triangles stray from it.

Liang & Wong, "Exact visual hull from marching cubes" (VISAPP 2008). Marching cubes on an occupancy grid
puts every vertex on an edge between two neighbouring voxel centres, one inside and one outside; the true
hull surface crosses that edge somewhere between them. Bisection along the edge, testing each point against
every silhouette, finds the crossing (kernels/refine.cl). Vertices whose edge disagrees with the point test
are searched for along their normal instead.

With every vertex on the hull, flat triangles between them still cut inside convex outlines and poke out of
concave ones (chord error). So each edge whose midpoint, moved onto the hull along the normal, shifts by more
than ``split_px`` pixels in some view is split there (nodes/subdivide.py, conforming), a few rounds.

Binary masks are read through their signed distance outline (``Silhouettes.distance_outline``): 0.5 + the
pixel distance to the other class, bilinear, inside at >= 0.5. Along straight runs it is the pixel edge, as
nearest-pixel lookup; at staircase steps it rounds the corners, a continuous surface for the bisections
(thu_wd_human at 128^3 after splits: 1766 mesh pixels outside the masks, 33911 mask pixels not covered;
nearest-pixel lookup: 2717 and 33577, with 21 % more vertices). The same point test fits vertices to the hull in ``relax``.

    views = Silhouettes.from_inputs(masks, cameras).distance_outline()
    test = HullTestCL(views)                                  # or HullTestNumPy(views): the NumPy reference
    v, on_edges, on_normals = refine_vertices(mesh.vertices, mesh.faces, volume, test)
    v, f = split_towards_hull(v, mesh.faces, test, cameras, reach=voxel, px=0.25, rounds=2)
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from nodegraph import CameraSet, Masks, Mesh, Node, NodeError, Param, Volume
from nodegraph.cameras import Cameras, project_packed_f32

POLICIES = ("carve", "ignore")   # views a point projects outside of: not inside, or no vote (as the hull node)
OUTLINES = ("distance", "pixels")  # how binary masks are read: signed distance outline or nearest pixel
IN, BACKGROUND, UNSEEN = 1, 2, 3


# ---------------------------------------------------------------- silhouettes
@dataclass
class Silhouettes:
    """Everything the point test reads: packed cameras, binary masks, optional soft alpha, the vote rule."""

    cams: np.ndarray                  # (N, 32) float32, Cameras.pack()
    masks: list[np.ndarray]           # uint8 (H, W), inside when > 127
    alpha: list[np.ndarray] | None    # float32 (H, W), inside when bilinear alpha >= 0.5; used when given
    min_views: int = 0
    policy: str = "carve"

    @classmethod
    def from_inputs(cls, masks, cameras: Cameras, min_views: int = 0, outside: str = "carve", use_alpha: bool = True,
                    node: str = "refine") -> "Silhouettes":
        """Check a MaskSet against the cameras (NodeError naming the camera) and pack both."""
        if masks is None or cameras is None:
            raise NodeError(f"{node}: needs both 'masks' and 'cameras' inputs")
        if len(masks.masks) != len(cameras):
            raise NodeError(f"{node}: {len(masks.masks)} masks for {len(cameras)} cameras")
        if min_views > len(cameras):
            raise NodeError(f"{node}: min_views {min_views} is more than the {len(cameras)} cameras")
        if outside not in POLICIES:
            raise NodeError(f"{node}: outside must be one of {', '.join(POLICIES)}, got {outside!r}")
        binary, soft = [], []
        use_alpha = use_alpha and masks.alpha is not None
        for i, cam in enumerate(cameras):
            m = np.asarray(masks.masks[i])
            if m.dtype != np.uint8 or m.ndim != 2:
                raise NodeError(f"{node}: mask of camera '{cam.name}' must be an (H, W) uint8 array, got {m.dtype} {m.shape}")
            if m.shape != (cam.height, cam.width):
                raise NodeError(f"{node}: mask of camera '{cam.name}' is {m.shape[1]}x{m.shape[0]} but the camera is "
                                f"{cam.width}x{cam.height}")
            binary.append(np.ascontiguousarray(m))
            if use_alpha:
                a = np.asarray(masks.alpha[i], dtype=np.float32)
                if a.shape != m.shape:
                    raise NodeError(f"{node}: alpha of camera '{cam.name}' is {a.shape[1]}x{a.shape[0]}, its mask {m.shape[1]}x{m.shape[0]}")
                if not np.all(np.isfinite(a)):
                    raise NodeError(f"{node}: alpha of camera '{cam.name}' contains NaN or infinity")
                soft.append(np.ascontiguousarray(a))
        return cls(cameras.pack(), binary, soft if use_alpha else None, min_views, outside)


    def distance_outline(self, sigma: float = 0.0) -> "Silhouettes":
        """Binary masks without alpha get alpha = 0.5 + signed pixel distance to the other class (positive
        inside; cv2.distanceTransform between pixel centres, minus half a pixel), Gaussian-blurred by
        ``sigma`` pixels when > 0 (a smoother outline through the staircase). Bilinear >= 0.5 is then the
        pixel edge along straight runs and a rounded corner at steps. Soft alpha is kept as is."""
        if self.alpha is not None:
            return self
        import cv2

        fields = []
        for m in self.masks:
            fg = (m > 127).astype(np.uint8)
            to_bg = cv2.distanceTransform(fg, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
            to_fg = cv2.distanceTransform(1 - fg, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
            d = np.where(fg > 0, to_bg - 0.5, 0.5 - to_fg).astype(np.float32)
            if sigma > 0:
                d = cv2.GaussianBlur(d, (0, 0), sigma)
            fields.append(d + np.float32(0.5))
        return Silhouettes(self.cams, self.masks, fields, self.min_views, self.policy)


# ---------------------------------------------------------------- NumPy reference
def view_states(points: np.ndarray, views: Silhouettes, v: int) -> np.ndarray:
    """Per point (N, 3 float32) in view ``v``: 1 inside the silhouette, 2 background, 3 unseen (behind the
    camera or outside the image). Float32 in the kernel's order."""
    c = views.cams[v]
    f = np.float32
    u, w, front = project_packed_f32(c, points)
    W, H = int(c[22]), int(c[23])
    with np.errstate(invalid="ignore"):
        seen = front & (u >= f(-0.5)) & (u < f(W) - f(0.5)) & (w >= f(-0.5)) & (w < f(H) - f(0.5))
    state = np.full(len(points), UNSEEN, np.uint8)
    u, w = u[seen], w[seen]
    if views.alpha is not None:
        a = views.alpha[v]
        fx0, fy0 = np.floor(u), np.floor(w)
        fx, fy = u - fx0, w - fy0
        x0, x1 = np.clip(fx0.astype(np.int64), 0, W - 1), np.clip(fx0.astype(np.int64) + 1, 0, W - 1)
        y0, y1 = np.clip(fy0.astype(np.int64), 0, H - 1), np.clip(fy0.astype(np.int64) + 1, 0, H - 1)
        top = (f(1) - fx) * a[y0, x0] + fx * a[y0, x1]
        bottom = (f(1) - fx) * a[y1, x0] + fx * a[y1, x1]
        inside = (f(1) - fy) * top + fy * bottom >= f(0.5)
    else:
        inside = views.masks[v][(w + f(0.5)).astype(np.int64), (u + f(0.5)).astype(np.int64)] > 127
    state[seen] = np.where(inside, IN, BACKGROUND)
    return state


def inside_hull(points: np.ndarray, views: Silhouettes) -> np.ndarray:
    """Boolean per point: inside the visual hull under the vote rule (see kernels/refine.cl)."""
    points = np.asarray(points, np.float32).reshape(-1, 3)
    n_in = np.zeros(len(points), np.int32)
    n_bg = np.zeros(len(points), np.int32)
    for v in range(len(views.cams)):
        s = view_states(points, views, v)
        n_in += s == IN
        n_bg += s == BACKGROUND
    if views.min_views > 0:
        return n_in >= views.min_views
    if views.policy == "carve":
        return n_in == len(views.cams)
    return (n_bg == 0) & (n_in > 0)


def _bisect(a: np.ndarray, b: np.ndarray, views: Silhouettes, steps: int) -> tuple[np.ndarray, np.ndarray]:
    f = np.float32
    lo = np.zeros(len(a), f)
    hi = np.ones(len(a), f)
    d = b - a
    for _ in range(steps):
        t = f(0.5) * (lo + hi)
        ins = inside_hull(a + t[:, None] * d, views)
        lo = np.where(ins, t, lo)
        hi = np.where(ins, hi, t)
    return lo, hi


def exit_reference(a, b, views: Silhouettes, steps: int) -> np.ndarray:
    """Where each segment a[i] (inside) -> b[i] (outside) leaves the hull: middle of the last bisection interval."""
    a, b = np.asarray(a, np.float32), np.asarray(b, np.float32)
    lo, hi = _bisect(a, b, views, steps)
    t = np.float32(0.5) * (lo + hi)
    return a + t[:, None] * (b - a)


def clamp_reference(a, b, views: Silhouettes, steps: int, dirs=None, reach: float = 0.0) -> np.ndarray:
    """Move from a[i] towards b[i]; where b[i] is outside the hull, go back to the last point found inside:
    along -dirs[i] from c = b[i] - reach * dirs[i] when reach > 0 and c is inside, else along the move."""
    a, b = np.asarray(a, np.float32), np.asarray(b, np.float32)
    out = b.copy()
    bad = np.flatnonzero(~inside_hull(b, views))
    if len(bad):
        start = a[bad]
        if reach > 0:
            c = b[bad] - np.float32(reach) * np.asarray(dirs, np.float32)[bad]
            start = np.where(inside_hull(c, views)[:, None], c, start)
        lo, _ = _bisect(start, b[bad], views, steps)
        out[bad] = start + lo[:, None] * (b[bad] - start)
    return out


# ---------------------------------------------------------------- OpenCL
class HullTestCL:
    """The silhouettes on the device and the kernels of kernels/refine.cl (point test, exit, clamp)."""

    def __init__(self, views: Silhouettes):
        from nodegraph import clrt

        self.ctx, self.queue = clrt.context()
        self.views = views
        sizes = [m.size for m in views.masks]
        mask_off = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int32)
        self.d_cams = clrt.to_device(views.cams)
        self.d_masks = clrt.to_device(np.concatenate([m.ravel() for m in views.masks]))
        self.d_mask_off = clrt.to_device(mask_off)
        if views.alpha is not None:
            self.d_alpha = clrt.to_device(np.concatenate([a.ravel() for a in views.alpha]).astype(np.float32))
            self.d_alpha_off = self.d_mask_off
        else:
            self.d_alpha = clrt.to_device(np.zeros(1, np.float32))
            self.d_alpha_off = clrt.to_device(np.zeros(len(sizes), np.int32))
        self.kernels = {k: clrt.kernel("refine.cl", k) for k in ("hull_exit", "hull_clamp", "hull_inside")}

    def hull_args(self) -> tuple:
        v = self.views
        return (self.d_cams, np.int32(len(v.cams)), self.d_masks, self.d_mask_off, self.d_alpha, self.d_alpha_off,
                np.int32(v.alpha is not None), np.int32(v.min_views), np.int32(POLICIES.index(v.policy)))

    def enqueue_exit(self, d_a, d_b, n: int, steps: int, d_out):
        """Enqueue ``hull_exit`` on device buffers of n float3 points (no copies)."""
        import pyopencl as cl

        k = self.kernels["hull_exit"]
        k.set_args(d_a, d_b, np.int32(n), np.int32(steps), *self.hull_args(), d_out)
        cl.enqueue_nd_range_kernel(self.queue, k, (-(-n // 64) * 64,), None)

    def enqueue_clamp(self, d_a, d_b, d_dirs, reach: float, n: int, steps: int, d_out):
        """Enqueue ``hull_clamp`` on device buffers of n float3 points (no copies)."""
        import pyopencl as cl

        k = self.kernels["hull_clamp"]
        k.set_args(d_a, d_b, d_dirs, np.float32(reach), np.int32(n), np.int32(steps), *self.hull_args(), d_out)
        cl.enqueue_nd_range_kernel(self.queue, k, (-(-n // 64) * 64,), None)

    def _run(self, arrays: list, enqueue) -> np.ndarray:
        import pyopencl as cl

        from nodegraph import clrt

        arrays = [np.ascontiguousarray(x, np.float32).reshape(-1, 3) for x in arrays]
        out = np.empty_like(arrays[0])
        if len(out) == 0:
            return out
        d_out = cl.Buffer(self.ctx, cl.mem_flags.WRITE_ONLY, out.nbytes)
        bufs = [clrt.to_device(x) for x in arrays]  # kept alive until the copy below has finished
        enqueue(*bufs, d_out)
        cl.enqueue_copy(self.queue, out, d_out, is_blocking=True)
        return out

    def exit(self, a, b, steps: int) -> np.ndarray:
        """As ``exit_reference``."""
        n = len(np.asarray(a).reshape(-1, 3))
        return self._run([a, b], lambda da, db, do: self.enqueue_exit(da, db, n, steps, do))

    def clamp(self, a, b, steps: int, dirs=None, reach: float = 0.0) -> np.ndarray:
        """As ``clamp_reference``."""
        n = len(np.asarray(a).reshape(-1, 3))
        dirs = np.zeros((n, 3), np.float32) if dirs is None else dirs
        return self._run([a, b, dirs], lambda da, db, dd, do: self.enqueue_clamp(da, db, dd, reach, n, steps, do))

    def inside(self, points) -> np.ndarray:
        """Boolean per point, as ``inside_hull``."""
        import pyopencl as cl

        from nodegraph import clrt

        p = np.ascontiguousarray(points, np.float32).reshape(-1, 3)
        out = np.zeros(len(p), np.uint8)
        if len(p) == 0:
            return out.astype(bool)
        d_out = cl.Buffer(self.ctx, cl.mem_flags.WRITE_ONLY, out.nbytes)
        k = self.kernels["hull_inside"]
        d_p = clrt.to_device(p)  # kept alive until the copy below has finished
        k.set_args(d_p, np.int32(len(p)), *self.hull_args(), d_out)
        cl.enqueue_nd_range_kernel(self.queue, k, (-(-len(p) // 64) * 64,), None)
        cl.enqueue_copy(self.queue, out, d_out, is_blocking=True)
        return out.astype(bool)


# ---------------------------------------------------------------- lattice edges
def lattice_edges(vertices: np.ndarray, volume) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The voxel-centre edge each vertex lies on: (inside end (V, 3), outside end (V, 3), ok (V,) bool).

    In voxel-centre lattice units g = (x - bbox_min) / voxel_size - 0.5 a marching-cubes vertex has two
    integer coordinates; the third (the one farthest from an integer) names the edge. ``ok`` is False where
    the vertex is not on an edge of this grid or both ends have the same occupancy (the vertex is kept)."""
    occ = np.asarray(volume.occupancy)
    occ = occ > 0.5 if occ.dtype.kind == "f" else occ > 0
    dims = np.array(occ.shape)
    g = (np.asarray(vertices, np.float64) - volume.bbox_min) / volume.voxel_size - 0.5
    frac = np.abs(g - np.round(g))
    axis = np.argmax(frac, axis=1)
    rows = np.arange(len(g))
    lo = np.round(g).astype(np.int64)
    lo[rows, axis] = np.floor(g[rows, axis]).astype(np.int64)
    hi = lo.copy()
    hi[rows, axis] += 1
    others = frac.copy()
    others[rows, axis] = 0
    ok = (others.max(axis=1, initial=0) < 1e-3) & np.all(lo >= 0, axis=1) & np.all(hi < dims, axis=1)
    lo_c, hi_c = np.clip(lo, 0, dims - 1), np.clip(hi, 0, dims - 1)
    occ_lo = occ[lo_c[:, 0], lo_c[:, 1], lo_c[:, 2]]
    occ_hi = occ[hi_c[:, 0], hi_c[:, 1], hi_c[:, 2]]
    ok &= occ_lo != occ_hi
    centre = lambda idx: volume.bbox_min + (idx + 0.5) * volume.voxel_size  # noqa: E731
    inside = np.where(occ_lo[:, None], centre(lo), centre(hi))
    outside = np.where(occ_lo[:, None], centre(hi), centre(lo))
    return inside, outside, ok


class HullTestNumPy:
    """The NumPy reference with HullTestCL's methods (inside, exit, clamp)."""

    def __init__(self, views: Silhouettes):
        self.views = views

    def inside(self, points) -> np.ndarray:
        return inside_hull(points, self.views)

    def exit(self, a, b, steps: int) -> np.ndarray:
        return exit_reference(a, b, self.views, steps)

    def clamp(self, a, b, steps: int, dirs=None, reach: float = 0.0) -> np.ndarray:
        return clamp_reference(a, b, self.views, steps, dirs, reach)


def hull_test(views: Silhouettes, method: str = "opencl"):
    """HullTestCL (method "opencl") or HullTestNumPy ("numpy") for ``views``."""
    return HullTestCL(views) if method == "opencl" else HullTestNumPy(views)


def onto_hull(points, directions, reach, test, steps: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Points moved along +-``directions`` (unit, outward) onto the hull boundary: an inside point searches
    out to ``reach`` (scalar or per point), an outside point back in as far. Returns (points, found);
    points with no boundary within reach stay where they are."""
    p = np.asarray(points, np.float32).reshape(-1, 3)
    step = np.broadcast_to(np.asarray(reach, np.float32).reshape(-1, 1), (len(p), 1)) * np.asarray(directions, np.float32)
    inside = test.inside(p)
    a = np.where(inside[:, None], p, p - step)
    b = np.where(inside[:, None], p + step, p)
    ends = test.inside(np.vstack([a, b]))
    found = ends[: len(p)] & ~ends[len(p):]
    out = p.copy()
    if found.any():
        out[found] = test.exit(a[found], b[found], steps)
    return out.astype(np.float64), found


def push_out(points, directions, reach, test, steps: int = 16) -> np.ndarray:
    """Inside points moved outwards along ``directions`` by up to ``reach`` (per point), stopping at the hull
    boundary; outside points and points with reach 0 stay."""
    p = np.asarray(points, np.float32).reshape(-1, 3)
    reach = np.asarray(reach, np.float32).reshape(-1)
    go = np.flatnonzero(reach > 0)
    go = go[test.inside(p[go])]
    b = p[go] + reach[go, None] * np.asarray(directions, np.float32)[go]
    stop = ~test.inside(b)
    out = p.copy()
    out[go[~stop]] = b[~stop]
    if stop.any():
        out[go[stop]] = test.clamp(p[go[stop]], b[stop], steps)
    return out.astype(np.float64)


def refine_vertices(vertices, faces, volume, test, steps: int = 16) -> tuple[np.ndarray, int, int]:
    """Vertices moved onto the hull boundary: along their grid edge where its inside end passes the point
    test and its outside end fails it, else along the vertex normal within one voxel.
    Returns (vertices, moved along edges, moved along normals); the rest stay."""
    vertices = np.asarray(vertices, np.float64)
    a, b, ok = lattice_edges(vertices, volume)
    ends = test.inside(np.vstack([a, b]))
    on_edge = ok & ends[: len(a)] & ~ends[len(a):]
    out = vertices.copy()
    out[on_edge] = test.exit(a[on_edge], b[on_edge], steps)
    rest = np.flatnonzero(~on_edge)
    found = np.zeros(0, bool)
    if len(rest):
        normals = trimesh.Trimesh(vertices, faces, process=False).vertex_normals[rest]
        out[rest], found = onto_hull(vertices[rest], normals, float(np.max(volume.voxel_size)), test, steps)
    return out, int(on_edge.sum()), int(found.sum())


def chord_shift(points, moved, cameras: Cameras) -> np.ndarray:
    """Largest image distance (pixels, over all views) between each point and its moved twin."""
    shift = np.zeros(len(points))
    for v in range(len(cameras)):
        shift = np.maximum(shift, np.linalg.norm(cameras.project(points, v)[0] - cameras.project(moved, v)[0], axis=1))
    return np.nan_to_num(shift, nan=np.inf)


def split_towards_hull(vertices, faces, test, cameras: Cameras, reach: float, px: float = 0.25, rounds: int = 2,
                       steps: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """``rounds`` of conforming edge splits: an edge whose midpoint, moved onto the hull along the mean normal
    of its ends (within ``reach``, halved every round), moves more than ``px`` pixels in some view is split
    at that hull point. Returns (vertices, faces)."""
    from .subdivide import split_edges, unique_edges

    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    for _ in range(rounds):
        edges, face_edges = unique_edges(f)
        normals = trimesh.Trimesh(v, f, process=False).vertex_normals
        mid = 0.5 * (v[edges[:, 0]] + v[edges[:, 1]])
        n = normals[edges[:, 0]] + normals[edges[:, 1]]
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        on_hull, found = onto_hull(mid, n, reach, test, steps)
        split = found & (chord_shift(mid, on_hull, cameras) > px)
        if not split.any():
            break
        v, f = split_edges(v, f, edges, face_edges, split, on_hull)
        reach /= 2
    return v, f


class Refine(Node):
    """Exact visual-hull surface (Liang & Wong 2008): every marching-cubes vertex moves along its grid edge to
    the point where the edge leaves the hull, found by bisection against every silhouette (sub-pixel: soft
    alpha, or the signed distance outline of binary masks); then edges whose chord strays more than
    split_px from the hull in some view are split onto it."""

    type_name = "refine"
    version = 2
    inputs = {"mesh": Mesh, "volume": Volume, "masks": Masks, "cameras": CameraSet}
    outputs = {"mesh": Mesh}
    params = {
        "steps": Param(int, 16, range=(1, 30), doc="bisection steps per edge (error: voxel / 2^steps)"),
        "split_rounds": Param(int, 2, range=(0, 6), doc="rounds of edge splits onto the hull; 0 = same topology as the input"),
        "split_px": Param(float, 0.25, range=(0.01, 100.0), doc="split an edge when its midpoint is off the hull by more than this, in pixels"),
        "outline": Param(str, "distance", choices=OUTLINES, doc="binary masks: signed distance outline (rounded steps), or nearest pixel"),
        "min_views": Param(int, 0, range=(0, None), doc="0 = all views; k = inside at least k silhouettes (as the hull)"),
        "outside": Param(str, "carve", choices=POLICIES, doc="points projecting outside an image: carve, or ignore that view"),
        "use_alpha": Param(bool, True, doc="test against soft alpha (bilinear, >= 0.5) when the masks carry it"),
        "method": Param(str, "opencl", choices=("opencl", "numpy"), doc="OpenCL kernel or the NumPy reference"),
    }
    kernels = ["refine.cl"]
    uses = ["nodes.subdivide"]

    def run(self, mesh, volume, masks, cameras, *, steps, split_rounds, split_px, outline, min_views, outside, use_alpha,
            method):
        views = Silhouettes.from_inputs(masks, cameras, min_views, outside, use_alpha, node="refine")
        if outline == "distance":
            views = views.distance_outline()
        test = hull_test(views, method)
        faces = np.asarray(mesh.faces)
        vertices, on_edge, on_normal = refine_vertices(mesh.vertices, faces, volume, test, steps)
        reach = float(np.max(volume.voxel_size))
        vertices, faces = split_towards_hull(vertices, faces, test, cameras, reach, split_px, split_rounds, steps)
        self.log.info("refine: %d of %d vertices onto the hull along grid edges, %d along normals; %d vertices after "
                      "splits", on_edge, len(mesh.vertices), on_normal, len(vertices))
        return {"mesh": trimesh.Trimesh(vertices, faces, process=False)}
