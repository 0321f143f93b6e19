"""Linear-blend-skinning weights and bone motions fitted to a dynamic mesh (SSDR, Le & Deng 2012), with
bones of fixed length and rotation-only joints as an option.

LBS: vertex v at frame t is sum_j w_vj (R_tj v + t_tj), v its rest position, w_v on the simplex with at
most ``influences`` non-zero entries. The fit alternates two steps, each lowering the squared error summed
over vertices and frames:

- weights, bone motions fixed: per vertex a small quadratic programme over the bones of its own part and
  the parts next to it (mesh or tree neighbours), min |sum_j w_j (y_j - q)|^2 over the frames (y_j: where
  bone j takes v, q: the tracked position), w >= 0, sum w = 1, solved by an active set (closed-form KKT
  solves on the support, the most negative weight dropped each round; solve_simplex_qp is the projected-
  gradient reference); then the ``influences`` largest are kept, never two bones that the current bone motions turn
  more than ``APART`` (165 degrees) from each other in some frame (their blend collapses: (R_a + R_b) / 2 at 179
  degrees has a smallest singular value of 0.009, the "candy wrapper", which no corrective shape can undo), and solved
  again (the next motion step may still turn a pair further: child_rope's segment 0 keeps 0.2 % of its vertices
  collapsing in some frame, 6.7 % without the rule). Writing it with y_j - q makes the
  sum-to-one direction drop out, so the problem is well conditioned. ``smooth`` adds a Laplacian term
  (Jacobi: neighbours' previous weights) where the motion leaves the weights undetermined.
- bone motions, weights fixed:
  * ``fixed_lengths`` (default): the skeleton is a tree of rotation-only joints; bone j's motion is its
    parent's followed by a rotation about the joint's rest pivot, the root also translates, so every
    joint stays where its parent puts it and bone lengths never change. Per frame, Gauss-Newton (with
    Levenberg damping) on one rotation increment per joint (about its current world pivot, applied to its
    whole subtree) and the root translation: 3J + 3 unknowns; the normal equations and the error are
    products of a frame's motions with vertex sums taken once per step (_pose_moments), so a Gauss-Newton
    round costs no pass over the vertices, and all frames are solved together (_pose_frames).
  * free: SSDR's per-bone update, a weighted Procrustes fit of each bone to what the other bones leave
    (what Dem Bones does; shared pivots then drift apart and bone lengths change over frames).

A bone that skins nothing has no data term (its pivot and rotation would drift: a leaf joint a metre off
the body), so a bone that is the strongest influence of no vertex is merged into its parent
(drop_weightless), and a rest-joint move that leaves a joint farther outside the mesh than its bones'
thickness is refused (joint_clearance). The alternation stops when one iteration lowers the rms by less
than ``tol`` of it, or by less than ``FLOOR`` (1e-5) of the bounding-box diagonal.

Helper bones (fit_helpers): a fitted rig, e.g. a humanoid template, takes free rigid bones under its own for what
rotation-only limbs cannot follow (loose clothes): the rig's bones keep their rest joints and lengths, and LBS with
the two together reaches what a free-bone fit with as many bones reaches (child_rope: Dem Bones' error at 19 bones
is 1.5-2x its goal).

    fit = fit_skin(traj, faces, rig, influences=4, iterations=10)   # SkinFit: weights, motions, errors
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from nodes.common.meshops import edge_length_graph

from .motion import Rig, Trajectories, label_adjacency

BLOCK = 1 << 24                # (vertex, bone pair) products held at once by the weights and rest steps (128 MB)
TWIST_SCALE = 0.05             # the pose step's twist term: a radian beyond TWIST_RANGE weighs ``twist`` times a bone's
                               # vertices each off by this share of the body's size
TWIST_RANGE = np.radians(45)   # twist of a joint against its parent that costs nothing (beyond: the term)
APART = np.radians(165)        # two bones turned further apart than this in some frame never share a vertex: their
                               # blend collapses there (0.5 / 0.5 at 179 degrees: smallest singular value 0.009;
                               # at 165: 0.13). child_rope's character: 150 and 165 both bring every frame within the
                               # corrective goal; 165 costs plain LBS less (median rms +0.4-2.3 mm, 150: +0.9-3.1)


@dataclass
class SkinFit:
    """``rest`` (V, 3) the rest shape the fit skins; ``weights`` (V, J) dense with <= influences non-zeros per row; ``rotations`` (F, J, 3, 3),
    ``translations`` (F, J, 3): rest -> frame; ``joints`` (J, 3) rest pivots; ``parents``; per-frame
    ``rmse`` and ``max_error`` (F,); ``history``: total rmse after each iteration kept (one that raised it
    is undone and not listed); ``kept``: the rig's bone
    index of each bone (bones that skinned no vertex were merged into their parents: drop_weightless);
    ``refused``: rest-joint moves refused because they left the body (joint_clearance)."""

    rest: np.ndarray
    weights: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    joints: np.ndarray
    parents: list[int]
    rmse: np.ndarray
    max_error: np.ndarray
    history: list[float]
    kept: list[int]
    refused: int = 0


# ---------------------------------------------------------------- LBS
def lbs(rest: np.ndarray, weights: np.ndarray, rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
    """Skinned positions (F, V, 3) (or (V, 3) for one frame's (J, 3, 3), (J, 3))."""
    one = rotations.ndim == 3
    r = rotations[None] if one else rotations
    t = translations[None] if one else translations
    out = lbs_by_vertex(rest, weights, r, t).reshape(len(rest), r.shape[0], 3).transpose(1, 0, 2)
    return out[0] if one else out


def lbs_by_vertex(rest: np.ndarray, weights: np.ndarray, rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
    """Skinned positions in the vertex-major layout of ``Trajectories.by_vertex``: (V, 3F), column (frame,
    axis). One product of the per-vertex weighted homogeneous rest points w_vj [v, 1] with the bones' stacked
    motions."""
    f, j = rotations.shape[:2]
    x = np.concatenate([rotations, translations[..., None]], axis=-1)   # (F, J, 3, 4)
    vh = np.c_[rest, np.ones(len(rest))]
    lifted = (weights[:, :, None] * vh[:, None, :]).reshape(len(rest), 4 * j)   # column (j, c)
    return lifted @ x.transpose(1, 3, 0, 2).reshape(4 * j, 3 * f)


def errors(traj: Trajectories, weights, rotations, translations) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame rms and max distance between the skinned and the given positions."""
    diff = lbs_by_vertex(traj.rest, weights, rotations, translations) - traj.by_vertex
    x, y, z = diff.reshape(len(diff), -1, 3).transpose(2, 0, 1)
    dd = x * x + y * y + z * z                                              # (V, F) (as Trajectories.qq)
    return np.sqrt(dd.mean(0)), np.sqrt(dd.max(0))


# ---------------------------------------------------------------- simplex QP
def project_simplex(x: np.ndarray, allowed: np.ndarray) -> np.ndarray:
    """Row-wise Euclidean projection onto {w >= 0, sum w = 1, w = 0 where not allowed}."""
    x = np.where(allowed, x, -1e30)
    u = -np.sort(-x, axis=1)
    css = np.cumsum(u, axis=1) - 1.0
    k = np.arange(1, x.shape[1] + 1)
    ok = (u - css / k) > 0
    rho = ok.shape[1] - 1 - np.argmax(ok[:, ::-1], axis=1)
    theta = css[np.arange(len(x)), rho] / (rho + 1)
    return np.maximum(x - theta[:, None], 0.0) * allowed


def solve_simplex_qp(h: np.ndarray, g: np.ndarray, allowed: np.ndarray, w0: np.ndarray, iterations: int = 150) -> np.ndarray:
    """Batched min w^T h w - 2 g^T w over the (allowed) simplex, FISTA from ``w0``. h (N, K, K), g (N, K)."""
    lip = np.linalg.eigvalsh(h)[:, -1]
    step = 0.5 / np.maximum(lip, 1e-30)
    w = project_simplex(w0, allowed)
    z, tk = w.copy(), 1.0
    for _ in range(iterations):
        grad = 2.0 * (np.einsum("nab,nb->na", h, z) - g)
        w_new = project_simplex(z - step[:, None] * grad, allowed)
        tn = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * tk * tk))
        z = w_new + ((tk - 1.0) / tn) * (w_new - w)
        w, tk = w_new, tn
    return w


def _kkt_solve(hr, g, sup):
    """Minimiser of w^T h w - 2 g^T w subject to sum w = 1 and w = 0 off ``sup`` (batched KKT systems), each on its
    support: the bones of a support taken first, the systems as wide as the widest support (a vertex has a few of
    its 10-30 candidates on: a system of all of them costs (30 / 6)^3 times more)."""
    n, k = g.shape
    m = int(sup.sum(1).max()) if n else 0
    if 0 < m < k:
        order = np.argsort(~sup, axis=1, kind="stable")[:, :m]           # each support's bones first
        z = _kkt_solve(np.take_along_axis(np.take_along_axis(hr, order[:, :, None], axis=1), order[:, None, :], axis=2),
                       np.take_along_axis(g, order, axis=1), np.take_along_axis(sup, order, axis=1))
        out = np.zeros((n, k))
        np.put_along_axis(out, order, z, axis=1)
        return out
    kkt = np.zeros((n, k + 1, k + 1))
    kkt[:, :k, :k] = hr * (sup[:, :, None] & sup[:, None, :]) + (~sup)[:, :, None] * np.eye(k)
    kkt[:, :k, k] = sup
    kkt[:, k, :k] = sup
    rhs = np.zeros((n, k + 1))
    rhs[:, :k] = g * sup
    rhs[:, k] = 1.0
    return np.linalg.solve(kkt, rhs[..., None])[..., 0][:, :k] * sup


def solve_simplex_active(h: np.ndarray, g: np.ndarray, allowed: np.ndarray, ridge: float = 1e-9,
                         w0: np.ndarray | None = None) -> np.ndarray:
    """Batched min w^T h w - 2 g^T w over the (allowed) simplex: a primal active-set method (Lawson-Hanson
    style). From a feasible start (``w0`` where given, restricted to the allowed bones: the last weights
    step's, whose support rarely changes, ~4x fewer rounds; else the best single bone), solve the problem
    on the support with sum w = 1 in closed form; if a weight would go negative, step towards that solution
    until the first weight reaches 0 and drop it; otherwise add the allowed bone whose multiplier says the
    objective still falls, until none does. The problem is strictly convex (ridge): every start ends at the
    same minimiser."""
    n, k = g.shape
    scale = np.maximum(np.trace(h, axis1=1, axis2=2) / k, 1e-300)
    hr = h + (ridge * scale)[:, None, None] * np.eye(k)
    diag = np.einsum("nii->ni", hr) - 2 * g
    start = np.argmin(np.where(allowed, diag, np.inf), axis=1)
    w = np.zeros((n, k))
    w[np.arange(n), start] = 1.0
    if w0 is not None:
        w0 = np.where(allowed, np.maximum(w0, 0.0), 0.0)
        total = w0.sum(1)
        warm = total > 0
        w[warm] = w0[warm] / total[warm, None]
    sup = w > 0
    todo = allowed.any(1)
    tol = 1e-12 * scale
    for _ in range(4 * k + 4):
        idx = np.flatnonzero(todo)
        if not len(idx):
            break
        z = _kkt_solve(hr[idx], g[idx], sup[idx])
        wi, si = w[idx], sup[idx]
        blocked = si & (z < 0)
        feasible = ~blocked.any(1)
        # infeasible: step from w towards z until a weight reaches zero; drop it
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(blocked, wi / (wi - z), np.inf)
        alpha = np.clip(ratio.min(1), 0.0, 1.0)
        stepped = wi + alpha[:, None] * (z - wi)
        hit = np.argmin(ratio, axis=1)
        new_w = np.where(feasible[:, None], z, stepped)
        new_w[~feasible, hit[~feasible]] = 0.0
        new_w = np.maximum(new_w, 0.0)
        new_sup = si.copy()
        new_sup[~feasible, hit[~feasible]] = False
        # feasible: the multiplier of each allowed bone off the support; add the most negative
        grad = 2 * (np.einsum("nab,nb->na", hr[idx], new_w) - g[idx])
        mu = np.sum(np.where(new_sup, grad, 0), 1) / np.maximum(new_sup.sum(1), 1)
        lam = np.where(allowed[idx] & ~new_sup, grad - mu[:, None], np.inf)
        enter = np.argmin(lam, axis=1)
        add = feasible & (lam[np.arange(len(idx)), enter] < -tol[idx])
        new_sup[add, enter[add]] = True
        w[idx], sup[idx] = new_w, new_sup
        todo[idx[feasible & ~add]] = False
    return w / np.maximum(w.sum(1, keepdims=True), 1e-300)


# ---------------------------------------------------------------- weights step
def _homogeneous(rot, tr):
    return np.concatenate([rot, tr[..., None]], axis=-1)              # (F, J, 3, 4)


def candidates(rest, labels, edges, parents, j, radius: float) -> np.ndarray:
    """(V, C) candidate bones per vertex (-1 padded): its part, the parts next to it (mesh edges, tree) and
    the parts of rest vertices within ``radius`` (surfaces that nearly touch: the inner knees)."""
    from scipy.spatial import cKDTree

    adj = label_adjacency(labels, edges, j) > 0
    for c, p in enumerate(parents):
        if p >= 0:
            adj[c, p] = adj[p, c] = True
    np.fill_diagonal(adj, True)
    near = np.zeros((len(rest), j), bool)
    near[np.arange(len(rest)), labels] = True
    near |= adj[labels]
    pairs = cKDTree(rest).query_pairs(radius, output_type="ndarray")
    if len(pairs):
        near[pairs[:, 0], labels[pairs[:, 1]]] = True
        near[pairs[:, 1], labels[pairs[:, 0]]] = True
    width = int(near.sum(1).max())
    order = np.argsort(~near, axis=1, kind="stable")[:, :width]           # allowed bones first
    out = np.where(np.take_along_axis(near, order, axis=1), order, -1)
    return out


def _not_apart(w, cs, keep, rot, influences: int, apart: float | None) -> np.ndarray:
    """Which of each vertex's candidate bones (``cs`` (V, C), weights ``w``, ``keep`` the ones weighing > 0) stay:
    the ``influences`` heaviest, each taken only when no heavier one kept is turned more than ``apart`` radians
    from it in some frame of ``rot`` (F, J, 3, 3) (None: no such test). Returns (V, C) bool."""
    v, c = w.shape
    order = np.argsort(-np.where(keep, w, -1.0), axis=1, kind="stable")
    bones = np.take_along_axis(cs, order, axis=1)
    ok = np.take_along_axis(keep, order, axis=1)
    if apart is not None:
        trace = np.einsum("facd,fbcd->fab", rot, rot).min(axis=0)      # cos(angle) = (trace - 1) / 2, worst frame
        opposed = (trace - 1) / 2 < np.cos(apart)
    taken = np.zeros((v, c), bool)
    for i in range(c):
        good = ok[:, i] & (taken.sum(1) < influences)
        if apart is not None and i:
            clash = (opposed[bones[:, :i], bones[:, i:i + 1]] & taken[:, :i]).any(axis=1)
            good &= ~clash
        taken[:, i] = good
    out = np.zeros_like(keep)
    np.put_along_axis(out, order, taken, axis=1)
    return out


def fit_weights(traj: Trajectories, rot, tr, cand_of_vertex: np.ndarray, w_prev: np.ndarray, nbr, *, influences: int,
                smooth: float, warm: bool = True, apart: float | None = APART) -> np.ndarray:
    """The weights step (module docstring). ``cand_of_vertex`` (V, C) bone indices (-1 = none), ``w_prev``
    (V, J), ``nbr`` (offsets, neighbours) CSR of mesh neighbours; ``warm``: the QPs start from ``w_prev``
    (the same minimisers, fewer active-set rounds). The heaviest ``influences`` bones are kept (``_not_apart``:
    not two turned more than ``apart`` radians from each other in some frame, where their blend would collapse)
    and the weights solved again on them. Returns (V, J)."""
    f, j = rot.shape[:2]
    v = len(traj.rest)
    x = _homogeneous(rot, tr)
    xs = x.transpose(1, 0, 2, 3).reshape(j, 3 * f, 4)                  # (J, 3F, 4)
    gram = np.einsum("jkc,lkd->jlcd", xs, xs)                           # sum_t X_j^T X_l  (J, J, 4, 4)
    cross = (traj.by_vertex @ xs.transpose(1, 0, 2).reshape(3 * f, 4 * j)).reshape(v, j, 4)   # sum_t X_j^T q
    vh = np.c_[traj.rest, np.ones(v)]
    qq = traj.qq.sum(0)
    c = cand_of_vertex
    valid = c >= 0
    cs = np.where(valid, c, 0)
    # H_ab = sum_t (y_a - q).(y_b - q) = vh G_ab vh - g_a - g_b + qq   with g_a = sum_t y_a . q
    # vh G_ab vh for every bone pair (a, b) at once (one product with the vertices' outer products), then
    # each vertex's candidate pairs picked out
    # (in blocks of vertices when V J^2 is large: a rig with helper bones)
    outer, pick = (vh[:, :, None] * vh[:, None, :]).reshape(v, 16), (cs[:, :, None] * j + cs[:, None, :]).reshape(v, -1)
    step = v if v * j * j <= BLOCK else max(1, BLOCK // (j * j))
    h = np.concatenate([np.take_along_axis(outer[s:s + step] @ gram.reshape(j * j, 16).T, pick[s:s + step], axis=1)
                        for s in range(0, v, step)])
    h = h.reshape(v, c.shape[1], c.shape[1])
    gq = np.einsum("vac,vc->va", cross[np.arange(v)[:, None], cs], vh)     # (V, C)
    h = h - gq[:, :, None] - gq[:, None, :] + qq[:, None, None]
    g = np.zeros_like(gq)
    # Laplacian smoothing: lam * sum_{u in N(v)} |w_v - w_u|^2 (neighbours' previous weights)
    offsets, neighbours = nbr
    deg = np.diff(offsets).astype(np.float64)
    mean_nbr = np.add.reduceat(w_prev[neighbours], offsets[:-1], axis=0) if len(neighbours) else np.zeros_like(w_prev)
    mean_nbr[deg == 0] = 0.0
    lam = smooth * f * float(np.linalg.norm(np.ptp(traj.rest, axis=0))) ** 2
    h = h + (lam * deg)[:, None, None] * np.eye(c.shape[1])[None]
    g = g + lam * np.take_along_axis(mean_nbr, cs, axis=1)
    h = 0.5 * (h + h.transpose(0, 2, 1))
    w = solve_simplex_active(h, g, valid, w0=np.take_along_axis(w_prev, cs, axis=1) * valid if warm else None)
    keep = _not_apart(w, cs, valid & (w > 0), rot, influences, apart)
    if influences < c.shape[1] or not np.array_equal(keep, valid & (w > 0)):
        w = solve_simplex_active(h, g, keep, w0=w if warm else None)
    out = np.zeros((v, j))
    np.add.at(out, (np.repeat(np.arange(v), c.shape[1]), cs.ravel()), (w * valid).ravel())
    return out


# ---------------------------------------------------------------- bone motions: fixed lengths (Gauss-Newton)
def subtree_matrix(parents: list[int]) -> np.ndarray:
    """D (J, J): D[d, k] = 1 when joint d is k or below k."""
    j = len(parents)
    d = np.eye(j)
    for i in range(j):
        p = parents[i]
        while p >= 0:
            d[i, p] = 1.0
            p = parents[p]
    return d


def topological(parents: list[int]) -> list[int]:
    """Joint indices, each after its parent (graphlib.TopologicalSorter over the parent links)."""
    from graphlib import TopologicalSorter

    return list(TopologicalSorter({j: [p] if p >= 0 else [] for j, p in enumerate(parents)}).static_order())


def constrain(rot, tr, joints, parents):
    """Rotation-only joints: keep each bone's rotation, set its translation so that its pivot goes where
    its parent takes it (parents first). (F, J, 3, 3), (F, J, 3) -> same."""
    tr = tr.copy()
    for j in topological(parents):
        p = parents[j]
        if p >= 0:
            pivot = np.einsum("fab,b->fa", rot[:, p], joints[j]) + tr[:, p]
            tr[:, j] = pivot - np.einsum("fab,b->fa", rot[:, j], joints[j])
    return rot, tr


def _skew(a):
    z = np.zeros(a.shape[:-1])
    return np.stack([np.stack([z, -a[..., 2], a[..., 1]], -1), np.stack([a[..., 2], z, -a[..., 0]], -1),
                     np.stack([-a[..., 1], a[..., 0], z], -1)], -2)


def _rodrigues(w):
    """Rotation matrices (..., 3, 3) of axis-angle vectors (..., 3)."""
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    k = _skew(w)
    small = th < 1e-12
    s = np.where(small, 1.0, np.sin(th) / np.where(small, 1.0, th))
    c = np.where(small, 0.5, (1 - np.cos(th)) / np.where(small, 1.0, th * th))
    return np.eye(3) + s * k + c * (k @ k)


def _pose_moments(rest, frames, weights, parents):
    """What the pose step needs of the vertices, summed once (weights fixed). With h_v = [v, 1], the blend
    weights W (V, J) and U_vjk = W_vj [j in the subtree of k], the pose step's s_vk = sum_j U_vjk (X_j - c_k e4^T) h_v
    (_pose_frames): every sum over vertices in its Gauss-Newton system and error is a product of a frame's
    motions with Q = sum_v (U h)(U h)^T, P = sum_v (U h)(W h)^T, G = sum_v (W h)(W h)^T, sum_v U h, sum_v W h,
    and per frame sum_v (U h) q^T, sum_v (W h) q^T, sum_v q, sum_v |q|^2. U is kept on the ``pairs`` (j, k)
    with j in the subtree of k only (sorted by k; about a third of J^2 for a body), the rest are zeros.
    ``frames`` (F, V, 3). Returns a dict."""
    from scipy.sparse import csr_matrix

    v, j = weights.shape
    h = np.c_[rest, np.ones(v)]
    d = subtree_matrix(parents)
    pk, pj = np.nonzero(d.T)                                                # pairs (j, k), sorted by k
    pair = np.full((j, j), -1)
    pair[pj, pk] = np.arange(len(pj))
    rows, jj = np.nonzero(weights)                                          # U_vjk = W_vj D_jk, sparse
    jj, kk = np.repeat(jj, j), np.tile(np.arange(j), len(jj))
    rows = np.repeat(rows, j)
    on = d[jj, kk] > 0
    rows, jj, kk = rows[on], jj[on], kk[on]
    vals = weights[rows, jj][:, None] * h[rows]                             # (nnz, 4)
    cols = (pair[jj, kk] * 4)[:, None] + np.arange(4)
    npair = len(pj)
    b = csr_matrix((vals.ravel(), (np.repeat(rows, 4), cols.ravel())), shape=(v, npair * 4))   # (V, pairs 4)
    lw = csr_matrix((weights[:, :, None] * h[:, None, :]).reshape(v, j * 4))   # (V, J 4), sparse
    f = len(frames)
    qv = np.ascontiguousarray(frames.transpose(1, 0, 2)).reshape(v, 3 * f)   # (V, 3F)
    bt, lwt = b.T.tocsr(), lw.T.tocsr()          # sparse products: no BLAS threads on these thin shapes
    return {
        "pj": pj, "pk": pk, "starts": np.searchsorted(pk, np.arange(j)),
        "q": (bt @ b).toarray().reshape(npair, 4, npair, 4),
        "p": (bt @ lw).toarray(),                                                    # ((pair, c), (i, d))
        "g": (lwt @ lw).toarray(),                                                   # ((j, c), (i, d))
        "bsum": np.asarray(b.sum(0)).reshape(npair, 4),
        "lsum": np.asarray(lw.sum(0)).reshape(j, 4),
        "bq": np.asarray(bt @ qv).reshape(npair, 4, f, 3).transpose(2, 0, 1, 3),     # (F, pairs, 4, 3)
        "lq": np.asarray(lwt @ qv).reshape(j, 4, f, 3).transpose(2, 0, 1, 3),        # (F, J, 4, 3)
        "sq": frames.sum(1),                                                         # (F, 3)
        "qq": np.einsum("fva,fva->f", frames, frames),
        "count": v,
    }


def _pose_frames(mom, rot, tr, joints, parents, order, steps, hold=None, twist=None):
    """Gauss-Newton (Levenberg-damped) on the joint rotations (and root translation) of every frame at once,
    pivots fixed, from the vertex sums of _pose_moments; each frame is its own problem with its own damping,
    accepted or refused steps and stop (the per-frame arithmetic in stacked small products; einsum's own
    loops, no BLAS threads for arrays this small). ``rot`` (F, J, 3, 3), ``tr`` (F, J, 3).

    Per frame and joint k, s_vk = sum_a w_va [bone a of v is in the subtree of k] (y_va - c_k) with y_va
    where bone a takes v and c_k the joint's world pivot; the unknowns are one rotation increment per joint
    (about c_k, moving its subtree) and the root translation: J^T J from M[k, l] = sum_v s_vk s_vl^T.

    ``hold`` (targets (F, J, 3), lam (J,)) adds sum_k lam_k |c_k - target_k|^2 (skin: its input skeleton's posed
    joints): joint k's pivot moves by delta_d x (c_k - c_d) under each ancestor d's increment and by the root
    translation (_hold_normal_equations).

    ``twist`` (axes (J, 3), lam (J,)) adds sum_k lam_k tau_k^2, tau_k the twist of joint k against its parent (its
    rotation relative to the parent's, about its bone's rest axis: ``twists``). The data leave a bone's turn
    about its own axis nearly open (a limb is close to a cylinder), and the frames are fitted one by one: without
    it, the fit turned child_rope's bones about their axes by up to 178 degrees from one frame to the next (a
    knee twisted half round, blends collapsing where two such bones meet). Joint k's relative rotation moves
    with its own increment alone (its parent's turns the whole subtree: R_p^T exp([delta_k]) R_k), its twist by
    b_k . delta_k to first order, b_k = R_k g_k (``_twist_terms``: the bone's world axis where the joint is
    straight, tilted across it as the joint bends)."""
    n_f, j = rot.shape[:2]
    n = 3 * j + 3
    eye3 = np.eye(3)
    pj, pk, starts = mom["pj"], mom["pk"], mom["starts"]

    def stacked(rot, tr):                                                       # (P, (j, c), a): X_j[a, c]
        x = np.concatenate([rot, tr[..., None]], axis=-1)
        return x.transpose(0, 1, 3, 2).reshape(len(x), 4 * j, 3), x

    def sq_error(rot, tr, f):
        # sum_v |p_v - q_v|^2 = sum_ji tr(X_j G_ji X_i^T) - 2 sum_j tr(X_j sum_v W_vj h_v q_v^T) + sum_v |q_v|^2
        # (to ~1e-7 of itself on the bench figure: cancellation against |q|^2)
        xs, x = stacked(rot, tr)
        quad = np.einsum("pkb,pkb->p", xs, mom["g"] @ xs)
        out = quad - 2 * np.einsum("pjac,pjca->p", x, mom["lq"][f]) + mom["qq"][f]
        if hold is not None:
            off = np.einsum("pjab,jb->pja", rot, joints) + tr - hold[0][f]
            out = out + np.einsum("pja,pja,j->p", off, off, hold[1])
        if twist is not None:
            tw = _beyond(twists(rot, parents, twist[0]), twist[2])
            out = out + np.einsum("pj,pj,j->p", tw, tw, twist[1])
        return out

    rot, tr = rot.copy(), tr.copy()
    err = sq_error(rot, tr, np.arange(n_f))
    mu = None
    live = np.arange(n_f)                                                       # frames still iterating
    for _ in range(steps):
        if not len(live):
            break
        rl, tl = rot[live], tr[live]
        m_f = len(live)
        xs, x = stacked(rl, tl)                                                 # (P, 4J, 3), (P, J, 3, 4)
        pivots = np.einsum("pjab,jb->pja", rl, joints) + tl                    # world pivot of each joint
        # X~_jk = X_j - c_k e4^T on the pairs (j, k): s_vk = sum_j U_vjk X~_jk h_v
        y = x[:, pj]                                                            # (P, pairs, 3, 4)
        y[..., 3] -= pivots[:, pk]
        # M[k, l] = sum_v s_vk s_vl^T = sum over the pairs of k and of l of X~_jk Q_jk,il X~_il^T
        z = np.einsum("pxayd,pybd->pxayb", np.einsum("pxac,xcyd->pxayd", y, mom["q"]), y)
        m = np.add.reduceat(np.add.reduceat(z, starts, axis=1), starts, axis=3).transpose(0, 1, 3, 2, 4)
        jtj = np.zeros((m_f, n, n))
        tr_m = np.trace(m, axis1=3, axis2=4)
        # blocks[k, l] = sum_v [s_vk]x^T [s_vl]x = tr(M[k, l]) I - M[l, k]
        blocks = tr_m[..., None, None] * eye3 - np.swapaxes(m, 1, 2)
        jtj[:, :3 * j, :3 * j] = blocks.transpose(0, 1, 3, 2, 4).reshape(m_f, 3 * j, 3 * j)
        # J = [ -[s_vk]x ... | I ]; J^T J[k, tau] = sum_v (-[s_vk]x)^T = [sum_v s_vk]x
        ssum = np.add.reduceat(np.einsum("pxac,xc->pxa", y, mom["bsum"]), starts, axis=1)
        jtj[:, :3 * j, 3 * j:] = _skew(ssum).reshape(m_f, 3 * j, 3)
        jtj[:, 3 * j:, :3 * j] = jtj[:, :3 * j, 3 * j:].transpose(0, 2, 1)
        jtj[:, 3 * j:, 3 * j:] = mom["count"] * eye3
        # sum_v s_vk r_v^T with r = q - p: over k's pairs X~_jk (sum_v U_vjk h_v q_v^T - sum_i P_jk,i X_i^T)
        px = (mom["p"] @ xs).reshape(m_f, len(pj), 4, 3)
        c = np.add.reduceat(np.einsum("pxac,pxcb->pxab", y, mom["bq"][live] - px), starts, axis=1)
        jtr = np.empty((m_f, n))
        # (-[s]x)^T r = s x r, summed over v
        jtr[:, :3 * j] = np.stack([c[..., 1, 2] - c[..., 2, 1], c[..., 2, 0] - c[..., 0, 2],
                                   c[..., 0, 1] - c[..., 1, 0]], -1).reshape(m_f, 3 * j)
        jtr[:, 3 * j:] = mom["sq"][live] - np.einsum("pjac,jc->pa", x, mom["lsum"])
        if hold is not None:
            _hold_normal_equations(jtj, jtr, pivots, hold[0][live] - pivots, hold[1], parents)
        if twist is not None:
            tw, g = _twist_terms(rl, parents, twist[0])
            tw = _beyond(tw, twist[2])                                         # (P, J), 0 within the range
            lam = twist[1][None, :] * (tw != 0)
            b = np.einsum("pjab,pjb->pja", rl, g)                               # d twist = b . delta
            for k in np.flatnonzero(twist[1] > 0):
                jtj[:, 3 * k:3 * k + 3, 3 * k:3 * k + 3] += lam[:, k, None, None] * b[:, k, :, None] * b[:, k, None, :]
                jtr[:, 3 * k:3 * k + 3] -= (lam[:, k] * tw[:, k])[:, None] * b[:, k]
        if mu is None:
            mu = 1e-6 * np.trace(jtj, axis1=1, axis2=2) / n + 1e-12
        improved = np.zeros(m_f, bool)
        trying = np.arange(m_f)                                                 # positions within live
        diag = np.einsum("pii->pi", jtj) + 1e-12
        for _ in range(6):
            if not len(trying):
                break
            fr = live[trying]
            lhs = jtj[trying] + mu[fr][:, None, None] * (diag[trying][:, :, None] * np.eye(n))
            delta = np.linalg.solve(lhs, jtr[trying][..., None])[..., 0]
            dr = _rodrigues(delta[:, :3 * j].reshape(-1, j, 3))
            tau = delta[:, 3 * j:]
            pv = pivots[trying]
            # accumulated world motion A_d = A_parent o E_d, E_d: rotation dr_d about pivots_d; root adds tau
            a_rot = np.empty_like(dr)
            a_tr = np.empty((len(fr), j, 3))
            for d in order:
                e_t = pv[:, d] - np.einsum("pab,pb->pa", dr[:, d], pv[:, d])
                if parents[d] < 0:
                    a_rot[:, d], a_tr[:, d] = dr[:, d], e_t + tau
                else:
                    pr, pt = a_rot[:, parents[d]], a_tr[:, parents[d]]
                    a_rot[:, d], a_tr[:, d] = np.matmul(pr, dr[:, d]), np.einsum("pab,pb->pa", pr, e_t) + pt
            new_rot = np.matmul(a_rot, rot[fr])
            new_tr = np.einsum("pjab,pjb->pja", a_rot, tr[fr]) + a_tr
            e2 = sq_error(new_rot, new_tr, fr)
            ok = e2 < err[fr]
            good = fr[ok]
            rot[good], tr[good], err[good] = new_rot[ok], new_tr[ok], e2[ok]
            mu[good] *= 0.3
            mu[fr[~ok]] *= 10.0
            improved[trying[ok]] = True
            trying = trying[~ok]
        live = live[improved & (err[live] != 0.0)]
    return rot, tr


def bone_axes(joints, parents) -> np.ndarray:
    """(J, 3) unit rest axis of each joint's bone: towards its child (of several, the one heading the largest
    subtree: a chest's neck, not its clavicles); a leaf's from its parent's joint to its own; zero for a root without
    children or a bone of zero length (no twist term there)."""
    joints = np.asarray(joints, np.float64)
    size = subtree_matrix(parents).sum(axis=0)                   # joints in each joint's subtree
    axes = np.zeros_like(joints)
    for k, p in enumerate(parents):
        kids = [c for c in range(len(parents)) if parents[c] == k]
        if kids:
            d = joints[max(kids, key=lambda c: (size[c], -c))] - joints[k]
        elif p >= 0:
            d = joints[k] - joints[p]
        else:
            continue
        n = np.linalg.norm(d)
        axes[k] = d / n if n > 0 else 0.0
    return axes


def twists(rot, parents, axes) -> np.ndarray:
    """(F, J) radians in (-pi, pi]: each joint's twist against its parent, the part of its relative rotation
    R_parent^T R_k about its bone's rest axis (swing-twist: 2 atan2(q_v . a, q_w) of the relative rotation's
    quaternion); 0 for a root. ``rot`` (F, J, 3, 3) rest -> frame, ``axes`` (J, 3) (``bone_axes``)."""
    return _twist_terms(rot, parents, axes)[0]


def _twist_terms(rot, parents, axes) -> tuple[np.ndarray, np.ndarray]:
    """(``twists`` (F, J), g (F, J, 3)): with the relative rotation's quaternion (w, v) and s = a . v, turning the
    relative rotation by a small local rotation e (R_rel exp([e])) changes the twist by g . e,
    g = (w^2 a + w (a x v) + s v) / (w^2 + s^2): a itself where the joint is straight, tilted across the bone as
    it bends (|g| = 1 / cos(swing / 2)). Zero for roots."""
    from scipy.spatial.transform import Rotation

    rot = np.asarray(rot, np.float64)
    f, j = rot.shape[:2]
    out, grad = np.zeros((f, j)), np.zeros((f, j, 3))
    kids = [k for k, p in enumerate(parents) if p >= 0]
    if not kids or not f:
        return out, grad
    par = [parents[k] for k in kids]
    a = np.broadcast_to(np.asarray(axes, np.float64)[kids], (f, len(kids), 3))
    rel = np.einsum("fkba,fkbc->fkac", rot[:, par], rot[:, kids])                # R_p^T R_k
    q = Rotation.from_matrix(rel.reshape(-1, 3, 3)).as_quat().reshape(f, len(kids), 4)   # (x, y, z, w)
    v, w = q[..., :3], q[..., 3:]
    s = np.einsum("fka,fka->fk", v, a)[..., None]
    t = 2 * np.arctan2(s[..., 0], w[..., 0])
    out[:, kids] = np.angle(np.exp(1j * t))                                        # wrapped to (-pi, pi]
    den = np.maximum(w * w + s * s, 1e-12)                                         # 0 only at a half-turn swing
    grad[:, kids] = (w * w * a + w * np.cross(a, v) + s * v) / den
    return out, grad


def _beyond(t, free):
    """The part of twists ``t`` beyond +-``free`` (0 within)."""
    return np.sign(t) * np.maximum(np.abs(t) - free, 0.0)


def _hold_normal_equations(jtj, jtr, pivots, res, lam, parents):
    """Add the joint term of _pose_frames to its Gauss-Newton system (in place): per frame p, joint k with
    residual r = target - c_k and a_d = c_k - c_d for each proper ancestor d, the Jacobian is -[a_d]x for
    d's rotation increment and I for the root translation, so J^T J gains lam ([a_d]x^T [a_e]x = (a_d.a_e) I -
    a_e a_d^T), [a_d]x against the translation, lam I; J^T r gains lam a_d x r and lam r."""
    j = len(parents)
    eye3 = np.eye(3)
    for k in np.flatnonzero(lam > 0):
        anc, d = [], parents[k]
        while d >= 0:
            anc.append(d)
            d = parents[d]
        lk, r = lam[k], res[:, k]
        a = {d: pivots[:, k] - pivots[:, d] for d in anc}
        for d in anc:
            jtr[:, 3 * d:3 * d + 3] += lk * np.cross(a[d], r)
            sk = lk * _skew(a[d])
            jtj[:, 3 * d:3 * d + 3, 3 * j:] += sk
            jtj[:, 3 * j:, 3 * d:3 * d + 3] += sk.transpose(0, 2, 1)
            for e in anc:
                jtj[:, 3 * d:3 * d + 3, 3 * e:3 * e + 3] += lk * (
                    np.einsum("pa,pa->p", a[d], a[e])[:, None, None] * eye3 - a[e][:, :, None] * a[d][:, None, :])
        jtj[:, 3 * j:, 3 * j:] += lk * eye3
        jtr[:, 3 * j:] += lk * r


def fit_poses_fixed(traj, weights, rot, tr, joints, parents, influences, steps: int = 2, samples: int = 4000,
                    hold: float = 0.0, targets: np.ndarray | None = None, twist: float = 0.0,
                    twist_range: float = TWIST_RANGE):
    """The bone-motion step with fixed bone lengths (module docstring), every frame, on ``samples``
    vertices spread evenly over the vertex order (every vertex when fewer; 3J + 3 unknowns per frame need
    far fewer equations than a mesh has). ``hold`` > 0 with ``targets`` (F, J, 3) also pulls each posed joint
    towards its target: the joints together weigh ``hold`` times the sampled vertices. ``twist`` > 0 keeps each
    joint's twist against its parent within +-``twist_range`` (radians; _pose_frames): a radian of twist beyond
    it weighs ``twist`` times a bone's share of the sampled vertices each TWIST_SCALE of the body's size (its
    bounding-box diagonal) off."""
    held = None
    if hold > 0 and targets is not None:
        held = (targets, np.full(len(parents), hold * min(samples, len(weights)) / len(parents)))
    turn = None
    if twist > 0:
        size = TWIST_SCALE * float(np.linalg.norm(np.ptp(traj.rest, axis=0)))
        lam = np.full(len(parents), twist * min(samples, len(weights)) / len(parents) * size * size)
        lam[[k for k, p in enumerate(parents) if p < 0]] = 0.0
        turn = (bone_axes(joints, parents), lam, float(twist_range))
    sel = np.unique(np.linspace(0, len(weights) - 1, min(samples, len(weights))).astype(np.int64))
    weights = weights[sel]
    idx = np.argsort(-weights, axis=1, kind="stable")[:, :influences]
    top = np.zeros_like(weights)                                         # the ``influences`` largest
    np.put_along_axis(top, idx, np.take_along_axis(weights, idx, axis=1), axis=1)
    mom = _pose_moments(traj.rest[sel], traj.frames[:, sel], top, parents)
    rot, tr = _pose_frames(mom, rot, tr, joints, parents, topological(parents), steps, held, turn)
    # re-orthonormalise (numerical drift) and restore the exact pivot chain
    u, _, vt = np.linalg.svd(rot)
    rot = u @ vt
    return constrain(rot, tr, joints, parents)


def fit_pivots(traj, weights, rot, tr, joints, parents, anchor, reg: float = 1e-3):
    """Rest-pose joint pivots that lower the error with rotations and weights fixed (bone lengths stay fixed
    over frames; only the rest skeleton changes). Moving pivot c_j by dc moves bone j and its whole
    subtree by (R_parent - R_j) dc at each frame, so the update is one linear least-squares problem in
    3 (J - 1) unknowns: (sum_t A_jt^T Omega_jk A_kt) dc = sum_t A_jt^T (omega^T r_t)_j with A_jt =
    R_parent,t - R_j,t, omega = W D (subtree weight sums), Omega = omega^T omega. The root pivot stays.
    Along directions the motion leaves open (a hinge's axis) a Tikhonov term, ``reg`` x the largest
    eigenvalue of the joint's block, keeps each pivot near ``anchor`` (skeletonize.sequence's joints)."""
    j = len(parents)
    omega = weights @ subtree_matrix(parents)                            # (V, J)
    big = omega.T @ omega                                                # (J, J)
    a = np.zeros_like(rot)                                               # (F, J, 3, 3)
    for k, p in enumerate(parents):
        if p >= 0:
            a[:, k] = rot[:, p] - rot[:, k]
    # omega^T (q - LBS) without the (V, 3F) residual: omega^T q - (omega^T lifted) X (lbs_by_vertex), omega
    # sparse (a vertex's bones' ancestors only; a sparse product also keeps BLAS threads off this thin shape)
    from scipy.sparse import csr_matrix

    om_t = csr_matrix(omega.T)
    x = np.concatenate([rot, tr[..., None]], axis=-1).transpose(1, 3, 0, 2).reshape(4 * j, -1)   # (4J, 3F)
    vh = np.c_[traj.rest, np.ones(len(traj.rest))]
    lifted = (weights[:, :, None] * vh[:, None, :]).reshape(len(vh), 4 * j)
    rhs_vec = (np.asarray(om_t @ traj.by_vertex) - np.asarray(om_t @ lifted) @ x).reshape(j, -1, 3).transpose(1, 0, 2)   # (F, J, 3)
    ata = np.einsum("fjab,fkac->jkbc", a, a)                             # sum_t A_j^T A_k
    lhs = (big[:, :, None, None] * ata).transpose(0, 2, 1, 3).reshape(3 * j, 3 * j)
    rhs = np.einsum("fjab,fja->jb", a, rhs_vec).ravel()
    basis = []
    for k in range(j):
        block = lhs[3 * k:3 * k + 3, 3 * k:3 * k + 3]
        ev, vec = np.linalg.eigh(block)
        lam = reg * max(float(ev[-1]), 1e-30)
        lhs[3 * k:3 * k + 3, 3 * k:3 * k + 3] += lam * np.eye(3)
        rhs[3 * k:3 * k + 3] += lam * (anchor[k] - joints[k])
        basis.append(vec[:, ev > 0.01 * max(float(ev[-1]), 1e-30)])   # directions the motion determines
    keep = np.repeat([p >= 0 for p in parents], 3)
    lhs, rhs = lhs[np.ix_(keep, keep)], rhs[keep]
    dc = np.zeros(3 * j)
    dc[keep] = np.linalg.solve(lhs, rhs)
    dc = dc.reshape(j, 3)
    for k in range(j):  # no move along a hinge's axis (or any direction the data leave open)
        dc[k] = basis[k] @ (basis[k].T @ dc[k])
    joints = joints + dc
    rot, tr = constrain(rot, tr, joints, parents)
    return joints, rot, tr


def fit_rest(traj: Trajectories, weights, rot, tr, anchor: np.ndarray, reg: float = 1e-6) -> np.ndarray:
    """Rest positions that the skinned motion fits best, weights and bone motions fixed: per vertex
    min_u sum_t |A_t u + b_t - q_t|^2 + reg * F |u - anchor|^2, with A_t = sum_j w_j R_tj and
    b_t = sum_j w_j t_tj (a 3x3 system). A posed frame used as the rest shape is not exactly an LBS rest
    shape where bones blend; this removes that error (Dem Bones keeps the given rest shape)."""
    # from per-bone-pair sums over frames (no (V, F, 3, 3) array): sum_t A_t^T A_t = sum_jk w_j w_k G_jk with
    # G_jk = sum_t R_tj^T R_tk; sum_t A_t^T b_t = sum_jk w_j w_k H_jk, H_jk = sum_t R_tj^T t_tk; and
    # sum_t A_t^T q_t = sum_j w_j C_j, C_vj = sum_t R_tj^T q_vt
    f, j = rot.shape[:2]
    v = len(weights)
    g = np.einsum("fjab,fkac->jkbc", rot, rot).reshape(j * j, 9)
    h = np.einsum("fjab,fka->jkb", rot, tr).reshape(j * j, 3)
    c = (traj.by_vertex @ rot.transpose(0, 2, 1, 3).reshape(3 * f, 3 * j)).reshape(v, j, 3)
    gh = np.c_[g, h]
    k = int((weights > 0).sum(1).max()) if v else 0
    if v * j * j <= BLOCK or 12 * k * k >= j * j:          # every bone pair, in blocks of vertices when large
        step = v if v * j * j <= BLOCK else max(1, BLOCK // (j * j))
        both = np.concatenate([(weights[s:s + step, :, None] * weights[s:s + step, None, :]).reshape(-1, j * j) @ gh
                               for s in range(0, v, step)])
    else:       # many bones (helpers): each vertex's few non-zero weights' pairs only, in blocks of vertices
        top = np.argpartition(-weights, k - 1, axis=1)[:, :k]
        wk = np.take_along_axis(weights, top, axis=1)
        pairs = (top[:, :, None] * j + top[:, None, :]).reshape(v, k * k)
        ww = (wk[:, :, None] * wk[:, None, :]).reshape(v, k * k)
        step = max(1, BLOCK // (12 * k * k))
        both = np.concatenate([np.einsum("vp,vpc->vc", ww[s:s + step], gh[pairs[s:s + step]])
                               for s in range(0, v, step)])
    lhs = both[:, :9].reshape(v, 3, 3) + reg * f * np.eye(3)
    rhs = np.einsum("vj,vjb->vb", weights, c) - both[:, 9:] + reg * f * anchor
    return np.linalg.solve(lhs, rhs[..., None])[..., 0]


def repose(traj: Trajectories, faces, parents, weights, rot, tr, joints, turns, new_joints, *, influences: int,
           smooth: float, rounds: int = 2, refits: int = 0, hold: float = 0.0, targets=None, twist: float = 0.0,
           twist_range: float = TWIST_RANGE):
    """The same skinned motion about another rest pose: each bone j turned about its joint,
    A_j: x -> G_j (x - p_j) + p'_j (``turns`` G (J, 3, 3), ``new_joints`` p'), so its motion becomes
    M_tj A_j^-1 (the joint still goes where it went: rotation-only joints stay so, bone lengths unchanged).
    The rest shape is the old one skinned by A, then refit (fit_rest) to the frames, and ``rounds`` times the
    weights and the rest shape again: an LBS rest shape does not turn exactly where bones blend (child_rope,
    27 frames: rms 23.6 mm captured, 31.7 turned, 28.1 after two rounds). ``refits`` more rounds then also
    refit the bone motions (fit_poses_fixed about the new rest joints: still rotation-only, the same bone
    lengths) before the weights and the rest shape: the SSDR alternation carried on about the new rest pose,
    so the posed joints move off the captured rig's (child_rope segment 79-105: 27.8 -> 21.3 mm after 6; the
    captured rig 22.4); of the last plain round and the refit rounds, the one with the lowest error is kept.
    Returns (trajectories with the new rest, weights, rotations, translations)."""
    from nodes.common.meshops import vertex_neighbours

    g = np.asarray(turns, np.float64)
    shift = new_joints - np.einsum("jab,jb->ja", g, joints)                    # A_j = (G_j, p'_j - G_j p_j)
    posed = lbs(traj.rest, weights, g, shift)
    gt = g.transpose(0, 2, 1)
    rot2 = np.einsum("fjab,jbc->fjac", rot, gt)                                # R G^T
    tr2 = tr + np.einsum("fjab,jb->fja", rot, joints - np.einsum("jab,jb->ja", gt, new_joints))
    moved = traj.with_rest(posed)
    moved = moved.with_rest(fit_rest(moved, weights, rot2, tr2, posed))
    if rounds or refits:
        _, edges = edge_length_graph(posed, faces)
        nbr = vertex_neighbours(faces, len(posed))
        diag = float(np.linalg.norm(np.ptp(posed, axis=0)))
    best = None
    for k in range(rounds + refits):
        if k >= rounds:
            rot2, tr2 = fit_poses_fixed(moved, weights, rot2, tr2, new_joints, parents, influences, hold=hold,
                                        targets=targets, twist=twist, twist_range=twist_range)
        cand = candidates(moved.rest, np.argmax(weights, 1), edges, parents, len(new_joints), 0.03 * diag)
        weights = fit_weights(moved, rot2, tr2, cand, weights, nbr, influences=influences, smooth=smooth)
        moved = moved.with_rest(fit_rest(moved, weights, rot2, tr2, moved.rest))
        if refits and k >= rounds - 1:   # the refit rounds need not lower the error each time: the best one kept
            total = float((errors(moved, weights, rot2, tr2)[0] ** 2).mean())
            if best is None or total < best[0]:
                best = (total, moved, weights, rot2, tr2)
    return best[1:] if best else (moved, weights, rot2, tr2)


# ---------------------------------------------------------------- bone motions: free (SSDR)
def fit_poses_free(traj, weights, rot, tr, only=None):
    """SSDR's bone update: each bone (of ``only``, default all) a weighted Procrustes fit to what the other bones
    leave unexplained."""
    rot, tr = rot.copy(), tr.copy()
    rest, q = traj.rest, traj.frames
    pred = lbs(rest, weights, rot, tr)                                   # (F, V, 3)
    for j in (range(weights.shape[1]) if only is None else only):
        idx = np.flatnonzero(weights[:, j] > 1e-8)
        if len(idx) < 3:
            continue
        wj = weights[idx, j]
        mine = np.einsum("fab,vb->fva", rot[:, j], rest[idx]) + tr[:, j, None]
        others = pred[:, idx] - wj[None, :, None] * mine
        target = (q[:, idx] - others) / wj[None, :, None]
        om = wj * wj
        om = om / om.sum()
        pbar = om @ rest[idx]
        qbar = np.einsum("v,fva->fa", om, target)
        cov = np.einsum("v,va,fvb->fab", om, rest[idx] - pbar, target - qbar[:, None])
        u, _, vt = np.linalg.svd(cov)
        d = np.sign(np.linalg.det(u) * np.linalg.det(vt))
        vt[:, 2] *= d[:, None]
        r = np.einsum("fba,fcb->fac", vt, u)
        t = qbar - np.einsum("fab,b->fa", r, pbar)
        rot[:, j], tr[:, j] = r, t
        new = np.einsum("fab,vb->fva", r, rest[idx]) + t[:, None]
        pred[:, idx] = others + wj[None, :, None] * new
    return rot, tr


# ---------------------------------------------------------------- helper bones
HELPER = "helper_"      # a helper bone's name starts so: a free rigid bone under a template bone (fit_helpers)
HELPER_VERTICES = 40    # a host bone gets at most one helper per this many of its vertices


def is_helper(name: str) -> bool:
    return name.startswith(HELPER)


def family_weights(weights, parents, names) -> np.ndarray:
    """(V, J) the weights with each helper bone's added to its host's (a helper is a leaf that moves under it): what
    a body bone skins with its helpers, for the tests that speak of the body's bones (thickness, weightless)."""
    out = np.array(weights, np.float64)
    for h in (j for j, n in enumerate(names) if is_helper(n)):
        out[:, parents[h]] += out[:, h]
    return out


