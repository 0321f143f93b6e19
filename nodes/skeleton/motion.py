"""A skeleton from the motion of a dynamic mesh (constant connectivity over frames): rigid parts, their
per-frame rigid transforms, joints between adjacent parts, a tree.

Rigid parts (after De Aguiar et al. 2008 and the clustering that initialises SSDR, Le & Deng 2012): the
rest mesh is cut into ``patches`` small, surface-connected patches (farthest-point seeds, geodesic Voronoi
cells on the edge graph); neighbouring patches are merged greedily, cheapest first, where the cost of a
merge is how much the best single rigid motion per frame of the union explains worse than two motions
(the increase of the summed squared Kabsch residual; each patch keeps only first and second moments over
frames, so a merge costs O(frames)). Merging stops at ``bones`` parts, or, with bones = 0, skips merges
where the smaller part would follow the union's motion worse than ``tolerance`` (rms). Vertices are then moved to the neighbouring part whose motion fits their trajectory best
(``refine`` rounds, k-means style; the parts' moments are updated by the moved vertices only, and only the
parts that changed are fitted again), and every part gets its Kabsch transform per frame.

Joints: between adjacent parts a and b the joint is the rest-pose point c that both motions move alike,
min_c sum_t |(R_a c + t_a) - (R_b c + t_b)|^2, a 3x3 linear least-squares problem per pair; along the
directions the motion does not determine (a hinge's axis, a joint that never bends) c stays nearest to the
centre of the parts' common border (a Tikhonov term). The tree is the maximum spanning tree of the parts'
adjacency (border length), rooted at the largest part; each part's joint is the one to its parent, the
root's is the root part's centroid.

    parts = rigid_parts(rest, frames, faces, bones=0)      # RigidParts: labels, transforms, adjacency
    rig = build_rig(rest, frames, faces, parts)            # Rig: joints, parents, transforms, labels
"""
from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np

from nodes.common.meshops import edge_length_graph


# ---------------------------------------------------------------- the data, in the layouts the products need
class Trajectories:
    """A dynamic mesh's rest positions (V, 3) and frames (F, V, 3), with the layouts used below computed
    once: ``by_vertex`` (V, 3F), squared norms per vertex and frame ``qq`` (F, V)."""

    def __init__(self, rest: np.ndarray, frames: np.ndarray):
        self.rest = np.ascontiguousarray(rest, np.float64)
        self.frames = np.ascontiguousarray(frames, np.float64)
        f, v = self.frames.shape[:2]
        # copied in blocks of vertices (one transposed copy strides over all frames per vertex: 4x slower),
        # squared norms as x*x + y*y + z*z (a sum over an axis of 3 is 5x slower); the same values either way
        self.by_vertex = np.empty((v, f, 3))
        for s in range(0, v, 512):
            self.by_vertex[s:s + 512] = self.frames[:, s:s + 512].transpose(1, 0, 2)
        self.by_vertex = self.by_vertex.reshape(v, 3 * f)
        x, y, z = self.frames.transpose(2, 0, 1)
        self.qq = x * x + y * y + z * z

    @property
    def count(self) -> int:
        return self.frames.shape[0]

    def with_rest(self, rest: np.ndarray) -> "Trajectories":
        """The same frames with another rest shape (no copies of the frame layouts)."""
        out = object.__new__(Trajectories)
        out.__dict__.update(self.__dict__)
        out.rest = np.ascontiguousarray(rest, np.float64)
        return out


# ---------------------------------------------------------------- Kabsch from moments
@dataclass
class Moments:
    """Sufficient statistics of a vertex set for rigid fits rest -> each frame: count n, sums of rest
    points sp (3,), of frame points sq (F, 3), of outer products spq (F, 3, 3) = sum p q^T, and of squared
    norms spp (scalar), sqq (F,)."""

    n: float
    sp: np.ndarray
    sq: np.ndarray
    spq: np.ndarray
    spp: float
    sqq: np.ndarray

    def __add__(self, o: "Moments") -> "Moments":
        return Moments(self.n + o.n, self.sp + o.sp, self.sq + o.sq, self.spq + o.spq, self.spp + o.spp, self.sqq + o.sqq)


