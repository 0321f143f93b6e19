"""Non-rigid registration of a mesh onto a target surface: an embedded deformation graph (Sumner, Schmid &
Pauly 2007) regularised as-rigid-as-possible between graph nodes, fitted by non-rigid ICP with point-to-plane
data terms in both directions (source -> target and target -> source) and an optional silhouette term, then a
per-vertex normal displacement that brings the surface detail onto the target.

Graph: nodes are surface vertices at least ``spacing`` apart along the mesh (geodesic Poisson-disk sampling),
each vertex is driven by up to ``k`` nodes of its geodesic neighbourhood (its own Voronoi cell's node and that
node's neighbours), with Sumner's weights (1 - d / d_max)^2; two nodes are neighbours when their cells share a
mesh edge, so touching but unconnected limbs never pull on each other. A node j carries a rotation R_j and a
translation t_j; a vertex moves to

    x_i = sum_j w_ij (R_j (v_i - g_j) + g_j + t_j)

Fit (one ICP iteration): correspondences by nearest neighbours (rejected beyond a distance or when normals
disagree), then with the rotations fixed every term is linear in the translations t (3N unknowns):

    E(t) = w_data sum_s rho (n_c . (x_s - c_s))^2 + w_point sum_s |x_s - c_s|^2           source -> target
         + w_data sum_q rho (n_q . (x_i(q) - q))^2                                       target -> source
         + w_sil  sum_(i, view) (g^ . (x_i - x_i0) - d_i)^2   (vertices outside a silhouette, pushed back in)
                                  (only within silhouette_reach of the outline: a limb far outside has moved,
                                   and pulling it to the nearest outline crushes it onto the body)
         + w_arap sum_(j, k) |(g_k + t_k) - (g_j + t_j) - R_j (g_k - g_j)|^2

solved by a sparse Cholesky factorisation (CHOLMOD's supernodal one where cvxopt is installed, else SuperLU in a
minimum-degree order; its order found once per keyframe: nodes/common/cholesky.py) of the 3N x 3N normal equations; the rotations then follow from the ARAP local step
(Procrustes per node, on the OpenCL device: kernels/rotations.cl). Everything is computed in voxel units (coordinates divided by ``voxel``), so
the weights are dimensionless. Nearest vertices and closest points on a surface (the matches, the detail, the
snap, the unfold, the residuals) are searched on the OpenCL device (kernels/closest.cl): ``PointGrid`` and
``SurfaceQuery`` in nodes/common/closest.py (each checked against its NumPy reference by a test).

    graph = build_graph(vertices, faces, spacing=4.0 * voxel)
    reg = Registration(graph, faces, FitParams())
    state = GraphState.identity(graph)
    target = Target(t_vertices, t_faces, origin, voxel)
    state, info = reg.fit(state, target)
    x = detail(graph.deform(state), faces, target, reg.params)
    x = snap(x, faces, target, reg.params)                      # onto the target surface
    x = unfold(x, faces, edge_face_pairs(faces), ring_operator(faces, len(x)), 8, target)   # folds opened
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kernels import source
from nodegraph import clrt
from nodes.common.cholesky import SparseCholesky
from nodes.common.closest import PointGrid, SurfaceQuery, used_vertices
from nodes.common.meshops import (edge_length_graph, face_normals, folded_edges, neighbour_mean, ring_degree,
                                  ring_operator, row_norms, vertex_normals)


# ---------------------------------------------------------------- deformation graph
@dataclass
class DeformationGraph:
    rest: np.ndarray          # (V, 3) rest vertices (voxel units)
    nodes: np.ndarray         # (N, 3) node rest positions g_j
    node_vertex: np.ndarray   # (N,) vertex index of each node
    edges: np.ndarray         # (E, 2) undirected node pairs j < k
    vertex_nodes: np.ndarray  # (V, K) node indices
    vertex_weights: np.ndarray  # (V, K) weights, rows sum to 1 (0 for padding)

    def __post_init__(self):
        from scipy.sparse import coo_matrix

        v, k = self.vertex_nodes.shape
        self.offsets = self.rest[:, None, :] - self.nodes[self.vertex_nodes]   # (V, K, 3)
        self.W = coo_matrix((self.vertex_weights.ravel(), (np.repeat(np.arange(v), k), self.vertex_nodes.ravel())),
                            shape=(v, len(self.nodes))).tocsr()
        both = np.r_[self.edges, self.edges[:, ::-1]]
        self.directed = both                                                    # (2E, 2): (j, k)
        # the ARAP local step's covariances S_j = sum_k e_jk (e_jk + t_k - t_j)^T (e_jk = g_k - g_j) are linear in
        # t: S = cov_rest + cov_map @ t, both built once (one sparse product per step instead of a scatter)
        j, kk = both[:, 0], both[:, 1]
        n = len(self.nodes)
        self.rest_edges = self.nodes[kk] - self.nodes[j]                        # (2E, 3)
        cov_rest = np.zeros((n, 9))
        outer = (self.rest_edges[:, :, None] * self.rest_edges[:, None, :]).reshape(-1, 9)
        for c in range(9):
            cov_rest[:, c] = np.bincount(j, outer[:, c], minlength=n)
        self.cov_rest = cov_rest.reshape(n, 3, 3) + np.eye(3) * 1e-9
        a, b = np.divmod(np.arange(9), 3)                                        # entry (a, b) of S_j
        rows = np.broadcast_to(j[:, None] * 9 + np.arange(9), (len(j), 9))
        vals = self.rest_edges[:, a]                                             # e_a, times (t_k - t_j)_b
        self.cov_map = coo_matrix((np.r_[vals.ravel(), -vals.ravel()],
                                   (np.r_[rows.ravel(), rows.ravel()],
                                    np.r_[(kk[:, None] * 3 + b).ravel(), (j[:, None] * 3 + b).ravel()])),
                                  shape=(9 * n, 3 * n)).tocsr()

    def rotated_part(self, R: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """p_i = sum_j w_ij (R_j (v_i - g_j) + g_j): vertex positions without the node translations."""
        idx = self.vertex_nodes if rows is None else self.vertex_nodes[rows]
        w = self.vertex_weights if rows is None else self.vertex_weights[rows]
        off = self.offsets if rows is None else self.offsets[rows]
        moved = np.einsum("vkab,vkb->vka", R[idx], off) + self.nodes[idx]
        return np.einsum("vk,vka->va", w, moved)

    def blend_map(self, vectors: np.ndarray):
        """The sparse (3V, 9N) map M with (M @ vec(R))_i = sum_j w_ij R_j y_i for per-vertex vectors y (V, 3):
        one sparse product per frame instead of gathering every vertex's node rotations (a (V, K, 3, 3) array)."""
        from scipy.sparse import csr_matrix

        v, k = self.vertex_nodes.shape
        a3 = np.arange(3)
        # row 3 i + a holds, per node slot and b, column 9 j + 3 a + b with w_ij y_ib: laid out row by row (no sort)
        cols = self.vertex_nodes[:, None, :, None] * 9 + a3[None, :, None, None] * 3 + a3[None, None, None, :]
        y = np.asarray(vectors, np.float64).reshape(v, -1, 3)
        vals = np.broadcast_to((self.vertex_weights[:, :, None] * y)[:, None, :, :], (v, 3, k, 3))
        return csr_matrix((vals.ravel(), cols.ravel(), np.arange(0, 9 * k * v + 1, 3 * k)), shape=(3 * v, 9 * len(self.nodes)))

    def deform(self, state: "GraphState", rows: np.ndarray | None = None) -> np.ndarray:
        if rows is not None:
            return self.rotated_part(state.R, rows) + self.W[rows] @ state.t
        if getattr(self, "_deform_map", None) is None:          # x = M vec(R) + sum_j w_ij g_j + W t, M built once
            self._deform_map = self.blend_map(self.offsets)
            self._deform_base = self.W @ self.nodes
        return (self._deform_map @ state.R.reshape(-1)).reshape(-1, 3) + self._deform_base + self.W @ state.t