def _procrustes(src, dst):
    """Rigid (R (F, 3, 3), t (F, 3)) taking points ``src`` (V, 3) closest to ``dst`` (F, V, 3) per frame."""
    ps, pd = src.mean(0), dst.mean(1)
    cov = np.einsum("va,fvb->fab", src - ps, dst - pd[:, None])
    u, _, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(u) * np.linalg.det(vt))
    vt[:, 2] *= d[:, None]
    r = np.einsum("fba,fcb->fac", vt, u)
    return r, pd - np.einsum("fab,b->fa", r, ps)


def _merge_candidates(a, b):
    """Row-wise union of two (V, C) candidate lists (-1 padded)."""
    both = np.concatenate([a, b], axis=1)
    both = np.sort(np.where(both < 0, np.iinfo(np.int64).max, both), axis=1)
    dup = np.zeros_like(both, bool)
    dup[:, 1:] = both[:, 1:] == both[:, :-1]
    both = np.where(dup | (both == np.iinfo(np.int64).max), -1, both)
    order = np.argsort(both < 0, axis=1, kind="stable")
    both = np.take_along_axis(both, order, axis=1)
    return both[:, :int((both >= 0).sum(1).max())]


def fit_helpers(traj: Trajectories, faces, weights, rot, tr, joints, parents, names, count: int, *, influences: int,
                smooth: float, iterations: int = 10, tol: float = 1e-3, rest_fit: bool = True, rig_poses=None,
                seed: int = 0, log=None, progress=None):
    """``count`` helper bones added to a fitted rig, each a free rigid bone (SSDR's, as Dem Bones moves them) under a
    template bone (its host), for what rotation-only limbs cannot follow (loose clothes, soft tissue).

    Helpers go one at a time to the host whose vertices' LBS error per helper is the largest (at most one per
    HELPER_VERTICES of its vertices). A host's vertices are clustered by what LBS leaves at them over the frames
    (k-means, one cluster more than its helpers: the one with the least error in all stays the host's; an empty one
    gives no helper); each other cluster's rigid motion starts a helper. Then weights (over the rig's and the
    helpers' bones, <= ``influences``), the helpers' motions, the rig's own bones' motions (``rig_poses``:
    fit_poses_fixed's keywords (hold, targets, twist, twist_range) for rotation-only joints, refitted against what
    the helpers leave, lengths and pivots as they were; "free": every bone as SSDR moves it; None: the rig's motion
    kept) and (``rest_fit``) the rest shape alternate until an iteration gains less than ``tol``; an iteration that
    loses (the first one against the rig alone) is undone. A helper that skins nothing is dropped; a helper's pivot
    is the weighted centre of the rest vertices it skins (a free bone's skinning does not depend on its pivot; there
    its motion carries the pivot along with its patch of surface: child_rope's helpers pivoted on their host bone put
    168 of 9200 posed (frame, joint) pairs of segment 0 beyond their bones' thickness outside the body, up to 15 cm).
    Returns (rest, weights, rot, tr, joints, parents, names, history)."""
    from scipy.cluster.vq import kmeans2

    from nodes.common.meshops import vertex_neighbours

    f, j = rot.shape[:2]
    rest = traj.rest
    v = len(rest)
    res = lbs(rest, weights, rot, tr) - traj.frames                              # (F, V, 3)
    err = (res ** 2).sum(2).sum(0)                                                # (V,) squared error over frames
    host = np.argmax(weights, axis=1)
    own = np.bincount(host, minlength=j)
    share = np.bincount(host, weights=err, minlength=j)
    cap = own // HELPER_VERTICES
    quota = np.zeros(j, int)
    for _ in range(count):                           # one at a time to the host with the most error per helper
        room = quota < cap
        if not room.any():
            break
        quota[np.argmax(np.where(room, share / (quota + 1), -1.0))] += 1
    labels = host.copy()
    new_joints, new_parents, new_names = [np.asarray(joints, np.float64)], list(parents), list(names)
    new_rot, new_tr = [rot], [tr]
    rng = np.random.default_rng(seed)
    for b in np.flatnonzero(quota):
        idx = np.flatnonzero(host == b)
        # clusters of what LBS leaves at each vertex over the frames (child_rope's segment 1, 48 helpers: 9.6 mm rms
        # median per frame; of the trajectories themselves 9.5, of both with the positions weighted in 9.8)
        with warnings.catch_warnings():                # an empty cluster: fewer helpers here
            warnings.simplefilter("ignore")
            _, lab = kmeans2(res[:, idx].transpose(1, 0, 2).reshape(len(idx), -1), int(quota[b]) + 1, minit="++",
                             seed=rng)
        size = np.bincount(lab, minlength=int(quota[b]) + 1)
        total = np.bincount(lab, weights=err[idx], minlength=len(size))
        found = np.flatnonzero(size > 0)
        found = found[np.argsort(-total[found], kind="stable")]
        # the cluster with the least error in all stays the host's (child_rope, 96 helpers: frames within both goals
        # 185 of 200; the least error per vertex instead, which leaves the host a large well-fitted part: 174)
        for k in found[:-1]:
            members = idx[lab == k]
            if len(members) < 3:
                continue
            r, t = _procrustes(rest[members], traj.frames[:, members])
            labels[members] = len(new_parents)
            new_joints.append(rest[members].mean(0)[None])
            new_parents.append(int(b))
            new_names.append(f"{HELPER}{names[b]}_{len(new_names) - len(names) + 1}")
            new_rot.append(r[:, None])
            new_tr.append(t[:, None])
    helpers = list(range(j, len(new_parents)))
    if not helpers:
        return rest, weights, rot, tr, joints, list(parents), list(names), []
    joints = np.concatenate(new_joints)
    rot, tr = np.concatenate(new_rot, axis=1), np.concatenate(new_tr, axis=1)
    total = len(new_parents)
    w = np.zeros((v, total))
    w[:, :j] = weights
    _, edges = edge_length_graph(rest, faces)
    nbr = vertex_neighbours(faces, v)
    diag = float(np.linalg.norm(np.ptp(rest, axis=0)))
    cand = _merge_candidates(candidates(rest, host, edges, new_parents, total, 0.03 * diag),
                             candidates(rest, labels, edges, new_parents, total, 0.03 * diag))
    rmse, _ = errors(traj, w, rot, tr)                 # the rig alone (helpers at 0): an iteration must beat it
    history, prev, best = [], float(np.sqrt((rmse ** 2).mean())), (traj, w, rot, tr)
    anchor = traj.rest
    for it in range(iterations):
        w = fit_weights(traj, rot, tr, cand, w, nbr, influences=influences, smooth=smooth)
        rot, tr = fit_poses_free(traj, w, rot, tr, only=helpers)
        if rig_poses == "free":          # free rigid bones: every bone's motion again
            rot, tr = fit_poses_free(traj, w, rot, tr)
        elif rig_poses is not None:      # the rig's own bones again, rotation-only, against what the helpers leave
            others = traj.frames - lbs(traj.rest, w[:, j:], rot[:, j:], tr[:, j:])
            rot[:, :j], tr[:, :j] = fit_poses_fixed(Trajectories(traj.rest, others), w[:, :j], rot[:, :j], tr[:, :j],
                                                    joints[:j], new_parents[:j], influences, **rig_poses)
        if rest_fit:
            traj = traj.with_rest(fit_rest(traj, w, rot, tr, anchor))
        rmse, _ = errors(traj, w, rot, tr)
        now = float(np.sqrt((rmse ** 2).mean()))
        if log:
            log(f"skin: helper bones, iteration {it + 1}/{iterations}, rms {1000 * now:.4g} mm, {len(helpers)} helpers")
        if progress:
            progress(it + 1, iterations, f"helper iterations, rms {1000 * now:.3g} mm")
        if now > prev:
            traj, w, rot, tr = best
            break
        history.append(now)
        if tol > 0 and prev - now < max(tol * prev, FLOOR * diag):
            break
        prev, best = now, (traj, w, rot, tr)
    keep = list(range(j)) + [h for h in helpers if w[:, h].max() > 0]      # a helper that skins nothing goes (a leaf)
    for h in keep[j:]:      # its pivot: the weighted centre of what it skins (its motion carries it with the surface)
        joints[h] = w[:, h] @ traj.rest / w[:, h].sum()
    return (traj.rest, w[:, keep], rot[:, keep], tr[:, keep], joints[keep], [new_parents[b] for b in keep],
            [new_names[b] for b in keep], history)