def moments(rest: np.ndarray, frames: np.ndarray, idx: np.ndarray) -> Moments:
    p, q = rest[idx], frames[:, idx]
    return Moments(float(len(idx)), p.sum(0), q.sum(1), np.einsum("va,fvb->fab", p, q), float((p * p).sum()),
                   (q * q).sum(axis=(1, 2)))


def part_arrays(traj: Trajectories, labels: np.ndarray, b: int):
    """Moments of every part at once as arrays (n (B,), sp (B, 3), sq (B, F, 3), spq (B, F, 3, 3), spp (B,),
    sqq (B, F)): sparse one-hot products, no per-part copies."""
    from scipy.sparse import csr_matrix

    v = len(labels)
    return weighted_sums(traj, csr_matrix((np.ones(v), (labels, np.arange(v))), shape=(b, v)))


def weighted_sums(traj: Trajectories, w, vertices: np.ndarray | None = None):
    """``part_arrays``' moments with a sparse weight (B, V) of each vertex in each part (or (B, M) of only
    ``vertices``)."""
    rest, q, qq = traj.rest, traj.by_vertex, traj.qq.T
    if vertices is not None:
        rest, q, qq = rest[vertices], q[vertices], qq[vertices]
    b, f = w.shape[0], traj.count
    n = np.asarray(w.sum(1)).ravel()
    sp = w @ rest
    sq = (w @ q).reshape(b, f, 3)
    spq = np.stack([(w.multiply(rest[:, a][None])).tocsr() @ q for a in range(3)], axis=1)  # (B, 3, F*3)
    spq = spq.reshape(b, 3, f, 3).transpose(0, 2, 1, 3)
    spp = w @ (rest * rest).sum(1)
    sqq = w @ qq                                                        # (B, F)
    return n, sp, sq, spq, spp, sqq


class _Fits:
    """The current parts' moments (``part_arrays``), Kabsch motions (rot (F, B, 3, 3), tr (F, B, 3)) and
    every vertex's ``motion_errors`` under every part's motion, for labels that change a few vertices at a
    time: moving vertices updates the moments of the parts they leave and join (moments are sums: one
    signed sparse product over the moved vertices), and only those parts' motions and error columns are
    computed again, when next asked for (``errors``)."""

    def __init__(self, traj: Trajectories, labels: np.ndarray, b: int):
        self.traj = traj
        self.mom = part_arrays(traj, labels, b)
        f, v = traj.count, len(labels)
        self.rot, self.tr, self.err = np.empty((f, b, 3, 3)), np.empty((f, b, 3)), np.empty((v, b))
        self.stale = np.arange(b)

    def move(self, old: np.ndarray, new: np.ndarray):
        """Every vertex moves from part old[v] to new[v]."""
        from scipy.sparse import csr_matrix

        idx = np.flatnonzero(old != new)
        m = np.arange(len(idx))
        w = csr_matrix((np.r_[np.ones(len(idx)), -np.ones(len(idx))], (np.r_[new[idx], old[idx]], np.r_[m, m])),
                       shape=(len(self.mom[0]), len(idx)))
        self.mom = tuple(a + d for a, d in zip(self.mom, weighted_sums(self.traj, w, idx)))
        self.stale = np.union1d(self.stale, np.r_[old[idx], new[idx]])

    def keep(self, used: np.ndarray):
        """Only parts ``used`` (sorted) remain, numbered 0, 1, ... in that order."""
        self.mom = tuple(m[used] for m in self.mom)
        self.rot, self.tr, self.err = self.rot[:, used], self.tr[:, used], self.err[:, used]
        self.stale = np.flatnonzero(np.isin(used, self.stale))

    def errors(self) -> np.ndarray:
        """(V, B) ``motion_errors`` of the current motions (NaN columns for empty parts)."""
        if len(self.stale):
            p = self.stale
            with np.errstate(invalid="ignore", divide="ignore"):  # an empty part: NaN motions, never chosen
                r, t, _ = kabsch_arrays(*(m[p] for m in self.mom))
            self.rot[:, p], self.tr[:, p] = r.transpose(1, 0, 2, 3), t.transpose(1, 0, 2)
            self.err[:, p] = motion_errors(self.traj, self.rot[:, p], self.tr[:, p])
            self.stale = np.arange(0)
        return self.err


