"""Marching cubes (Lorensen & Cline 1987) on an occupancy volume, as an indexed, watertight mesh.

One vertex per grid edge whose two samples lie on different sides of ``level`` (shared by the up to four
cells around the edge), triangles wound so that normals point out of the solid (from values above
``level`` towards values below). The volume is padded by one empty voxel on every side, so shapes that
touch the box still close.

The case table is built here from a face rule instead of being typed in: on each cube face the crossing
points are joined by segments, and where a face is ambiguous (two diagonal corners inside) the inside
corners are cut off separately. Both cubes sharing a face apply the same rule to the same four samples, so
their polygons meet edge to edge: the mesh is watertight. Each closed loop of segments is fanned into
triangles. The OpenCL kernels (kernels/mc.cl) walk the grid row by row along its contiguous axis in the
style of Flying Edges (Schroeder et al. 2015): a first pass finds each row's span of occupied samples, a
counting pass gives each row of cells its vertex and triangle counts, an exclusive prefix sum gives output
offsets, and the emitting pass walks only the span. The volume is read in place (the empty border is
handled in the kernels, not copied) and vertices and triangles come back in one read.
``marching_cubes_reference`` is the vectorised NumPy version of the same computation.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from kernels import source
from nodegraph import clrt

# corner c of a cell sits at offset (c & 1, c >> 1 & 1, c >> 2 & 1); edge e runs from EDGES[e][0] along axis
# EDGES[e][1] (to the corner with that bit set)
EDGES = [(c, a) for a in range(3) for c in range(8) if not c >> a & 1]


def _edge_of(c0: int, c1: int) -> int:
    lo, hi = min(c0, c1), max(c0, c1)
    return EDGES.index((lo, (hi ^ lo).bit_length() - 1))


def _face_segments(case: int, axis: int, side: int) -> list[tuple[int, int]]:
    """Oriented segments (edge, edge) on one cube face: the solid's outward surface normal, seen from
    outside the cube, keeps the inside corners on the right of each segment."""
    b, c = [a for a in range(3) if a != axis]
    ring = [(side << axis) | (u << b) | (v << c) for u, v in ((0, 0), (1, 0), (1, 1), (0, 1))]
    inside = [bool(case >> q & 1) for q in ring]
    cross = [i for i in range(4) if inside[i] != inside[(i + 1) % 4]]
    edge = lambda i: _edge_of(ring[i], ring[(i + 1) % 4])  # noqa: E731  ring edge i joins ring[i], ring[i+1]
    if not cross:
        return []
    if len(cross) == 2:
        pairs = [(cross[0], cross[1], [ring[i] for i in range(4) if inside[i]])]
    else:  # ambiguous face: cut each inside corner off on its own
        pairs = [((i - 1) % 4, i, [ring[i]]) for i in range(4) if inside[i]]
    out = []
    for ia, ib, corners in pairs:
        ea, eb = edge(ia), edge(ib)
        p, q = _midpoint(ea), _midpoint(eb)
        cs = [_corner_xyz(x) for x in corners]
        centre = [sum(c[k] for c in cs) / len(cs) for k in range(3)]
        # the solid's normal along ``axis`` (outward: +1 on side 1, -1 on side 0) against cross(q - p, centre - p),
        # whose ``axis`` component is all the dot product keeps (plain floats: 0.1 s of numpy calls at start-up)
        u, w = [q[k] - p[k] for k in range(3)], [centre[k] - p[k] for k in range(3)]
        i, j = (axis + 1) % 3, (axis + 2) % 3
        along = u[i] * w[j] - u[j] * w[i]
        out.append((ea, eb) if (along if side else -along) < 0 else (eb, ea))
    return out


def _corner_xyz(c: int) -> tuple[float, float, float]:
    return float(c & 1), float(c >> 1 & 1), float(c >> 2 & 1)


def _midpoint(e: int) -> list[float]:
    """The middle of edge ``e``: its first corner plus half a cell along its axis."""
    c, a = EDGES[e]
    return [x + (0.5 if k == a else 0.0) for k, x in enumerate(_corner_xyz(c))]


def _faces_of(e: int) -> set:
    c0, a = EDGES[e]
    return {(b, c0 >> b & 1) for b in range(3) if b != a}


def _triangulate(loop: list[int]) -> list[tuple[int, int, int]]:
    """Triangles of a closed loop of edges (kept winding) whose inner diagonals never run along a cube face:
    the neighbour across that face could draw the same diagonal, and the edge would have four triangles."""
    if len(loop) == 3:
        return [tuple(loop)]
    n = len(loop)
    for i in range(n):
        for j in range(i + 2, n - (i == 0)):
            if _faces_of(loop[i]) & _faces_of(loop[j]):
                continue
            left, right = _triangulate(loop[i:j + 1]), _triangulate(loop[j:] + loop[:i + 1])
            if left is not None and right is not None:
                return left + right
    return None


@lru_cache(maxsize=None)
def case_table() -> tuple[np.ndarray, np.ndarray]:
    """(triangle count per case (256,), edge triples per case (256, MAX, 3) padded with -1).
    Bit c of a case is set when corner c is inside (value > level)."""
    tris = []
    for case in range(256):
        nxt = {}
        for axis in range(3):
            for side in (0, 1):
                for ea, eb in _face_segments(case, axis, side):
                    nxt[ea] = eb
        loops, seen = [], set()
        for start in sorted(nxt):
            if start in seen:
                continue
            loop, e = [], start
            while e not in seen:
                seen.add(e)
                loop.append(e)
                e = nxt[e]
            loops.append(loop)
        tris.append([t for lp in loops for t in _triangulate(lp)])
    most = max(len(t) for t in tris)
    table = np.full((256, most, 3), -1, np.int8)
    for case, t in enumerate(tris):
        if t:
            table[case, : len(t)] = t
    return np.array([len(t) for t in tris], np.int32), table


def padded(volume) -> np.ndarray:
    """The occupancy with one empty voxel around it (uint8 stays uint8, anything else becomes float32)."""
    occ = volume.occupancy
    if occ.dtype != np.uint8:
        occ = occ.astype(np.float32)
    return np.pad(occ, 1)


# ---------------------------------------------------------------- NumPy reference
def marching_cubes_reference(volume, level: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised NumPy marching cubes: (vertices (N, 3) float32 world, faces (M, 3) int64)."""
    f = np.float32
    P = padded(volume).astype(f)
    inside = P > f(level)
    N = np.array(P.shape)
    bmin, vs = volume.bbox_min.astype(f), volume.voxel_size.astype(f)
    # one vertex per crossing edge, numbered by (point, axis)
    vid = np.full(P.size * 3, -1, np.int64)
    verts = []
    count = 0
    keys = []
    for a in range(3):
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[a], hi[a] = slice(0, -1), slice(1, None)
        crossing = np.zeros(P.shape, bool)
        crossing[tuple(lo)] = inside[tuple(lo)] != inside[tuple(hi)]
        pts = np.argwhere(crossing)
        keys.append(np.ravel_multi_index(pts.T, P.shape) * 3 + a)
        v0 = P[tuple(pts.T)]
        step = pts.copy()
        step[:, a] += 1
        v1 = P[tuple(step.T)]
        t = (f(level) - v0) / (v1 - v0)
        pos = bmin + (pts.astype(f) - f(0.5)) * vs
        pos[:, a] = pos[:, a] + t * vs[a]
        verts.append(pos)
    keys = np.concatenate(keys)
    order = np.argsort(keys)
    vid[keys[order]] = np.arange(len(keys))
    verts = np.concatenate(verts)[order]
    count = len(keys)
    # cells and their cases
    cells = np.argwhere(np.ones(N - 1, bool))
    case = np.zeros(len(cells), np.int64)
    for c in range(8):
        off = np.array([c & 1, c >> 1 & 1, c >> 2 & 1])
        case |= inside[tuple((cells + off).T)].astype(np.int64) << c
    ntri, table = case_table()
    active = ntri[case] > 0
    cells, case = cells[active], case[active]
    edges = table[case].reshape(len(cells), 3 * table.shape[1])  # (cells, MAX*3)
    cell_idx, slot = np.nonzero(edges >= 0)
    e = edges[cell_idx, slot]
    e_corner = np.array([EDGES[i][0] for i in range(12)])
    e_axis = np.array([EDGES[i][1] for i in range(12)])
    corner_off = np.array([[c & 1, c >> 1 & 1, c >> 2 & 1] for c in range(8)])
    pts = cells[cell_idx] + corner_off[e_corner[e]]
    faces = vid[np.ravel_multi_index(pts.T, P.shape) * 3 + e_axis[e]].reshape(-1, 3)
    assert count == 0 or faces.min() >= 0
    return verts, faces