# ---------------------------------------------------------------- joints stay in the body
def drop_weightless(weights, rot, tr, joints, parents, labels, pinned: bool = True):
    """Merge every non-root bone that is the strongest influence of no vertex into its nearest kept
    ancestor: a bone that skins nothing has no data term, so its pivot and rotation drift freely (a leaf
    joint 1 m out of the body). Its weights go to that ancestor, its children are re-parented to it (and
    with ``pinned``, rotation-only joints, their pivots then follow it: constrain). ``labels`` (V,) bone per
    vertex (the candidates' parts) are mapped the same way. Returns (kept indices, weights, rot, tr, joints, parents, labels)."""
    j = len(parents)
    count = np.bincount(np.argmax(weights, axis=1), minlength=j)
    drop = (count == 0) & (np.asarray(parents) >= 0)
    if not drop.any():
        return list(range(j)), weights, rot, tr, joints, parents, labels

    def home(b):                                   # b itself if kept, else its nearest kept ancestor
        while drop[b]:
            b = parents[b]
        return b

    kept = [b for b in range(j) if not drop[b]]
    index = {b: i for i, b in enumerate(kept)}
    to = np.array([index[home(b)] for b in range(j)])
    merged = np.zeros((len(weights), len(kept)))
    np.add.at(merged.T, to, weights.T)
    new_parents = [-1 if parents[b] < 0 else index[home(parents[b])] for b in kept]
    rot, tr = rot[:, kept], tr[:, kept]
    if pinned:
        rot, tr = constrain(rot, tr, joints[kept], new_parents)
    return kept, merged, rot, tr, joints[kept], new_parents, to[labels]