@dataclass
class GraphState:
    R: np.ndarray   # (N, 3, 3)
    t: np.ndarray   # (N, 3)

    @classmethod
    def identity(cls, graph: DeformationGraph) -> "GraphState":
        n = len(graph.nodes)
        return cls(np.repeat(np.eye(3)[None], n, axis=0), np.zeros((n, 3)))

    def copy(self) -> "GraphState":
        return GraphState(self.R.copy(), self.t.copy())


def sample_nodes(vertices: np.ndarray, faces: np.ndarray, spacing: float, seed: int = 0) -> np.ndarray:
    """Vertex indices at least ``spacing`` apart along the mesh edges (geodesic Poisson-disk, greedy in a
    fixed random order); every used vertex lies within ``spacing`` of one."""
    from scipy.sparse.csgraph import dijkstra

    graph, _ = edge_length_graph(vertices, faces)
    used = np.zeros(len(vertices), bool)
    used[np.asarray(faces).ravel()] = True
    covered = ~used
    order = np.random.default_rng(seed).permutation(len(vertices))
    picks = []
    # the searches of the next ``batch`` candidates still uncovered run in one call (directed: the edge graph holds
    # both directions already; undirected, scipy symmetrises it on every call, 3x the time), then are taken in
    # order as one at a time would: a candidate an earlier one of its batch covered is skipped (its search
    # wasted, a few %), so the picks are exactly the sequential greedy's
    batch = 16
    pos = 0
    while pos < len(order):
        rest = order[pos:]
        pending = np.flatnonzero(~covered[rest])[:batch]
        if len(pending) == 0:
            break
        d = dijkstra(graph, directed=True, indices=rest[pending], limit=spacing)
        for row, i in zip(d, rest[pending]):
            if covered[i]:
                continue
            picks.append(i)
            covered |= np.isfinite(row)
        pos += int(pending[-1]) + 1
    return np.array(picks, np.int64)


