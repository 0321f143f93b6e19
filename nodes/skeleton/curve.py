"""Curve skeleton of a solid (a voxel volume or a closed mesh), simplified into a joint tree.

The centre lines are found the way TEASAR does (Sato et al. 2000; what kimimaro implements): a distance
field to the boundary (DBF, scipy's exact EDT) makes paths near the surface expensive, and from a root at
one extremity (the end of its longest extent) the cheapest paths through the solid run along its middle.
The voxel farthest from the root
(plain geodesic distance) is joined to the root along that cheap path, every voxel within ``scale`` local
radii (+ ``const`` voxels) of the path is marked as explained, and the next farthest voxel not yet
explained is joined to the skeleton built so far, until none is left. The union of the paths is a tree.

Then it is made into a joint tree: branches ending in a leaf that are short next to the radius where they
leave the tree (surface bumps, a fat torso's corners) are cut, the tree is re-rooted at its centre (the
branch point with the smallest distance to its farthest extremity), every branch is smoothed along its arc
and simplified by Douglas-Peucker: joints sit at the root, at branch points, at bends (points farther
than ``bend`` from the chord) and at the extremities.

    occ, origin, voxel = voxelize(vertices, faces, resolution=128)
    sk = curve_skeleton(occ, origin, voxel)          # CurveSkeleton: joints, parents, names, radii, leaves
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# the 13 "forward" neighbours of the 26-neighbourhood (the other 13 are their negatives)
_OFFSETS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                     if (i, j, k) > (0, 0, 0)], dtype=np.int64)


# ---------------------------------------------------------------- voxelization
def voxelize(vertices: np.ndarray, faces: np.ndarray, resolution: int, pad: int = 2):
    """Solid voxelization of a closed triangle mesh by ray parity along z through every voxel column.

    Returns (occupancy bool (nx, ny, nz), origin (3,) = corner of voxel 0, voxel edge length): a voxel is
    inside when its centre is. ``resolution`` voxels span the mesh's longest side; ``pad`` empty voxels
    surround it. A column crossing the surface an odd number of times (an open mesh) drops its last
    crossing."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    lo, hi = v.min(axis=0), v.max(axis=0)
    voxel = float((hi - lo).max()) / resolution
    if not voxel > 0:
        raise ValueError("the mesh has no extent")
    origin = lo - pad * voxel
    shape = np.ceil((hi - lo) / voxel).astype(np.int64) + 2 * pad
    # grid units in which voxel (i, j, k) has its centre at (i, j, k); a tiny offset keeps centres off edges
    g = (v - origin) / voxel - 0.5 + np.array([1.3e-7, 2.9e-7, 0.0])
    tri = g[f]                                                         # (F, 3, 3)
    x0 = np.ceil(tri[:, :, 0].min(axis=1)).astype(np.int64)
    x1 = np.floor(tri[:, :, 0].max(axis=1)).astype(np.int64)
    y0 = np.ceil(tri[:, :, 1].min(axis=1)).astype(np.int64)
    y1 = np.floor(tri[:, :, 1].max(axis=1)).astype(np.int64)
    nx_, ny_ = np.maximum(x1 - x0 + 1, 0), np.maximum(y1 - y0 + 1, 0)
    count = nx_ * ny_
    t = np.repeat(np.arange(len(f)), count)                            # one row per (triangle, column)
    local = np.arange(len(t)) - np.repeat(np.cumsum(count) - count, count)
    cx = x0[t] + local % np.maximum(nx_[t], 1)
    cy = y0[t] + local // np.maximum(nx_[t], 1)
    a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
    d = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    w1 = ((cx - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (cy - a[:, 1]))
    w2 = ((b[:, 0] - a[:, 0]) * (cy - a[:, 1]) - (cx - a[:, 0]) * (b[:, 1] - a[:, 1]))
    with np.errstate(divide="ignore", invalid="ignore"):
        w1, w2 = w1 / d, w2 / d
        hit = (d != 0) & (w1 >= 0) & (w2 >= 0) & (w1 + w2 <= 1)
        z = (a[:, 2] + w1 * (b[:, 2] - a[:, 2]) + w2 * (c[:, 2] - a[:, 2]))[hit]
    col = (cx * shape[1] + cy)[hit]
    order = np.lexsort((z, col))
    z, col = z[order], col[order]
    first = np.r_[True, col[1:] != col[:-1]]
    start = np.flatnonzero(first)
    n_in_col = np.diff(np.r_[start, len(col)])
    rank = np.arange(len(col)) - np.repeat(start, n_in_col)
    keep = rank < np.repeat(n_in_col - n_in_col % 2, n_in_col)
    z, col, rank = z[keep], col[keep], rank[keep]
    enter, leave = z[rank % 2 == 0], z[rank % 2 == 1]
    cols = col[rank % 2 == 0]
    k0 = np.clip(np.ceil(enter).astype(np.int64), 0, shape[2])
    k1 = np.clip(np.floor(leave).astype(np.int64) + 1, 0, shape[2])
    diff = np.zeros((shape[0] * shape[1], shape[2] + 1), np.int32)
    ok = k1 > k0
    np.add.at(diff, (cols[ok], k0[ok]), 1)
    np.add.at(diff, (cols[ok], k1[ok]), -1)
    occ = np.cumsum(diff[:, :-1], axis=1) > 0
    return occ.reshape(shape[0], shape[1], shape[2]), origin, voxel


# ---------------------------------------------------------------- TEASAR
@dataclass
class VoxelSkeleton:
    """The raw skeleton: a tree over voxels. ``points`` (S, 3) world positions, ``parent`` (S,) index of the
    next voxel towards the root (-1 at the root), ``radius`` (S,) distance to the boundary."""

    points: np.ndarray
    parent: np.ndarray
    radius: np.ndarray


def _largest_component(occ: np.ndarray) -> np.ndarray:
    from scipy import ndimage

    labels, n = ndimage.label(occ, structure=np.ones((3, 3, 3), bool))
    if n <= 1:
        return occ
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return labels == sizes.argmax()


def _voxel_edges(occ: np.ndarray, spacing: np.ndarray):
    """26-neighbour edges between inside voxels, each once: (a, b, length), indices into
    ``np.flatnonzero(occ)``; and the voxels' (i, j, k)."""
    padded = np.pad(occ, 1)
    shape = np.array(padded.shape)
    strides = np.array([shape[1] * shape[2], shape[2], 1])
    pflat = np.flatnonzero(padded.ravel())
    index = np.full(padded.size, -1, np.int64)
    index[pflat] = np.arange(len(pflat))
    rows, cols, lengths = [], [], []
    for off in _OFFSETS:
        dst = index[pflat + off @ strides]
        good = dst >= 0
        rows.append(np.flatnonzero(good))
        cols.append(dst[good])
        lengths.append(np.full(int(good.sum()), float(np.linalg.norm(off * spacing))))
    ijk = np.stack(np.unravel_index(pflat, padded.shape), axis=1) - 1
    return np.concatenate(rows), np.concatenate(cols), np.concatenate(lengths), ijk


def _graph(a, b, w, n):
    from scipy.sparse import coo_matrix

    return coo_matrix((np.concatenate([w, w]), (np.concatenate([a, b]), np.concatenate([b, a]))), shape=(n, n)).tocsr()


def teasar(occ: np.ndarray, origin, voxel, *, scale: float = 1.5, const: float = 2.0,
           pdrf_scale: float = 1e5, pdrf_exponent: float = 8.0) -> VoxelSkeleton:
    """TEASAR centre lines of the largest 26-connected component of ``occ`` (bool (nx, ny, nz); voxel
    (i, j, k) has its centre at origin + (i + 0.5, j + 0.5, k + 0.5) * voxel). ``scale`` and ``const``
    (voxels): the radius around each path voxel that counts as explained, scale * DBF + const.
    ``pdrf_scale``, ``pdrf_exponent``: the penalty field pdrf_scale * (1 - DBF / max DBF) ** exponent + 1."""
    from scipy import ndimage
    from scipy.sparse.csgraph import dijkstra

    spacing = np.broadcast_to(np.asarray(voxel, np.float64), (3,)).copy()
    origin = np.asarray(origin, np.float64)
    occ = _largest_component(np.asarray(occ, bool))
    if not occ.any():
        raise ValueError("the volume is empty")
    flat = np.flatnonzero(occ.ravel())
    padded = np.pad(occ, 1)
    d = ndimage.distance_transform_edt(padded, sampling=spacing)[1:-1, 1:-1, 1:-1].ravel()[flat]
    cost = pdrf_scale * (1.0 - d / d.max()) ** pdrf_exponent + 1.0
    a, b, w, ijk = _voxel_edges(occ, spacing)
    plain = _graph(a, b, w, len(flat))
    penal = plain.copy()                      # same structure, edge length x mean penalty of its ends
    rows = np.repeat(np.arange(len(flat)), np.diff(penal.indptr))
    penal.data = penal.data * 0.5 * (cost[rows] + cost[penal.indices])
    pts = origin + (ijk + 0.5) * spacing
    if len(flat) == 1:
        return VoxelSkeleton(pts, np.array([-1]), d)
    # root: an extremity, the voxel farthest along the solid's longest extent (TEASAR takes the voxel
    # farthest from an arbitrary one; this one is as good for tracing and needs no search)
    axis = int(np.argmax(np.ptp(ijk, axis=0) * spacing))
    root = int(np.argmin(ijk[:, axis]))
    daf = dijkstra(plain, indices=root)
    _, pred = dijkstra(penal, indices=root, return_predecessors=True)
    valid = np.isfinite(daf)
    in_skel = np.zeros(len(flat), bool)
    in_skel[root] = True
    parent = np.full(len(flat), -1, np.int64)
    step = float(spacing.min())
    # balls are stamped into a padded grid: offsets sorted by length, a ball of radius r is a prefix
    r_max = scale * float(d.max()) + const * step
    reach = np.ceil(r_max / spacing).astype(np.int64) + 1
    axes = [np.arange(-k, k + 1) for k in reach]
    off = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    norm = np.linalg.norm(off * spacing, axis=1)
    order = np.argsort(norm, kind="stable")
    norm = norm[order]
    shape = np.array(occ.shape) + 2 * reach
    strides = np.array([shape[1] * shape[2], shape[2], 1])
    off_flat = (off[order] @ strides)
    explained = np.zeros(int(np.prod(shape)), bool)
    voxel_flat = (ijk + reach) @ strides

    def explain(ids):
        """Mark voxels within scale * DBF + const of the path as explained. Balls of path voxels a small
        fraction of their radius apart nearly coincide: every ball is represented by one of them, enlarged
        by the gap (so nothing a full ball set would mark is missed; at most a gap more is)."""
        radius = scale * d[ids] + const * step
        keep, i = [], 0
        while i < len(ids):
            keep.append(i)
            i += max(1, int(0.2 * radius[i] / step))
        keep = np.array(keep)
        gap = np.diff(np.r_[keep, len(ids) - 1]) * step * np.sqrt(3)
        counts = np.searchsorted(norm, np.minimum(radius[keep] + gap, r_max), side="right")
        centres = np.repeat(voxel_flat[ids[keep]], counts)
        within = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        explained[centres + off_flat[within]] = True
        valid[explained[voxel_flat]] = False

    explain(np.array([root]))
    while valid.any():
        target = int(np.argmax(np.where(valid, daf, -1.0)))
        path = [target]
        v = target
        while not in_skel[v]:
            p = int(pred[v])
            if p < 0:
                break
            parent[v] = p
            v = p
            path.append(v)
        ids = np.array(path)
        in_skel[ids] = True
        valid[ids] = False
        explain(ids)
    keep = np.flatnonzero(in_skel)
    remap = np.full(len(flat), -1, np.int64)
    remap[keep] = np.arange(len(keep))
    par = parent[keep]
    par = np.where(par >= 0, remap[np.maximum(par, 0)], -1)
    return VoxelSkeleton(pts[keep], par, d[keep])


# ---------------------------------------------------------------- joint tree
@dataclass
class CurveSkeleton:
    """A joint tree: ``joints`` (J, 3), ``parents`` (J,) with -1 at the root, ``names``, ``radius`` (J,)
    distance to the boundary at each joint, ``kind`` per joint (root, branch, bend, end)."""

    joints: np.ndarray
    parents: list[int]
    names: list[str] = field(default_factory=list)
    radius: np.ndarray | None = None
    kind: list[str] = field(default_factory=list)

    @property
    def leaves(self) -> list[int]:
        has_child = set(p for p in self.parents if p >= 0)
        return [j for j in range(len(self.parents)) if j not in has_child and self.parents[j] >= 0]


def _adjacency(parent: np.ndarray) -> list[list[int]]:
    adj: list[list[int]] = [[] for _ in range(len(parent))]
    for v, p in enumerate(parent):
        if p >= 0:
            adj[v].append(int(p))
            adj[int(p)].append(v)
    return adj


def _prune(sk: VoxelSkeleton, factor: float, min_length: float) -> np.ndarray:
    """Alive mask after cutting, repeatedly, leaf branches shorter than factor * radius at the branch
    point (+ min_length)."""
    n = len(sk.points)
    alive = np.ones(n, bool)
    adj = _adjacency(sk.parent)
    changed = True
    while changed:
        changed = False
        deg = np.array([sum(alive[u] for u in adj[v]) if alive[v] else 0 for v in range(n)])
        for leaf in np.flatnonzero(alive & (deg == 1)):
            if not alive[leaf] or deg[leaf] != 1:
                continue
            path, prev, v, length = [leaf], -1, leaf, 0.0
            while True:
                nxt = [u for u in adj[v] if alive[u] and u != prev]
                if len(nxt) != 1:
                    break
                length += float(np.linalg.norm(sk.points[nxt[0]] - sk.points[v]))
                prev, v = v, nxt[0]
                if deg[v] != 2:
                    break
                path.append(v)
            if deg[v] >= 3 and length < factor * sk.radius[v] + min_length:
                alive[path] = False
                deg[v] -= 1
                changed = True
    return alive


def _douglas_peucker(points: np.ndarray, tol: float) -> list[int]:
    """Indices kept by Douglas-Peucker (first and last always)."""
    keep = [0, len(points) - 1]
    stack = [(0, len(points) - 1)]
    while stack:
        i, j = stack.pop()
        if j - i < 2:
            continue
        a, b = points[i], points[j]
        ab = b - a
        seg = points[i + 1:j] - a
        L = float(ab @ ab)
        if L > 0:
            t = np.clip(seg @ ab / L, 0, 1)
            dist = np.linalg.norm(seg - t[:, None] * ab, axis=1)
        else:
            dist = np.linalg.norm(seg, axis=1)
        k = int(np.argmax(dist))
        if dist[k] > tol:
            m = i + 1 + k
            keep.append(m)
            stack += [(i, m), (m, j)]
    return sorted(set(keep))


def _smooth(points: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing along a polyline's arc (ends kept)."""
    if len(points) < 3 or sigma <= 0:
        return points
    s = np.r_[0, np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]
    w = np.exp(-0.5 * ((s[:, None] - s[None]) / sigma) ** 2)
    out = (w @ points) / w.sum(axis=1, keepdims=True)
    out[0], out[-1] = points[0], points[-1]
    return out


def joint_tree(sk: VoxelSkeleton, *, prune: float = 2.0, prune_min: float = 0.0, bend: float = 0.03,
               smooth: float = 0.0, up=(0.0, 0.0, 1.0)) -> CurveSkeleton:
    """Simplify a voxel skeleton into a joint tree (see the module docstring). ``prune``: leaf branches
    shorter than prune * radius at their branch point (+ ``prune_min``, world units) are cut; ``bend``
    (world units): Douglas-Peucker tolerance; ``smooth`` (world units): arc-length Gaussian sigma applied
    to each branch before simplification. ``up`` names a five-extremity tree (head, hands, feet)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    alive = _prune(sk, prune, prune_min)
    ids = np.flatnonzero(alive)
    remap = np.full(len(sk.points), -1, np.int64)
    remap[ids] = np.arange(len(ids))
    pts, rad = sk.points[ids], sk.radius[ids]
    par = sk.parent[ids]
    par = np.where(par >= 0, remap[np.maximum(par, 0)], -1)
    n = len(pts)
    if n == 1:
        return CurveSkeleton(pts.copy(), [-1], ["root"], rad.copy(), ["root"])
    adj = _adjacency(par)
    deg = np.array([len(a) for a in adj])
    child = np.flatnonzero(par >= 0)
    lengths = np.linalg.norm(pts[child] - pts[par[child]], axis=1)
    g = coo_matrix((np.r_[lengths, lengths], (np.r_[child, par[child]], np.r_[par[child], child])), shape=(n, n)).tocsr()
    leaves = np.flatnonzero(deg == 1)
    branch = np.flatnonzero(deg >= 3)
    candidates = branch if len(branch) else np.arange(n)
    dist = dijkstra(g, indices=candidates)
    ecc = dist[:, leaves].max(axis=1)
    root = int(candidates[np.argmin(ecc)])
    # walk the tree from the new root; key vertices: root, branch points, leaves
    order, parent = [root], np.full(n, -1, np.int64)
    seen = np.zeros(n, bool)
    seen[root] = True
    for v in order:
        for u in adj[v]:
            if not seen[u]:
                seen[u] = True
                parent[u] = v
                order.append(u)
    key = (deg != 2)
    key[root] = True
    joints, parents, kinds, radius, joint_of = [pts[root]], [-1], ["root"], [rad[root]], {root: 0}
    for v in order:  # every key vertex starts one branch per child
        if not key[v]:
            continue
        for u in adj[v]:
            if u == parent[v]:
                continue
            chain = [v, u]
            while not key[chain[-1]]:
                nxt = [w for w in adj[chain[-1]] if w != parent[chain[-1]]]
                chain.append(nxt[0])
            if deg[chain[-1]] == 1 and len(chain) > 3:
                # TEASAR's paths end on the surface: end an extremity where the branch's radius says its
                # medial axis ends (one typical radius before the tip)
                tip = pts[chain[-1]]
                r_end = float(np.median(rad[chain[max(1, len(chain) - 12):]]))
                near = np.linalg.norm(pts[chain] - tip, axis=1) < r_end
                cut = len(chain) - 1
                while cut > 1 and near[cut - 1]:
                    cut -= 1
                chain = chain[:cut + 1]
                deg_end = 1
            else:
                deg_end = deg[chain[-1]]
            line = _smooth(pts[chain], smooth)
            keep = _douglas_peucker(line, bend)
            prev = joint_of[v]
            for k in keep[1:]:
                joints.append(line[k])
                radius.append(rad[chain[k]])
                parents.append(prev)
                kinds.append(("end" if deg_end == 1 else "branch") if k == len(chain) - 1 else "bend")
                prev = len(joints) - 1
            joint_of[chain[-1]] = prev
    out = CurveSkeleton(np.array(joints), parents, [], np.array(radius), kinds)
    out.names = name_joints(out, up)
    return out


def name_joints(sk: CurveSkeleton, up=(0.0, 0.0, 1.0)) -> list[str]:
    """Joint names: "root", "joint_K" inside; extremities "end_K", or for exactly five of them (a person)
    "foot_0/1" (the two lowest along ``up``), "head" (of the other three, the nearest to the root along the
    tree: arms are longer than the neck, and a raised hand can be higher than the head) and "hand_0/1"."""
    names = ["root" if p < 0 else f"joint_{j}" for j, p in enumerate(sk.parents)]
    leaves = sk.leaves
    for k, j in enumerate(leaves):
        names[j] = f"end_{k}"
    if len(leaves) == 5:
        u = np.asarray(up, np.float64)
        u = u / (np.linalg.norm(u) or 1.0)
        h = sk.joints[leaves] @ u
        order = [leaves[i] for i in np.argsort(h, kind="stable")]
        feet, rest = order[:2], order[2:]

        def reach(j):
            length = 0.0
            while sk.parents[j] >= 0:
                length += float(np.linalg.norm(sk.joints[j] - sk.joints[sk.parents[j]]))
                j = sk.parents[j]
            return length

        head = min(rest, key=reach)
        hands = [j for j in rest if j != head]
        names[head] = "head"
        for k, j in enumerate(feet):
            names[j] = f"foot_{k}"
        for k, j in enumerate(hands):
            names[j] = f"hand_{k}"
    return names


def curve_skeleton(occ: np.ndarray, origin, voxel, *, scale: float = 1.5, const: float = 2.0, prune: float = 2.0,
                   bend: float = 2.0, smooth: float = 1.0, up=(0.0, 0.0, 1.0)) -> CurveSkeleton:
    """TEASAR centre lines of a solid, simplified into a joint tree. ``bend`` and ``smooth`` in voxels."""
    step = float(np.min(voxel))
    raw = teasar(occ, origin, voxel, scale=scale, const=const)
    return joint_tree(raw, prune=prune, prune_min=step, bend=bend * step, smooth=smooth * step, up=up)