def winding_numbers(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, batch: int = 8) -> np.ndarray:
    """Generalized winding number of each point (P,) w.r.t. a triangle mesh (Jacobson et al. 2013, "Robust
    inside-outside segmentation using generalized winding numbers", doi:10.1145/2461912.2461916): the
    signed solid angles of the triangles (van Oosterom & Strackee) over 4 pi; about 1 inside a closed
    outward-oriented mesh, 0 outside, graceful across small holes. The corners' coordinates as nine (T,)
    arrays and ``batch`` points at a time, products written out per axis (no reductions over an axis of 3):
    winding_numbers_reference's formula, 2-3x faster (skin's posed-joint report on child_rope's segments of 79 / 27 /
    94 frames: 8.1 / 2.4 / 8.0 -> 3.5 / 0.8 / 3.0 s, against 18-21 s for the skin itself)."""
    points = np.asarray(points, np.float64)
    tri = np.asarray(vertices, np.float64)[faces]                            # (T, 3, 3)
    cols = [np.ascontiguousarray(tri[:, k, c]) for k in range(3) for c in range(3)]
    out = np.empty(len(points))
    for s in range(0, len(points), batch):
        p = points[s:s + batch]
        ax, ay, az, bx, by, bz, cx, cy, cz = (cols[i][None, :] - p[:, i % 3, None] for i in range(9))
        la = np.sqrt(ax * ax + ay * ay + az * az)
        lb = np.sqrt(bx * bx + by * by + bz * bz)
        lc = np.sqrt(cx * cx + cy * cy + cz * cz)
        det = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
        den = (la * lb * lc + (ax * bx + ay * by + az * bz) * lc + (bx * cx + by * cy + bz * cz) * la
               + (cx * ax + cy * ay + cz * az) * lb)
        out[s:s + batch] = 2.0 * np.arctan2(det, den).sum(axis=1) / (4 * np.pi)
    return out