def build_graph(vertices, faces, spacing: float, k: int = 4, seed: int = 0) -> DeformationGraph:
    """The embedded deformation graph of a mesh (see the module docstring); ``spacing`` in the vertices' units."""
    from scipy.sparse.csgraph import dijkstra

    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    nodes = sample_nodes(vertices, faces, spacing, seed)
    graph, _ = edge_length_graph(vertices, faces)
    _, _, source = dijkstra(graph, directed=True, indices=nodes, min_only=True, return_predecessors=True)   # symmetric
    node_of = np.full(len(nodes) and int(nodes.max()) + 1, -1, np.int64)
    node_of[nodes] = np.arange(len(nodes))
    cell = np.where(source >= 0, node_of[np.maximum(source, 0)], -1)           # Voronoi cell per vertex
    # unused vertices (no faces): the Euclidean nearest node
    lost = cell < 0
    if lost.any():
        from scipy.spatial import cKDTree

        cell[lost] = cKDTree(vertices[nodes]).query(vertices[lost])[1]
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    ce = np.sort(cell[e], axis=1)
    ce = np.unique(ce[ce[:, 0] != ce[:, 1]], axis=0)
    n = len(nodes)
    # candidate nodes per vertex: its cell's node and that node's neighbours
    nbr = [[j] for j in range(n)]
    for a, b in ce:
        nbr[a].append(b)
        nbr[b].append(a)
    width = max(len(x) for x in nbr)
    table = np.full((n, width), -1, np.int64)
    for j, x in enumerate(nbr):
        table[j, : len(x)] = x
    cand = table[cell]                                                          # (V, width)
    d = np.linalg.norm(vertices[:, None, :] - vertices[nodes][np.maximum(cand, 0)], axis=2)
    d[cand < 0] = np.inf
    order = np.argsort(d, axis=1, kind="stable")[:, : k + 1]
    rows = np.arange(len(vertices))[:, None]
    dk = d[rows, order]
    idx = cand[rows, order]
    kk = min(k, dk.shape[1])
    dmax = dk[:, kk] if dk.shape[1] > kk else np.full(len(vertices), np.inf)
    dmax = np.where(np.isfinite(dmax), dmax, dk[:, :kk].max(axis=1, initial=0) * 1.5 + 1e-9)
    with np.errstate(invalid="ignore"):
        w = np.clip(1 - dk[:, :kk] / dmax[:, None], 0, None) ** 2
    w[~np.isfinite(w)] = 0
    idx = idx[:, :kk]
    w[:, 0] = np.where(w.sum(axis=1) <= 0, 1.0, w[:, 0])                      # a vertex at its own node only
    w /= w.sum(axis=1, keepdims=True)
    idx = np.where(idx < 0, idx[:, :1], idx)
    return DeformationGraph(vertices, vertices[nodes], nodes, ce, idx, w)


# ---------------------------------------------------------------- target and parameters
class Target:
    """A frame's reconstruction in voxel units, with its nearest-point query; optional silhouettes for the
    silhouette term (``views``: nodes.common.silhouettes.Silhouettes with a distance outline)."""

    def __init__(self, vertices, faces, origin: np.ndarray, voxel: float, views=None):
        self.origin = np.asarray(origin, np.float64)
        self.voxel = float(voxel)
        self.vertices = (np.asarray(vertices, np.float64) - self.origin) / self.voxel
        self.faces = np.asarray(faces, np.int64)
        self.query = SurfaceQuery(self.vertices, self.faces)
        self.normals = self.query.normals
        self.views = views

    def world(self, x: np.ndarray) -> np.ndarray:
        return x * self.voxel + self.origin


@dataclass
class FitParams:
    iterations: int = 6           # ICP iterations per frame (the schedule below spans them; fast motion: 15)
    inner: int = 4                # local/global ARAP steps per ICP iteration (one factorisation)
    arap: float = 1.0             # ARAP weight at the last iteration (relative to the data terms)
    arap_start: float = 4.0       # ... at the first (the stiffness is relaxed geometrically)
    point: float = 0.1            # point-to-point share of the source -> target term
    coverage: float = 6.0         # weight of the target -> source term (every part of the target reached)
    silhouette: float = 4.0       # silhouette term weight (0: off)
    silhouette_reach: float = 2.0  # only points at most this far (voxels) outside a silhouette are pulled in
    reject: float = 15.0          # correspondences farther than this (voxels) at the first iteration ...
    reject_end: float = 2.5       # ... shrinking to this at the last
    normal_cos: float = 0.3       # correspondences whose normals differ by more (cosine below) are rejected
    robust: float = 1.5           # Geman-McClure scale (voxels) of the point-to-plane residuals at the last
                                  # iteration (earlier: larger, in proportion to the rejection distance)
    samples: int = 6000           # source vertices and target vertices sampled for the graph fit
    detail: float = 2.0           # rings of neighbours the normal displacement is smoothed over (0: no detail step)
    detail_reach: float = 4.0     # largest normal displacement (voxels)
    detail_out: float = 1.0       # largest outward one (voxels): at a contact the reconstruction is one blob, and
                                  # pushing the surfaces that face each other out onto it slid them over the body
    snap: int = 3                 # rounds of closest-point projection onto the target after the detail step (0: none)
    unfold: int = 8               # rounds of opening folds after the snap, back on the target (0: none)
    snap_reach: float = 1.5       # ... for vertices within this distance (voxels) whose normals agree
    tangential: int = 5           # tangential smoothing steps after each detail pass (0: none)
    seed: int = 0


@dataclass
class FitInfo:
    iterations: int = 0
    matched_source: float = 0.0   # share of source samples with a correspondence at the last iteration
    matched_target: float = 0.0
    seconds: dict = field(default_factory=dict)


# ---------------------------------------------------------------- the fit
def _sample(n: int, count: int, seed: int) -> np.ndarray:
    if n <= count:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, count, replace=False))


def scatter_rows(index: np.ndarray, values: np.ndarray, count: int) -> np.ndarray:
    """(count, C) sums of the rows of ``values`` (P, C) by ``index`` (P,): one bincount (np.add.at is 10x slower)."""
    c = values.shape[1]
    flat = (np.asarray(index, np.int64)[:, None] * c + np.arange(c)).ravel()
    return np.bincount(flat, values.ravel(), minlength=count * c).reshape(count, c)


def arap_rotations(graph: DeformationGraph, t: np.ndarray) -> np.ndarray:
    """ARAP local step: per node the rotation best mapping its rest edges g_k - g_j onto the deformed edges
    (g_k + t_k) - (g_j + t_j) (Procrustes: the rotation nearest to their covariance, ``nearest_rotations``)."""
    return nearest_rotations(graph.cov_rest + (graph.cov_map @ t.reshape(-1)).reshape(-1, 3, 3))