def kabsch(m: Moments) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best rigid motions rest -> frame of a moment set: (R (F, 3, 3), t (F, 3), residual (F,) = summed
    squared distances after the fit)."""
    return kabsch_arrays(np.float64(m.n), m.sp, m.sq, m.spq, np.float64(m.spp), m.sqq)


def _centred(n, sp, sq, spq, spp, sqq):
    """From moments (``kabsch_arrays``' shapes): the means pbar (..., 3) and qbar (..., F, 3), the centred
    cross sums cov = sum (p - pbar)(q - qbar)^T (..., F, 3, 3), and sum |p - pbar|^2 + |q - qbar|^2 (..., F)."""
    n = np.asarray(n, np.float64)
    pbar = sp / n[..., None]
    qbar = sq / n[..., None, None]
    cov = spq - n[..., None, None, None] * pbar[..., None, :, None] * qbar[..., :, None, :]
    spp_c = spp - n * (pbar * pbar).sum(-1)
    sqq_c = sqq - n[..., None] * (qbar * qbar).sum(-1)
    return pbar, qbar, cov, spp_c[..., None] + sqq_c


def kabsch_arrays(n, sp, sq, spq, spp, sqq):
    """``kabsch`` for moments with any leading dimensions (``part_arrays``: all parts in one SVD call):
    n (...), sp (..., 3), sq (..., F, 3), spq (..., F, 3, 3), spp (...), sqq (..., F) -> R (..., F, 3, 3),
    t (..., F, 3), residual (..., F)."""
    pbar, qbar, cov, spread = _centred(n, sp, sq, spq, spp, sqq)
    u, s, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(np.einsum("...ab,...bc->...ac", u, vt)))
    d[d == 0] = 1.0
    s = s.copy()
    s[..., 2] *= d
    vt = vt.copy()
    vt[..., 2, :] *= d[..., None]
    r = np.einsum("...ba,...cb->...ac", vt, u)                          # R = V diag(1,1,d) U^T
    t = qbar - np.einsum("...fab,...b->...fa", r, pbar)
    res = np.maximum(spread - 2 * s.sum(-1), 0.0)
    return r, t, res


def kabsch_residual(n, sp, sq, spq, spp, sqq):
    """The residual (..., F) of ``kabsch_arrays`` alone, for pricing merges: from the singular values and
    the sign of det(cov) (= det(U V^T)), an SVD without U and V (40 % cheaper). It agrees with
    ``kabsch_arrays``' residual to rounding (2e-17 of the summed squared norms on the bench figure)."""
    _, _, cov, spread = _centred(n, sp, sq, spq, spp, sqq)
    s = np.linalg.svd(cov, compute_uv=False)
    d = np.sign(np.linalg.det(cov))
    d[d == 0] = 1.0
    return np.maximum(spread - 2 * (s[..., 0] + s[..., 1] + d * s[..., 2]), 0.0)


def fit_rigid(rest: np.ndarray, frames: np.ndarray, idx: np.ndarray):
    """Kabsch transforms (R (F, 3, 3), t (F, 3)) of vertices ``idx``, rest -> each frame."""
    r, t, _ = kabsch(moments(rest, frames, idx))
    return r, t


# ---------------------------------------------------------------- mesh graph helpers
def patches(vertices: np.ndarray, faces: np.ndarray, count: int) -> np.ndarray:
    """Label (V,) of ``count`` surface patches: farthest-point seeds over geodesic (edge-graph) distance,
    each vertex to its geodesically nearest seed. Vertices no seed reaches (other components) get seeds of
    their own."""
    from scipy.sparse.csgraph import dijkstra

    g, _ = edge_length_graph(vertices, faces)
    n = len(vertices)
    count = max(1, min(count, n))
    seeds = [int(np.argmax(np.linalg.norm(vertices - vertices.mean(0), axis=1)))]
    dist = dijkstra(g, indices=seeds[0])
    while len(seeds) < count:
        far = np.where(np.isfinite(dist), dist, np.inf)
        nxt = int(np.argmax(far))
        if far[nxt] <= 0:
            break
        seeds.append(nxt)
        dist = np.minimum(dist, dijkstra(g, indices=nxt, limit=float(dist[nxt]) if np.isfinite(dist[nxt]) else np.inf))
    _, _, src = dijkstra(g, indices=seeds, min_only=True, return_predecessors=True)
    label = np.full(n, -1, np.int64)
    ok = src >= 0
    order = np.argsort(seeds, kind="stable")
    label[ok] = order[np.searchsorted(np.asarray(seeds)[order], src[ok])]
    if not ok.all():  # pieces no seed reaches: one patch each
        from scipy.sparse.csgraph import connected_components

        _, comp = connected_components(g, directed=False)
        for c in np.unique(comp[~ok]):
            label[comp == c] = label.max() + 1
    return label


def label_adjacency(labels: np.ndarray, edges: np.ndarray, k: int) -> np.ndarray:
    """(k, k) count of mesh edges joining each pair of labels (symmetric, zero diagonal)."""
    a, b = labels[edges[:, 0]], labels[edges[:, 1]]
    cut = a != b
    adj = np.zeros((k, k), np.int64)
    np.add.at(adj, (a[cut], b[cut]), 1)
    np.add.at(adj, (b[cut], a[cut]), 1)
    return adj


def _connect_components(adj: np.ndarray, centroids: np.ndarray) -> np.ndarray:
    """Join disconnected groups of the adjacency by their closest centroids (weight 1), so a tree exists."""
    from scipy.sparse.csgraph import connected_components

    adj = adj.copy()
    while True:
        n, lab = connected_components(adj > 0, directed=False)
        if n <= 1:
            return adj
        a, b = np.flatnonzero(lab == 0), np.flatnonzero(lab != 0)
        d = np.linalg.norm(centroids[a][:, None] - centroids[b][None], axis=2)
        i, j = np.unravel_index(np.argmin(d), d.shape)
        adj[a[i], b[j]] = adj[b[j], a[i]] = 1


# ---------------------------------------------------------------- rigid parts
@dataclass
class RigidParts:
    labels: np.ndarray          # (V,) part of each vertex
    rotations: np.ndarray       # (F, B, 3, 3) rest -> frame
    translations: np.ndarray    # (F, B, 3)
    adjacency: np.ndarray       # (B, B) mesh edges between parts
    residual: np.ndarray        # (B,) rms fit residual of each part over all frames


def rigid_parts(rest: np.ndarray, frames: np.ndarray, faces: np.ndarray, *, bones: int = 0, tolerance: float = 0.005,
                patch_count: int = 200, refine: int = 3, log=None) -> RigidParts:
    """Rigid parts of a dynamic mesh (module docstring). ``rest`` (V, 3), ``frames`` (F, V, 3), ``faces``
    (T, 3). ``bones``: number of parts (0: automatic); ``tolerance``: with bones = 0, the largest rms
    residual of a part, relative to the rest mesh's bounding-box diagonal. ``log(str)`` gets a line per
    phase and per removal round (progress of a long sequence)."""
    import time

    t0 = time.perf_counter()
    say = (lambda msg: log(f"skeletonize.sequence: {msg} ({time.perf_counter() - t0:.1f} s)")) if log else (lambda msg: None)
    traj = Trajectories(rest, frames)
    rest, frames = traj.rest, traj.frames
    diag = float(np.linalg.norm(np.ptp(rest, axis=0)))
    _, edges = edge_length_graph(rest, faces)
    label = patches(rest, faces, patch_count)
    k = int(label.max()) + 1
    say(f"{k} surface patches of {len(rest)} vertices, {frames.shape[0]} frames")
    target = 2 * bones if bones > 0 else 1
    labels = _merge_patches(traj, edges, label, k, target, (0.5 * tolerance * diag) ** 2 if bones <= 0 else None)
    say(f"merged into {int(labels.max()) + 1} parts")
    fits = _Fits(traj, labels, int(labels.max()) + 1)
    labels = _reassign(traj, edges, labels, refine, fits)
    labels = _eliminate(traj, edges, labels, fits, bones, (tolerance * diag) ** 2, refine, say)
    out = _finish(traj, edges, labels)
    say(f"{len(out.residual)} rigid parts")
    return out


def _pair_errors(mom, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Summed Kabsch residual of the union of parts a[i] and b[i], for all pairs in one SVD call (``mom``:
    ``part_arrays``' moment arrays)."""
    return kabsch_residual(*(m[a] + m[b] for m in mom)).sum(-1)


def _merge_patches(traj, edges, label, k, target, limit) -> np.ndarray:
    """Merge neighbouring patches greedily, cheapest first (module docstring), until ``target`` parts remain;
    with a ``limit`` (mean squared distance per vertex and frame), skip merges that would cost the smaller
    part more. Returns the part of each vertex, parts numbered in the order of their lowest patch.

    A merged part's moments are kept at its lowest patch (moments are sums). Each heap entry (key, a, b)
    is checked against the pair's latest pushed key, so older entries are stale. After a merge of a and b
    the pairs (a + b, x) are not priced at once but pushed with a lower bound of their cost, and priced
    when that bound comes to the top: a union's residual is at least the sum of its halves', so
    cost(a + b, x) >= cost(a, x) - cost(a, b) (likewise for b), and >= 0, less a margin of 1e-12 of the
    summed squared norms for rounding. A bound is never above the price, so the merges are the same as
    pricing every pair at once (1857 pairs for the bench figure, 1042 so)."""
    mom = list(part_arrays(traj, label, k))
    n, nf = mom[0], traj.count
    err = kabsch_residual(*mom).sum(-1).tolist()
    scale = (mom[4] * nf + mom[5].sum(-1)).tolist()                    # summed squared norms of each patch
    adj = _connect_components(label_adjacency(label, edges, k), mom[1] / n[:, None])
    nbr = {i: set(np.flatnonzero(adj[i]).tolist()) for i in range(k)}
    members = {i: [i] for i in range(k)}
    heap, latest = [], {}                                               # latest[a, b]: (key, residual or None)

    def price(a, b):
        for x, y, e in zip(a.tolist(), b.tolist(), _pair_errors(mom, a, b).tolist()):
            latest[x, y] = (e - err[x] - err[y], e)
            heapq.heappush(heap, (latest[x, y][0], x, y))

    def key(x, y):
        return latest[min(x, y), max(x, y)][0]

    pairs = np.array([(a, b) for a in range(k) for b in sorted(nbr[a]) if a < b], np.int64).reshape(-1, 2)
    price(pairs[:, 0], pairs[:, 1])
    alive = k
    while alive > target and heap:
        c, a, b = heapq.heappop(heap)
        if a not in members or b not in members or latest[a, b][0] != c:
            continue  # a part is gone, or the entry is stale (the pair changed since it was pushed)
        if latest[a, b][1] is None:
            price(np.array([a]), np.array([b]))                        # a bound came to the top
            continue
        if limit is not None and c / (min(n[a], n[b]) * nf) > limit:
            continue  # the smaller part would follow the other's motion worse than the tolerance
        for m in mom:
            m[a] = m[a] + m[b]
        err[a], scale[a] = latest[a, b][1], scale[a] + scale[b]
        members[a] += members.pop(b)
        for x in (nbr[a] | nbr[b]) - {a, b}:
            before = max(key(a, x) if x in nbr[a] else 0.0, key(b, x) if x in nbr[b] else 0.0)
            bound = max(before - c, 0.0) - 1e-12 * (scale[a] + scale[x])
            latest[min(a, x), max(a, x)] = (bound, None)
            heapq.heappush(heap, (bound, min(a, x), max(a, x)))
        nbr[a] = (nbr[a] | nbr.pop(b)) - {a, b}
        for x in nbr[a]:
            nbr[x].discard(b)
            nbr[x].add(a)
        alive -= 1
    part_of_patch = np.empty(k, np.int64)
    for new, (_, pts) in enumerate(sorted(members.items())):
        part_of_patch[pts] = new
    return part_of_patch[label]


def _eliminate(traj, edges, labels, fits: _Fits, bones, limit, refine, say=lambda msg: None):
    """Remove parts one at a time, the one whose vertices are best explained by their neighbouring parts'
    motions first (a part straddling a joint splits between both sides, which a merge cannot do), until
    ``bones`` remain, or (bones = 0) until removing any would cost its vertices more than ``limit`` (mean
    squared distance per vertex and frame). ``fits``: those of ``labels``, kept up to date."""
    nf = traj.count
    while True:
        used = np.unique(labels)
        labels = np.searchsorted(used, labels)
        fits.keep(used)
        b = len(used)
        if (bones > 0 and b <= bones) or b == 1:
            return labels
        say(f"removing parts: {b} left" + (f", target {bones}" if bones > 0 else ""))
        err = fits.errors()
        adj = label_adjacency(labels, edges, b) > 0
        own = err[np.arange(len(labels)), labels]
        other = np.where(adj[labels], err, np.inf)
        best = other.min(axis=1)
        count = np.bincount(labels, minlength=b)
        cost = np.bincount(labels, weights=np.where(np.isfinite(best), best - own, np.inf), minlength=b)
        cost = np.where(count > 0, cost, np.inf)
        # parts with no neighbour (a separate piece) cannot be removed
        worst = int(np.argmin(cost / np.maximum(count, 1) if bones <= 0 else cost))
        if not np.isfinite(cost[worst]) or (bones <= 0 and cost[worst] / (count[worst] * nf) > limit):
            return labels
        idx = np.flatnonzero(labels == worst)
        new = labels.copy()
        new[idx] = np.argmin(other[idx], axis=1)
        fits.move(labels, new)
        used = np.unique(new)
        fits.keep(used)
        labels = _reassign(traj, edges, np.searchsorted(used, new), refine, fits)


def _transforms(mom, nf):
    """Kabsch motions of all parts from their moments (``part_arrays``): R (F, B, 3, 3), t (F, B, 3) and the
    rms residual (B,) over ``nf`` frames."""
    n = mom[0]
    with np.errstate(invalid="ignore", divide="ignore"):  # an empty part: NaN motions, never chosen
        r, t, e = kabsch_arrays(*mom)
    res = np.sqrt(e.sum(1) / (np.maximum(n, 1.0) * nf))
    return r.transpose(1, 0, 2, 3), t.transpose(1, 0, 2), res


def motion_errors(traj: Trajectories, rot: np.ndarray, tr: np.ndarray) -> np.ndarray:
    """(V, B) squared distance, summed over frames, between each vertex's trajectory and where motion b
    takes its rest position: sum_t |R_tb v + t_tb - q_tv|^2 = vh^T G_b vh - 2 vh . (sum_t X_tb^T q_tv) + |q_v|^2
    with X = [R | t] and G_b = sum_t X^T X (no (V, B, F) array); the cross term is one product of the
    trajectories (V, 3F) with all motions (3F, 4B)."""
    f, b = rot.shape[:2]
    x = np.concatenate([rot, tr[..., None]], axis=-1)                  # (F, B, 3, 4)
    vh = np.c_[traj.rest, np.ones(len(traj.rest))]                     # (V, 4)
    xs = x.transpose(1, 0, 2, 3).reshape(b, 3 * f, 4)                  # (B, 3F, 4), rows (frame, axis)
    gram = np.einsum("bkc,bkd->bcd", xs, xs)                           # sum_t X^T X   (B, 4, 4)
    pp = (vh[:, :, None] * vh[:, None, :]).reshape(-1, 16) @ gram.reshape(b, 16).T
    cross = (traj.by_vertex @ xs.transpose(1, 0, 2).reshape(3 * f, 4 * b)).reshape(-1, b, 4)   # sum_t X^T q
    pq = np.einsum("vbc,vc->vb", cross, vh)
    return np.maximum(pp - 2 * pq + traj.qq.sum(0)[:, None], 0.0)


def _reassign(traj, edges, labels, rounds, fits: _Fits):
    """Move vertices to the neighbouring part (or their own) whose motion predicts their trajectory best
    (``fits``: those of ``labels``, kept up to date)."""
    b = int(labels.max()) + 1
    for _ in range(rounds):
        adj = label_adjacency(labels, edges, b) > 0
        np.fill_diagonal(adj, True)
        err = np.where(adj[labels], fits.errors(), np.inf)
        new = np.argmin(err, axis=1)
        new = _keep_connected(new, edges, b, labels)
        if np.array_equal(new, labels):
            break
        fits.move(labels, new)
        labels = new
    return labels


def _keep_connected(labels, edges, b, fallback):
    """Vertices of a part that ended up cut off from the part's main piece go back to ``fallback``."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    same = labels[edges[:, 0]] == labels[edges[:, 1]]
    e = edges[same]
    n = len(labels)
    nc, comp = connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)), directed=False)
    pairs, count = np.unique(labels.astype(np.int64) * nc + comp, return_counts=True)
    part, piece = pairs // nc, pairs % nc
    order = np.lexsort((piece, -count, part))            # per part: the largest piece first (lowest index on ties)
    first = order[np.r_[True, part[order][1:] != part[order][:-1]]]
    main = np.full(b, -1, np.int64)
    main[part[first]] = piece[first]
    out = labels.copy()
    stray = comp != main[labels]
    out[stray] = fallback[stray]
    if not np.array_equal(out, labels):
        empty = [i for i in range(b) if not np.any(out == i)]
        if empty:
            return fallback
    return out


def _finish(traj, edges, labels) -> RigidParts:
    used = np.unique(labels)
    labels = np.searchsorted(used, labels)
    b = len(used)
    rot, tr, res = _transforms(part_arrays(traj, labels, b), traj.count)   # summed afresh, not the updated sums
    cent = np.array([traj.rest[labels == i].mean(0) for i in range(b)])
    adj = _connect_components(label_adjacency(labels, edges, b), cent)
    return RigidParts(labels, rot, tr, adj, res)


# ---------------------------------------------------------------- joints and tree
def carry_joints(traj: Trajectories, joints: np.ndarray, parents: list[int], labels: np.ndarray,
                 reach: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Where the surface around each joint (given in the rest shape) carries it in every frame: the rest
    vertices of the joint's own part, its parent's and its children's (``labels``: each vertex's joint) within
    2 ``reach`` a of it, a = the joint's distance to the nearest rest vertex (a limb's radius at a joint on
    its centre line), weighted exp(-(d / reach a)^2) by their distance d, fitted rigidly (weighted Kabsch) rest
    -> every frame, and the joint moved with them. Only the surface near the joint counts: a part's own motion
    is a poor carrier where the part holds vertices far from it (an arm's part reaching into the torso it
    lies against), and at a bent elbow the ring around it moves between its two limbs, inside both. Returns
    (positions (F, J, 3), ``has`` (J,)): joints with fewer than 6 such vertices get none (zeros)."""
    from scipy.sparse import csr_matrix
    from scipy.spatial import cKDTree

    j = len(parents)
    tree = cKDTree(traj.rest)
    near, _ = tree.query(joints)
    floor = 2.0 * float(np.median(tree.query(traj.rest, k=2)[0][:, 1]))      # two vertex spacings
    rows, cols, vals = [], [], []
    has = np.zeros(j, bool)
    for k in range(j):
        r = reach * max(float(near[k]), floor)
        mine = [k] + ([parents[k]] if parents[k] >= 0 else []) + [c for c, q in enumerate(parents) if q == k]
        idx = np.asarray(tree.query_ball_point(joints[k], 2 * r), np.int64)
        idx = idx[np.isin(labels[idx], mine)]
        if len(idx) < 6:
            continue
        rows.append(np.full(len(idx), k))
        cols.append(idx)
        vals.append(np.exp(-((traj.rest[idx] - joints[k]) ** 2).sum(1) / (r * r)))
        has[k] = True
    out = np.zeros((traj.count, j, 3))
    if has.any():
        w = csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(j, len(labels)))
        rot, tr, _ = kabsch_arrays(*(x[has] for x in weighted_sums(traj, w)))     # (H, F, 3, 3), (H, F, 3)
        out[:, has] = (np.einsum("hfab,hb->hfa", rot, joints[has]) + tr).transpose(1, 0, 2)
    return out, has


def joint_between(ra, ta, rb, tb, near: np.ndarray, reg: float = 1e-3) -> tuple[np.ndarray, float]:
    """Rest-pose point c that motions a and b (R (F, 3, 3), t (F, 3)) move alike, nearest to ``near`` along
    undetermined directions: min sum_t |(R_a - R_b) c + t_a - t_b|^2 + reg * s |c - near|^2 (s: the system's
    scale). Returns (c, rms of the remaining mismatch over frames)."""
    a = (ra - rb).reshape(-1, 3)
    y = -(ta - tb).reshape(-1)
    ata = a.T @ a
    lam = reg * max(float(np.trace(ata)) / 3.0, 1e-12)
    c = np.linalg.solve(ata + lam * np.eye(3), a.T @ y + lam * near)
    mismatch = (a @ c - y).reshape(-1, 3)
    return c, float(np.sqrt((mismatch ** 2).sum(1).mean()))


@dataclass
class Rig:
    """A skeleton fitted to a dynamic mesh: per bone (= joint, one per rigid part) the rest-pose pivot
    ``joints`` (J, 3), ``parents``, ``names``; ``rotations`` (F, J, 3, 3) and ``translations`` (F, J, 3) take
    rest-pose points of the bone to each frame; ``labels`` (V,) the part of each vertex; ``joint_error``
    (J,) rms mismatch of the two motions at each joint (0 at the root)."""

    joints: np.ndarray
    parents: list[int]
    names: list[str]
    rotations: np.ndarray
    translations: np.ndarray
    labels: np.ndarray
    joint_error: np.ndarray
    residual: np.ndarray


def build_rig(rest: np.ndarray, faces: np.ndarray, parts: RigidParts) -> Rig:
    """Joints between adjacent parts and a tree (module docstring); bones are reordered parents first."""
    from scipy.sparse.csgraph import minimum_spanning_tree

    rest = np.asarray(rest, np.float64)
    b = parts.adjacency.shape[0]
    sizes = np.bincount(parts.labels, minlength=b)
    root = int(np.argmax(sizes))
    _, edges = edge_length_graph(rest, faces)
    if b == 1:
        order, parent = [root], {root: -1}
    else:
        w = np.where(parts.adjacency > 0, 1.0 / (parts.adjacency + 1.0), 0.0)   # max border = min weight
        mst = minimum_spanning_tree(w).toarray()
        tree = (mst + mst.T) > 0
        order, parent = [root], {root: -1}
        for v in order:
            for u in np.flatnonzero(tree[v]):
                if int(u) not in parent:
                    parent[int(u)] = v
                    order.append(int(u))
    new_index = {old: i for i, old in enumerate(order)}
    joints = np.empty((b, 3))
    jerr = np.zeros(b)
    rot, tr = parts.rotations, parts.translations
    for old in order:
        i = new_index[old]
        p = parent[old]
        if p < 0:
            joints[i] = rest[parts.labels == old].mean(0)
            continue
        a, c = parts.labels[edges[:, 0]], parts.labels[edges[:, 1]]
        border = edges[((a == old) & (c == p)) | ((a == p) & (c == old))]
        near = rest[border.ravel()].mean(0) if len(border) else 0.5 * (
            rest[parts.labels == old].mean(0) + rest[parts.labels == p].mean(0))
        joints[i], jerr[i] = joint_between(rot[:, old], tr[:, old], rot[:, p], tr[:, p], near)
    perm = np.array(order)
    parents = [-1 if parent[old] < 0 else new_index[parent[old]] for old in order]
    labels = np.array([new_index[x] for x in range(b)])[parts.labels]
    names = ["root" if p < 0 else f"bone_{i}" for i, p in enumerate(parents)]
    return Rig(joints, parents, names, rot[:, perm], tr[:, perm], labels, jerr, parts.residual[perm])