def winding_numbers_reference(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """winding_numbers, one point at a time with vector products (the formula as written)."""
    tri = vertices[faces]                                                   # (T, 3, 3)
    out = np.empty(len(points))
    for i, p in enumerate(points):
        a, b, c = (tri[:, k] - p for k in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
        det = np.einsum("ta,ta->t", a, np.cross(b, c))
        den = la * lb * lc + (a * b).sum(1) * lc + (b * c).sum(1) * la + (c * a).sum(1) * lb
        out[i] = 2.0 * np.arctan2(det, den).sum() / (4 * np.pi)
    return out


def bone_thickness(rest, weights, joints, parents) -> np.ndarray:
    """(J,) median distance from each bone's vertices (those it is the strongest influence of) to the
    bone's segments: its pivot to each child's pivot, for a leaf its pivot to the tip estimate (the pivot
    mirrored through its vertices' centroid). 0 for a bone that skins nothing."""
    strongest = np.argmax(weights, axis=1)
    out = np.zeros(len(parents))
    for b in range(len(parents)):
        pts = rest[strongest == b]
        if not len(pts):
            continue
        ends = [joints[k] for k, p in enumerate(parents) if p == b] or [2 * pts.mean(0) - joints[b]]
        d = np.full(len(pts), np.inf)
        for e in ends:
            seg = e - joints[b]
            t = np.clip((pts - joints[b]) @ seg / max(float(seg @ seg), 1e-30), 0.0, 1.0)
            d = np.minimum(d, np.linalg.norm(pts - (joints[b] + t[:, None] * seg), axis=1))
        out[b] = float(np.median(d))
    return out


def joint_clearance(rest, faces, weights, joints, parents, lazy: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(outside, limit), each (J,): how far each joint is outside the rest mesh (0 inside, by the winding
    number; else the distance to the nearest vertex, within half an edge of the surface's) and the
    thickness of the thicker of the two bones that meet at it (its own and its parent's, bone_thickness).
    A joint with outside > limit has left the body. ``lazy``: the winding number (the costly part) only
    where the nearest vertex is farther than the limit; a nearer joint passes on either side and gets that
    distance (an upper bound) as ``outside``."""
    from scipy.spatial import cKDTree

    dist = cKDTree(rest).query(joints)[0]
    th = bone_thickness(rest, weights, joints, parents)
    limit = np.array([max(th[b], th[p] if p >= 0 else 0.0) for b, p in enumerate(parents)])
    need = dist > limit if lazy else np.ones(len(joints), bool)
    inside = np.zeros(len(joints), bool)
    inside[need] = winding_numbers(joints[need], rest, faces) > 0.5
    return np.where(inside, 0.0, dist), limit


def posed_clearance(frames: np.ndarray, faces: np.ndarray, rot, tr, joints, near) -> np.ndarray:
    """(F, J) how far each posed joint (rot, tr applied to the rest ``joints``) is outside the frame's mesh:
    0 inside (winding number), else the distance to the frame's nearest vertex; a joint within ``near`` (J,)
    of a vertex gets that distance without the inside test (an upper bound: counts above ``near`` are exact)."""
    from scipy.spatial import cKDTree

    posed = np.einsum("fjab,jb->fja", rot, joints) + tr
    out = np.zeros(posed.shape[:2])
    for f in range(len(frames)):
        dist = cKDTree(frames[f]).query(posed[f])[0]
        need = dist > near
        inside = np.zeros(len(dist), bool)
        inside[need] = winding_numbers(posed[f][need], frames[f], faces) > 0.5
        out[f] = np.where(inside, 0.0, dist)
    return out


# ---------------------------------------------------------------- the whole fit
FLOOR = 1e-5    # converged also when an iteration lowers the rms by less than this share of the bounding-box diagonal
                # (10 um per metre, far below a capture's noise: the synth figure's 15 iterations went 0.26 -> 0.19 mm)


def fit_skin(traj: Trajectories, faces: np.ndarray, rig: Rig, *, influences: int = 4, iterations: int = 15,
             smooth: float = 1e-6, fixed_lengths: bool = True, pivots: bool = True, rest: bool = True,
             tol: float = 1e-3, merge: bool = True, hold: float = 0.0, targets: np.ndarray | None = None,
             twist: float = 0.0, twist_range: float = TWIST_RANGE, log=None, progress=None) -> SkinFit:
    """Alternate the weights and bone-motion steps (module docstring) from the rig's rigid parts; with
    fixed lengths, ``pivots`` also moves the rest-pose joints (fit_pivots) after each bone-motion step,
    refusing a joint's move that takes it out of the body (joint_clearance); ``rest`` refits the rest shape
    (fit_rest) after it. Bones that skin no vertex are merged into their parents (drop_weightless), from
    the start and after each weights step, unless ``merge`` is off (a template's joints, kept where the body put
    them: the tree stays whole, its names complete). ``hold`` (fixed lengths) keeps the posed joints near ``targets``
    (F, J, 3) and ``twist`` each joint's twist against its parent within ``twist_range`` (fit_poses_fixed; like
    ``hold``, a trade against the LBS error, which alone judges the iterations below). Stops when
    an iteration lowers the total rms by less than
    ``tol`` of its previous value or by less than ``FLOOR`` of the bounding-box diagonal (``tol`` 0: every
    iteration runs; an iteration that raises it is undone). ``log(str)`` gets a line per iteration."""
    from nodes.common.meshops import vertex_neighbours

    joints = np.asarray(rig.joints, np.float64)
    anchor_joints = joints
    parents = list(rig.parents)
    labels = np.asarray(rig.labels)
    kept = list(range(len(parents)))
    _, edges = edge_length_graph(traj.rest, faces)
    nbr = vertex_neighbours(faces, len(traj.rest))
    diag = float(np.linalg.norm(np.ptp(traj.rest, axis=0)))
    weights = np.zeros((len(traj.rest), len(parents)))
    weights[np.arange(len(traj.rest)), labels] = 1.0
    rot, tr = rig.rotations.copy(), rig.translations.copy()

    def drop(weights, rot, tr, joints, parents, labels):
        nonlocal kept, anchor_joints
        if not merge:
            return weights, rot, tr, joints, parents, labels
        idx, weights, rot, tr, joints, new_parents, labels = drop_weightless(weights, rot, tr, joints, parents, labels,
                                                                            pinned=fixed_lengths)
        if len(idx) < len(parents):
            if log:
                log(f"skin: {len(parents) - len(idx)} bone(s) skin no vertex, merged into their parents: "
                    f"{sorted(set(kept) - {kept[i] for i in idx})}")
            kept, anchor_joints = [kept[i] for i in idx], anchor_joints[idx]
        return weights, rot, tr, joints, new_parents, labels

    weights, rot, tr, joints, parents, labels = drop(weights, rot, tr, joints, parents, labels)
    cand = candidates(traj.rest, labels, edges, parents, len(parents), 0.03 * diag)
    anchor = traj.rest
    if fixed_lengths:
        rot, tr = constrain(rot, tr, joints, parents)
        rot, tr = fit_poses_fixed(traj, weights, rot, tr, joints, parents, influences, steps=4, hold=hold,
                                  targets=None if targets is None else targets[:, kept], twist=twist,
                                  twist_range=twist_range)
    history = []
    refused = 0
    prev, best = np.inf, None
    for it in range(iterations):
        weights = fit_weights(traj, rot, tr, cand, weights, nbr, influences=influences, smooth=smooth)
        count = len(parents)
        weights, rot, tr, joints, parents, labels = drop(weights, rot, tr, joints, parents, labels)
        if len(parents) < count:
            cand = candidates(traj.rest, labels, edges, parents, len(parents), 0.03 * diag)
            prev, best = np.inf, None           # another model: no comparison with the last iteration
        if fixed_lengths:
            rot, tr = fit_poses_fixed(traj, weights, rot, tr, joints, parents, influences, hold=hold,
                                      targets=None if targets is None else targets[:, kept], twist=twist,
                                      twist_range=twist_range)
            if pivots:
                moved, rot, tr = fit_pivots(traj, weights, rot, tr, joints, parents, anchor_joints)
                outside, limit = joint_clearance(traj.rest, faces, weights, moved, parents, lazy=True)
                bad = outside > limit
                if bad.any():   # out of the body: the data leave that joint open; keep it where it was
                    refused += int(bad.sum())
                    moved[bad] = joints[bad]
                    rot, tr = constrain(rot, tr, moved, parents)
                joints = moved
        else:
            rot, tr = fit_poses_free(traj, weights, rot, tr)
        if rest:
            traj = traj.with_rest(fit_rest(traj, weights, rot, tr, anchor))
        rmse, _ = errors(traj, weights, rot, tr)
        total = float(np.sqrt((rmse ** 2).mean()))
        if log:
            log(f"skin: iteration {it + 1}/{iterations}, rms {1000 * total:.4g} mm, {len(parents)} bones")
        if progress:
            progress(it + 1, iterations, f"iterations, rms {1000 * total:.3g} mm")
        if total > prev and best is not None:   # worse: undo this iteration and stop
            traj, weights, rot, tr, joints = best
            break
        history.append(total)
        if tol > 0 and prev - total < max(tol * prev, FLOOR * diag):
            break
        prev, best = total, (traj, weights, rot, tr, joints)
    rmse, mx = errors(traj, weights, rot, tr)
    return SkinFit(traj.rest, weights, rot, tr, joints, parents, rmse, mx, history, kept, refused)