def nearest_rotations(S: np.ndarray) -> np.ndarray:
    """Per 3x3 matrix S (n, 3, 3) the rotation R maximising trace(R S) (V D U^T for S = U diag(s) V^T, D removing
    a reflection), on the OpenCL device (kernels/rotations.cl: one-sided Jacobi, 2 to 20 times faster than
    batched LAPACK for the ARAP step's ~600 nodes, which is 40 calls a frame); ``nearest_rotations_reference``
    is the same from LAPACK's SVD (equal to ~1e-14 wherever the rotation is unique: s2 > s3)."""
    S = np.ascontiguousarray(S, np.float64).reshape(-1, 3, 3)
    n = len(S)
    R = np.empty_like(S)
    if n:
        cl = RotationsCL.get()
        out = cl.buffer("R", R.nbytes)
        cl.launch("nearest_rotations", n, RotationsCL.GROUP, cl.upload("S", S), np.int32(n), out)
        cl.read(out, R.shape, np.float64, R)
    return R


def nearest_rotations_reference(S: np.ndarray) -> np.ndarray:
    """``nearest_rotations`` by LAPACK's SVD (batched), reflections removed."""
    U, _, Vt = np.linalg.svd(np.asarray(S, np.float64).reshape(-1, 3, 3))
    D = np.ones((len(U), 3))
    D[:, 2] = np.sign(np.linalg.det(U @ Vt))
    D[D[:, 2] == 0, 2] = 1
    return (np.swapaxes(Vt, 1, 2) * D[:, None, :]) @ np.swapaxes(U, 1, 2)    # V diag(D) U^T


class RotationsCL(clrt.Runner):
    """kernels/rotations.cl: the rotation nearest to each 3x3 matrix."""

    source = source("rotations.cl")
    GROUP = 64


class OutlineCL(clrt.Runner):
    """kernels/outline.cl: the silhouette term's rows."""

    source = source("outline.cl")
    GROUP = 64


def _outline_device(views, cl: OutlineCL):
    """The views' cameras and outline fields on the device (packed: fields, element offsets, widths, heights),
    made once per frame's silhouettes and kept on them with the host arrays the buffers use."""
    kept = getattr(views, "_outline_device", None)
    if kept is None or kept[0] is not cl:
        fields = [np.ascontiguousarray(a, np.float32) for a in views.alpha]
        host = (np.ascontiguousarray(views.cams, np.float32), np.concatenate([a.ravel() for a in fields]),
                np.cumsum([0] + [a.size for a in fields[:-1]]).astype(np.int64),
                np.array([a.shape[1] for a in fields], np.int32), np.array([a.shape[0] for a in fields], np.int32))
        kept = views._outline_device = (cl, host, [cl.host(a) for a in host])
    return kept[2]


def silhouette_rows(x: np.ndarray, target: Target, step: float = 0.5):
    """Points (voxel units) outside a silhouette: (point index, unit direction g^ (3,), distance d to move
    along it, in voxels) per (point, view), from the signed distance outline (alpha = 0.5 + pixels inside)
    and its gradient through the projection (central differences of ``step`` voxels); rows ordered by view,
    then point. On the OpenCL device (kernels/outline.cl, one work-item per (point, view): child_rope's 10 views
    x 6000 samples 29 ms a call in NumPy, 15 calls a fit); ``silhouette_rows_reference`` is the same in NumPy,
    bit for bit."""
    views = target.views
    X = np.ascontiguousarray(target.world(np.asarray(x, np.float64)), np.float64).reshape(-1, 3)
    n, nv = len(X), len(views.cams)
    if n == 0 or nv == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0)
    cl = OutlineCL.get()
    keep_b, g_b, d_b = cl.buffer("keep", nv * n), cl.buffer("g", 24 * nv * n), cl.buffer("d", 8 * nv * n)
    cl.launch("outline_pull", (n, nv), (OutlineCL.GROUP, 1), cl.upload("outline_points", X), np.int32(n),
              *_outline_device(views, cl), np.float64(step * target.voxel), np.float64(step), keep_b, g_b, d_b)
    keep = cl.read(keep_b, (nv, n), np.uint8)
    pv, pi = np.nonzero(keep)                                   # by view, then point: the reference's order
    if len(pv) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0)
    g = cl.read(g_b, (nv * n, 3), np.float64)
    d = cl.read(d_b, (nv * n,), np.float64)
    rows = pv * n + pi
    return pi.astype(np.int64), g[rows], d[rows]