# ---------------------------------------------------------------- OpenCL
class MarchingCubesCL(clrt.Runner):
    """Kernels, case tables and work buffers on the device (one per process; buffers grow and are reused)."""

    source = source("mc.cl")
    GROUP = 32  # work-items per group along j: PoCL runs odd global sizes as tiny groups

    def __init__(self):
        super().__init__()
        ntri, table = case_table()
        self.ntri = clrt.to_device(ntri)
        self.table = clrt.to_device(table.astype(np.int8).reshape(256, -1))
        self.max_tris = table.shape[1]
        self.host_arrays: dict[str, np.ndarray] = {}

    def voxel_options(self, voxel: str) -> tuple[str, ...]:
        return (f"-DVOXEL={voxel}", f"-DMAX_TRIS={self.max_tris}") + (("-DVOXEL_UCHAR",) if voxel == "uchar" else ())

    def scratch(self, name: str, shape: tuple, dtype) -> np.ndarray:
        """A host array of this shape, kept between calls."""
        arr = self.host_arrays.get(name)
        if arr is None or arr.shape != shape or arr.dtype != dtype:
            arr = self.host_arrays[name] = np.empty(shape, dtype)
        return arr

    def run(self, volume, level: float) -> tuple[np.ndarray, np.ndarray]:
        occ = volume.occupancy
        if occ.dtype == np.uint8:
            voxel = "uchar"
            if not 0 <= level < 255:  # every sample (the border's 0 too) on the same side: no surface
                return np.empty((0, 3), np.float32), np.empty((0, 3), np.int32)
        else:
            voxel, occ = "float", occ.astype(np.float32, copy=False)
        occ = np.ascontiguousarray(occ)
        opts = self.voxel_options(voxel)
        nx, ny, nz = occ.shape
        rows = (nx + 1) * (ny + 1)  # cell rows of the padded grid
        dims = (np.int32(nx), np.int32(ny), np.int32(nz), np.float32(level), np.int32(0 > level))
        vol = self.host(occ)  # no copy on CPUs
        spans = self.buffer("spans", nx * ny * 8)
        cbuf = self.buffer("counts", 3 * rows * 4)
        g = self.GROUP
        self.launch("mc_spans", (ny, nx), (g, 1), vol, *dims, spans, options=opts)
        self.launch("mc_count", (ny + 1, nx + 1), (g, 1), vol, *dims, spans, self.ntri, cbuf, options=opts)
        counts = self.read(cbuf, (3, rows), np.int32, out=self.scratch("counts", (3, rows), np.int32))
        offsets = self.scratch("offsets", (3, rows + 1), np.int32)  # exclusive prefix sums, totals last
        offsets[:2, 0] = 0
        np.cumsum(counts[:2], axis=1, out=offsets[:2, 1:])
        offsets[2, :rows] = counts[2]
        nv, nt = int(offsets[0, rows]), int(offsets[1, rows])
        out = np.empty(3 * (nv + nt), np.float32)
        if nt:
            obuf = self.upload("offsets", offsets)
            outbuf = self.buffer("out", out.nbytes)
            f4 = lambda a: np.array([*np.asarray(a, np.float32), 0], np.float32)  # noqa: E731
            self.launch("mc_emit", (ny + 1, nx + 1), (g, 1), vol, *dims, spans, self.ntri, self.table, obuf,
                        f4(volume.bbox_min), f4(volume.voxel_size), outbuf, options=opts)
            self.read(outbuf, out.shape, np.float32, out=out)
        return out[: 3 * nv].reshape(nv, 3), out[3 * nv:].view(np.int32).reshape(nt, 3)