def silhouette_rows_reference(x: np.ndarray, target: Target, step: float = 0.5):
    """``silhouette_rows`` in NumPy, view by view."""
    from nodes.common.cameras import project_packed_f32

    views = target.views
    out_i, out_g, out_d = [], [], []
    X = target.world(np.asarray(x, np.float64))
    h = step * target.voxel
    for v in range(len(views.cams)):
        cam = views.cams[v]
        field_ = views.alpha[v]
        H, W_ = field_.shape
        if W_ < 2 or H < 2:                          # a view that sees nothing (track.crop: 1 x 1 of an empty mask)
            continue

        def sample(P):
            u, w, front = project_packed_f32(cam, P.astype(np.float32))
            u, w = u.astype(np.float64), w.astype(np.float64)
            with np.errstate(invalid="ignore"):
                ok = front & (u >= 0) & (u <= W_ - 1) & (w >= 0) & (w <= H - 1)
            uc = np.clip(np.nan_to_num(u), 0, W_ - 1.001)
            wc = np.clip(np.nan_to_num(w), 0, H - 1.001)
            x0, y0 = uc.astype(np.int64), wc.astype(np.int64)
            fx, fy = uc - x0, wc - y0
            val = ((1 - fx) * (1 - fy) * field_[y0, x0] + fx * (1 - fy) * field_[y0, x0 + 1]
                   + (1 - fx) * fy * field_[y0 + 1, x0] + fx * fy * field_[y0 + 1, x0 + 1])
            return val, ok

        a0, ok = sample(X)
        bad = np.flatnonzero(ok & (a0 < 0.5))
        if len(bad) == 0:
            continue
        g = np.zeros((len(bad), 3))
        for axis in range(3):
            e = np.zeros(3)
            e[axis] = h
            ap, okp = sample(X[bad] + e)
            am, okm = sample(X[bad] - e)
            g[:, axis] = np.where(okp & okm, (ap - am) / (2 * step), 0.0)           # per voxel
        norm = np.linalg.norm(g, axis=1)
        keep = norm > 1e-6
        out_i.append(bad[keep])
        out_g.append(g[keep] / norm[keep, None])
        out_d.append((0.5 - a0[bad][keep]) / norm[keep])                              # voxels to move in
    if not out_i:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0)
    return np.concatenate(out_i), np.concatenate(out_g), np.concatenate(out_d)


class Registration:
    """Non-rigid ICP of one deformation graph (one keyframe mesh) onto targets (see the module docstring).

    Everything that depends only on the keyframe is prepared once: the sampled source vertices and their
    nodes and weights, and the sparsity pattern of the 3N x 3N normal equations (node pairs sharing a sample
    vertex or a graph edge) with its symbolic factorisation, so each ICP iteration only accumulates values into
    it (np.bincount) and factorises (nodes/common/cholesky.py: CHOLMOD, or SuperLU without cvxopt)."""

    def __init__(self, graph: DeformationGraph, faces: np.ndarray, params: FitParams):
        from scipy.sparse import coo_matrix, csr_matrix

        self.graph, self.faces, self.params = graph, np.asarray(faces, np.int64), params
        used = used_vertices(self.faces, len(graph.rest))
        self.src = used[_sample(len(used), params.samples, params.seed)]
        self.rest_normals = vertex_normals(graph.rest, self.faces)[self.src]
        self.idx = graph.vertex_nodes[self.src]                       # (S, K)
        self.w = graph.vertex_weights[self.src]                       # (S, K)
        self.off = graph.offsets[self.src]                            # (S, K, 3)
        n, K = len(graph.nodes), self.idx.shape[1]
        # node-pair pattern: (j, k) for every pair of nodes of a sample vertex and every graph edge
        pj = np.concatenate([np.repeat(self.idx, K, axis=1).ravel(), graph.directed[:, 0], graph.directed[:, 1],
                             np.arange(n)])
        pk = np.concatenate([np.tile(self.idx, (1, K)).ravel(), graph.directed[:, 1], graph.directed[:, 1], np.arange(n)])
        keys, inverse = np.unique(pj * n + pk, return_inverse=True)
        self.pair_j, self.pair_k = keys // n, keys % n
        s_len = self.idx.size * K
        self.sample_pairs = inverse[:s_len].reshape(len(self.src), K * K)            # (S, K*K)
        m = len(graph.directed)
        self.edge_jk = inverse[s_len: s_len + m]                                      # pair (j, k) per directed edge
        self.edge_kk = inverse[s_len + m: s_len + 2 * m]                              # pair (k, k)
        self.diag_pair = inverse[s_len + 2 * m:]                                      # (j, j)
        self.edge_jj = self.diag_pair[graph.directed[:, 0]]
        half = m // 2                                                                  # directed = [edges; reversed]
        self.edge_kj = self.edge_jk[(np.arange(m) + half) % max(m, 1)]                 # pair (k, j)
        P = len(keys)
        a_b = np.arange(9)
        rows = self.pair_j[:, None] * 3 + a_b[None, :] // 3          # value (pair, a * 3 + b) sits at (3j + a, 3k + b)
        cols = self.pair_k[:, None] * 3 + a_b[None, :] % 3
        # the pattern's lower triangle (A is symmetric positive definite), CSC: built with values 1..P*9 to find the
        # slot of every (pair, a, b) value; CHOLMOD finds its fill-reducing order and symbolic factorisation once
        # here, so each ICP iteration only gathers the values and refactorises (SparseCholesky)
        self.n3 = 3 * n
        rows, cols = rows.ravel(), cols.ravel()
        low = rows >= cols
        probe = coo_matrix((np.arange(1, P * 9 + 1, dtype=np.float64)[low], (rows[low], cols[low])),
                           shape=(self.n3, self.n3)).tocsc()
        probe.sort_indices()
        self.gather = probe.data.astype(np.int64) - 1                                 # CSC slot -> (pair, a, b)
        self.cholesky = SparseCholesky(probe)
        # the sampled vertices as linear maps of the state, built once: p = Mp vec(R) + p0 (translation-free
        # position), normals before normalising = Mn vec(R), and the skinning weights Wt (3N x 3S) whose
        # transpose blends the translations (x = p + Wt^T t) and which scatters per-sample rows to the nodes
        S = len(self.src)
        a3 = np.arange(3)
        rows9 = np.broadcast_to((np.arange(S)[:, None, None, None] * 3 + a3[None, None, :, None]), (S, K, 3, 3))
        cols9 = self.idx[:, :, None, None] * 9 + a3[None, None, :, None] * 3 + a3[None, None, None, :]
        vals = np.broadcast_to(self.w[:, :, None, None] * self.off[:, :, None, :], (S, K, 3, 3))
        self.Mp = csr_matrix((vals.ravel(), (rows9.ravel(), np.broadcast_to(cols9, (S, K, 3, 3)).ravel())), shape=(3 * S, 9 * n))
        vals = np.broadcast_to(self.w[:, :, None, None] * self.rest_normals[:, None, None, :], (S, K, 3, 3))
        self.Mn = csr_matrix((vals.ravel(), (rows9.ravel(), np.broadcast_to(cols9, (S, K, 3, 3)).ravel())), shape=(3 * S, 9 * n))
        self.p0 = np.einsum("sk,ska->sa", self.w, graph.nodes[self.idx])
        rows3 = self.idx[:, :, None] * 3 + a3
        cols3 = np.broadcast_to(np.arange(S)[:, None, None] * 3 + a3, (S, K, 3))
        self.Wt = csr_matrix((np.broadcast_to(self.w[:, :, None], (S, K, 3)).ravel(), (rows3.ravel(), cols3.ravel())),
                             shape=(3 * n, 3 * S))
        self.WtT = self.Wt.T.tocsr()
        # the ARAP rows' blocks per unit weight: +I at (j, j) and (k, k), -I at (j, k) and (k, j) per directed edge
        self.arap_blocks = np.zeros((P, 9))
        for pair, sign in ((self.edge_jj, 1.0), (self.edge_kk, 1.0), (self.edge_jk, -1.0), (self.edge_kj, -1.0)):
            np.add.at(self.arap_blocks, pair, sign * np.eye(3).ravel())
        # the ARAP rows' right-hand side, linear in the rotations: sum over edges (j, k) of c_jk at k and -c_jk at j,
        # c_jk = R_j e_jk - e_jk (e_jk = g_k - g_j): arap_rhs @ vec(R) - arap_rhs0
        jk, e = graph.directed, graph.rest_edges
        m = len(jk)
        row = np.broadcast_to(np.arange(3)[None, :, None], (m, 3, 3))
        col = jk[:, 0, None, None] * 9 + np.arange(3)[None, :, None] * 3 + np.arange(3)[None, None, :]
        val = np.broadcast_to(e[:, None, :], (m, 3, 3))
        self.arap_rhs = coo_matrix((np.r_[val.ravel(), -val.ravel()],
                                    (np.r_[(jk[:, 1, None, None] * 3 + row).ravel(), (jk[:, 0, None, None] * 3 + row).ravel()],
                                     np.r_[col.ravel(), col.ravel()])), shape=(self.n3, 9 * n)).tocsr()
        self.arap_rhs0 = (np.bincount((jk[:, 1, None] * 3 + np.arange(3)).ravel(), e.ravel(), minlength=self.n3)
                          - np.bincount((jk[:, 0, None] * 3 + np.arange(3)).ravel(), e.ravel(), minlength=self.n3))
        # node pair <- sample: w_sj w_sk (the data blocks of pair (j, k) are sum_s w_sj w_sk Q_s: one product)
        ww = (self.w[:, :, None] * self.w[:, None, :]).reshape(S, -1)
        self.pair_of_sample = csr_matrix((ww.ravel(), (self.sample_pairs.ravel(), np.repeat(np.arange(S), K * K))),
                                         shape=(P, S))

    def _sample_state(self, state: GraphState) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(positions x (S, 3), normals (S, 3), translation-free part p (S, 3)) of the sampled vertices."""
        r = state.R.reshape(-1)
        p = (self.Mp @ r).reshape(-1, 3) + self.p0
        x = p + (self.WtT @ state.t.reshape(-1)).reshape(-1, 3)
        nr = (self.Mn @ r).reshape(-1, 3)
        nr /= np.maximum(row_norms(nr), 1e-12)[:, None]
        return x, nr, p

    def _rhs(self, h: np.ndarray, Q: np.ndarray, state: GraphState, w_a: float) -> np.ndarray:
        """Right-hand side for the rotations in ``state``: data rows give q_s = h_s - Q_s p_s(R) per sample
        (p: the translation-free position), ARAP rows (t_k - t_j - c_jk) with c_jk = (R_j - I)(g_k - g_j)."""
        p = (self.Mp @ state.R.reshape(-1)).reshape(-1, 3) + self.p0
        q = h - (Q.reshape(-1, 3, 3) @ p[:, :, None])[:, :, 0]
        rhs = self.Wt @ q.reshape(-1)
        rhs += w_a * (self.arap_rhs @ state.R.reshape(-1) - self.arap_rhs0)
        return rhs

    def fit(self, state: GraphState, target: Target) -> tuple[GraphState, FitInfo]:
        """ICP iterations: correspondences, then (rotations fixed) the normal equations in t are assembled and
        factorised once and ``inner`` local/global ARAP steps reuse the factorisation (only the right-hand side
        depends on the rotations)."""
        import time

        prm = self.params
        graph = self.graph
        info = FitInfo()
        clock = {"match": 0.0, "assemble": 0.0, "solve": 0.0}
        state = state.copy()
        S = len(self.src)
        tgt = target.query.used[_sample(len(target.query.used), prm.samples, prm.seed + 1)]
        q, nq = target.vertices[tgt], target.normals[tgt]
        iters = max(1, prm.iterations)
        eye9 = np.eye(3).ravel()
        for it in range(iters):
            s = it / max(1, iters - 1)
            arap = prm.arap_start * (prm.arap / prm.arap_start) ** s
            reject = prm.reject + (prm.reject_end - prm.reject) * s
            robust = prm.robust * reject / prm.reject_end                # residual scale shrinks with the reach
            t0 = time.perf_counter()
            xs, ns, _ = self._sample_state(state)
            _, j = target.query.nearest_vertex(xs, reject)
            ok = j >= 0
            jj = np.maximum(j, 0)
            c, nc = target.vertices[jj], target.normals[jj]
            ok &= np.einsum("ij,ij->i", ns, nc) > prm.normal_cos
            dq, i_q = PointGrid(xs).nearest(q, reject)
            ok_q = np.isfinite(dq)
            i_q = np.where(ok_q, i_q, S - 1)
            ok_q &= np.einsum("ij,ij->i", ns[i_q], nq) > prm.normal_cos
            clock["match"] += time.perf_counter() - t0
            t0 = time.perf_counter()
            # every row reads a . x_s = a . c for one sample s: per sample Q_s = sum w a a^T, h_s = sum w a a^T c
            Q = np.zeros((S, 9))
            h = np.zeros((S, 3))
            r = np.einsum("ij,ij->i", nc, xs - c)                       # source -> target, point-to-plane
            gm = np.where(ok, 1.0 / (1.0 + (r / robust) ** 2) ** 2, 0.0) / max(1, ok.sum())
            nn = (nc[:, :, None] * nc[:, None, :]).reshape(S, 9)
            Q += gm[:, None] * nn
            h += (gm * np.einsum("ij,ij->i", nc, c))[:, None] * nc
            if prm.point > 0:                                             # a little point-to-point
                Q += (prm.point * gm)[:, None] * eye9
                h += (prm.point * gm)[:, None] * c
            rq = np.einsum("ij,ij->i", nq, xs[i_q] - q)                   # target -> source
            gq = prm.coverage * np.where(ok_q, 1.0 / (1.0 + (rq / robust) ** 2) ** 2, 0.0) / max(1, ok_q.sum())
            Q += scatter_rows(i_q, gq[:, None] * (nq[:, :, None] * nq[:, None, :]).reshape(-1, 9), S)
            h += scatter_rows(i_q, (gq * np.einsum("ij,ij->i", nq, q))[:, None] * nq, S)
            if prm.silhouette > 0 and target.views is not None:
                vi, g, dist = silhouette_rows(xs, target)
                near = dist <= prm.silhouette_reach                        # farther: a limb that moved, not a fit error
                vi, g, dist = vi[near], g[near], dist[near]
                if len(vi):
                    ws = prm.silhouette / S
                    goal = xs[vi] + g * dist[:, None]                     # the outline, along the gradient
                    Q += scatter_rows(vi, ws * (g[:, :, None] * g[:, None, :]).reshape(-1, 9), S)
                    h += scatter_rows(vi, (ws * np.einsum("ij,ij->i", g, goal))[:, None] * g, S)
            A_pairs = self.pair_of_sample @ Q
            w_a = arap / max(1, len(graph.directed))
            A_pairs += w_a * self.arap_blocks
            A_pairs[self.diag_pair] += 1e-8 * eye9
            clock["assemble"] += time.perf_counter() - t0
            t0 = time.perf_counter()
            self.cholesky.factor(A_pairs.ravel()[self.gather])
            for _ in range(max(1, prm.inner)):
                state.t = self.cholesky.solve(self._rhs(h, Q, state, w_a)).reshape(-1, 3)
                state.R = arap_rotations(graph, state.t)
            clock["solve"] += time.perf_counter() - t0
            info.matched_source = float(ok.mean()) if S else 0.0
            info.matched_target = float(ok_q.mean()) if len(ok_q) else 0.0
        info.iterations = iters
        info.seconds = clock
        return state, info


def detail(x: np.ndarray, faces: np.ndarray, target: Target, params: FitParams, adjacency=None, passes: int = 2,
           offsets: np.ndarray | None = None) -> np.ndarray:
    """Bring the surface detail of the target onto the graph-deformed surface, ``passes`` times:

    1. each vertex moves along its normal onto the tangent plane of its nearest target vertex (within
       ``detail_reach`` voxels, normals within 60 degrees), the displacements smoothed over ``detail`` rings of
       neighbours by normalised convolution (vertices without a match take their neighbours' displacement);
    2. ``tangential`` steps towards the keyframe's own triangle layout, restricted to each vertex's tangent
       plane (``tangential_smooth`` with ``offsets``: the keyframe's umbrella offsets turned by the graph, see
       ``laplacian_offsets``): the surface stays where it is, triangles crumpled by step 1 open up (a projection onto a faceted
       reconstruction folds the triangles that land on different facets: on the walking figure 2650 folded
       edges of 90k without, 670 with 2 x 5 steps; the keyframe reconstruction itself has 410)."""
    if params.detail <= 0 or len(faces) == 0:
        return x
    S = ring_operator(faces, len(x)) if adjacency is None else adjacency
    x = x.copy()
    for _ in range(passes):
        n = vertex_normals(x, faces)
        _, j = target.query.nearest_vertex(x, params.detail_reach + 1.0)
        ok = j >= 0
        jj = np.maximum(j, 0)
        c, nc = target.vertices[jj], target.normals[jj]
        cos = np.einsum("ij,ij->i", n, nc)
        ok &= cos > 0.5
        d = np.where(ok, np.einsum("ij,ij->i", nc, c - x) / np.maximum(cos, 0.5), 0.0)
        ok &= (d <= params.detail_out) & (d >= -params.detail_reach)
        w = ok.astype(np.float64)
        num, den = w * d, w
        for _ in range(int(round(params.detail))):
            num, den = S @ num, S @ den
        h = np.divide(num, den, out=np.zeros_like(num), where=den > 1e-9)
        x += h[:, None] * n
        x = tangential_smooth(x, faces, S, params.tangential, offsets=offsets)
    return x


def snap(x: np.ndarray, faces: np.ndarray, target: Target, params: FitParams, adjacency=None,
         offsets: np.ndarray | None = None) -> np.ndarray:
    """Put the tracked surface on the target surface: ``snap`` rounds of (``tangential`` steps towards the
    keyframe layout, then each vertex onto its closest point of the target within ``snap_reach`` voxels where
    the normals agree (cosine > 0.5); the others keep their place). After the graph fit and the detail step the
    tracked surface lies within a fraction of a voxel of the reconstruction but not on it, and a silhouette
    rim 0.1 voxel inside costs ~0.5 pixel all round the outline (about 2 % of IoU on child_rope): the
    projection removes that (same faces, vertices move by that fraction only)."""
    if params.snap <= 0 or len(faces) == 0:
        return x
    S = ring_operator(faces, len(x)) if adjacency is None else adjacency
    x = x.copy()
    for r in range(params.snap):
        if r:
            x = tangential_smooth(x, faces, S, params.tangential, offsets=offsets)
        n = vertex_normals(x, faces)
        q, d, f = target.query.closest(x, with_faces=True)
        fn = face_normals(target.vertices, target.faces[f])
        ok = (d <= params.snap_reach) & (np.einsum("ij,ij->i", n, fn) > 0.5)
        x[ok] = q[ok]
    return x


def tangential_smooth(x: np.ndarray, faces: np.ndarray, S, steps: int, lam: float = 0.5,
                      offsets: np.ndarray | None = None) -> np.ndarray:
    """``steps`` of x_i += lam * P_i (mean of the neighbours + offsets_i - x_i), P_i the projection onto the
    tangent plane (S = I + A). With ``offsets`` the keyframe's umbrella offsets (``laplacian_offsets``) the
    keyframe layout is the fixed point, so an undeformed mesh does not slide; without, uniform smoothing."""
    n = vertex_normals(x, faces)                  # tangential steps barely turn the normals: computed once
    degree = ring_degree(S)
    for _ in range(steps):
        move = neighbour_mean(S, x, degree) - x
        if offsets is not None:
            move += offsets
        move -= np.einsum("ij,ij->i", move, n)[:, None] * n
        x = x + lam * move
    return x


def laplacian_offsets(graph: DeformationGraph, state: GraphState, S) -> np.ndarray:
    """Per vertex the keyframe's umbrella offset v_i - mean of its neighbours, turned by the vertex's blend of
    its nodes' rotations (sum_j w_ij R_j)."""
    cached = getattr(graph, "_offset_map", None)
    if cached is None or cached[0] is not S:                     # per keyframe and ring operator: built once
        cached = graph._offset_map = (S, graph.blend_map(graph.rest - neighbour_mean(S, graph.rest)))
    return (cached[1] @ state.R.reshape(-1)).reshape(-1, 3)


def unfold(x: np.ndarray, faces: np.ndarray, pairs, S, rounds: int, target: "Target | None" = None,
           reach: float = 1.5, steps: int = 3) -> np.ndarray:
    """Open the folds the snap leaves (neighbouring vertices projected onto different sides of a thin part of
    the reconstruction, or onto different facets): up to ``rounds`` times, the vertices of folded edges and
    their one-ring take ``steps`` uniform Laplacian steps (half way to the mean of their neighbours), then go
    back onto the ``target`` surface (closest point within ``reach`` voxels, normals agreeing) unless that
    folds an edge again; the other vertices stay. Same faces; the surface moves only where it folded (so
    only the edges next to moved vertices are tested again)."""
    edges, pair = pairs
    f = np.asarray(faces, np.int64)
    x = x.copy()
    folded = np.zeros(len(edges), bool)
    folded[folded_edges(x, f, pairs)] = True
    degree = ring_degree(S)
    for _ in range(rounds):
        bad = np.flatnonzero(folded)
        if len(bad) == 0:
            break
        mark = np.zeros(len(x))
        mark[edges[bad].ravel()] = 1.0
        move = np.flatnonzero((S @ mark) > 0)                  # the fold's vertices and their one-ring
        moved = np.zeros(len(x), bool)
        moved[move] = True
        face_moved = moved[f[:, 0]] | moved[f[:, 1]] | moved[f[:, 2]]      # (any(axis=1): 10x as long)
        touched = np.flatnonzero(face_moved[pair[:, 0]] | face_moved[pair[:, 1]])
        # only the moving rows: the umbrella means of S's rows of ``move`` and the normals from the faces around
        # them (each the same sums in the same order as over the whole mesh: the same values)
        rows, deg = S[move], degree[move][:, None]
        for _ in range(steps):
            xm = x[move]
            x[move] = xm + 0.5 * ((rows @ x - xm) / deg - xm)
        if target is not None:
            n = vertex_normals(x, f[face_moved])[move]
            q, d, fq = target.query.closest(x[move], with_faces=True)
            fn = face_normals(target.vertices, target.faces[fq])
            ok = (d <= reach) & (np.einsum("ij,ij->i", n, fn) > 0.5)
            back = x.copy()
            back[move[ok]] = q[ok]
            again = folded_edges(back, f, pairs, touched)
            if len(again):                                      # those ends keep the smoothed place
                keep = np.zeros(len(x), bool)
                keep[edges[again].ravel()] = True
                back[keep] = x[keep]
            x = back
        folded[touched] = False
        folded[folded_edges(x, f, pairs, touched)] = True
    return x