def marching_cubes(volume, level: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """OpenCL marching cubes of a VoxelGrid: (vertices (N, 3) float32 world, faces (M, 3) int32)."""
    return MarchingCubesCL.get().run(volume, level)


# ---------------------------------------------------------------- vertex colours
def vertex_colors(volume, vertices: np.ndarray, level: float = 0.5) -> np.ndarray:
    """(N, 4) uint8 RGBA per vertex from ``volume.colors``: the colour of the nearest voxel inside the surface
    (occupancy > level) among the 8 around the vertex, i.e. the inside end of the grid edge it lies on."""
    occ = volume.occupancy
    g = (np.asarray(vertices, np.float64) - volume.bbox_min) / volume.voxel_size - 0.5
    base = np.floor(g).astype(np.int64)
    best = np.full(len(g), np.inf)
    pick = np.zeros((len(g), 3), np.int64)
    dims = np.array(occ.shape[:3])
    for c in range(8):
        q = base + np.array([c & 1, c >> 1 & 1, c >> 2 & 1])
        ok = np.all((q >= 0) & (q < dims), axis=1)
        qc = np.clip(q, 0, dims - 1)
        ok &= occ[qc[:, 0], qc[:, 1], qc[:, 2]] > level
        d = np.where(ok, ((g - q) ** 2).sum(axis=1), np.inf)
        better = d < best
        best[better], pick[better] = d[better], q[better]
    rgb = np.asarray(volume.colors)[pick[:, 0], pick[:, 1], pick[:, 2]]
    return np.concatenate([rgb, np.full((len(g), 1), 255, np.uint8)], axis=1).astype(np.uint8)
