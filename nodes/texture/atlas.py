"""UV atlas by normal-direction charts: fast enough to run per frame (xatlas took 12 s for 76k faces here).

    atlas = make_atlas(vertices, faces, size=2048)      # Atlas: per-corner texel coordinates, chart per face

Charting: each face goes to the one of ``directions`` (the 6 axes, or the 6 axes and the 8 diagonals) closest
to its normal; a few majority rounds over the face neighbours remove slivers (a face only joins a direction it
still faces, normal . d > 0.2); charts are the connected components of each direction's faces (through shared
edges); charts below ``min_faces`` faces are merged into a neighbouring chart they face. Each chart is
projected orthographically onto the plane perpendicular to its direction (so no face flips) and turned to its
principal axes. Packing: charts rasterised on a grid of cells (the ``gutter`` included) are dropped
Tetris-like onto a skyline, largest first, upright or turned, at the largest scale found to fit a ``size`` x
``size`` square. Orthographic projection is injective per chart only while no part of the chart hides another
along its direction: a fold whose two sides both face the chart's direction (a carved belly behind a leg, a spiral
ramp) lands on the same texels, and one side is painted with the other's colours. So the charts are checked before
the packing, laid out apart on a canvas of the atlas's size (``shelf_layout``) and rasterised once: of two faces of
a chart where a test point of one (its centroid or a point towards a corner) lies inside the other
(``hidden_faces``), the one further back along the direction is hidden, and the hidden faces leave for charts of
their own (``split_hidden``, not merged back: more, smaller charts), up to ``rounds`` times. Tests count texels
inside two faces: 0 on the cup, the figure and a spiral ramp; on middlebury_dinoSR's hull 18880 before the check,
91 with it, and the carved dino's belly, 1 cm behind its leg, no longer takes the leg's colours.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nodes.common.meshops import face_areas, face_normals

DIRECTIONS = {
    6: np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float),
}
DIRECTIONS[14] = np.vstack([DIRECTIONS[6], np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float) / np.sqrt(3)])


@dataclass
class Atlas:
    """A UV layout for one connectivity: per face corner texel coordinates (x right, y down, texel centres at
    +0.5) in a ``size`` x ``size`` texture, the chart of each face, and the faces it was made for."""

    face_uv: np.ndarray      # (F, 3, 2) float32 texel coordinates
    face_chart: np.ndarray   # (F,) int32
    size: int
    faces: np.ndarray        # (F, 3) int32, to check that a mesh has the same connectivity

    @property
    def n_charts(self) -> int:
        return int(self.face_chart.max()) + 1 if len(self.face_chart) else 0

    def uv01(self) -> np.ndarray:
        """(F, 3, 2) texture coordinates in [0, 1], v up (OBJ / trimesh convention)."""
        uv = self.face_uv / self.size
        return np.stack([uv[..., 0], 1.0 - uv[..., 1]], axis=-1)

    def matches(self, faces) -> bool:
        faces = np.asarray(faces)
        return faces.shape == self.faces.shape and np.array_equal(faces, self.faces)


def _components(faces_sel: np.ndarray, nbr: np.ndarray, group: np.ndarray) -> np.ndarray:
    """Connected components of faces through neighbours in the same group. Returns a label per face."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    nf = len(group)
    rows = np.repeat(np.arange(nf), 3)
    cols = nbr.ravel()
    ok = (cols >= 0)
    ok[ok] &= group[rows[ok]] == group[cols[ok]]
    g = coo_matrix((np.ones(int(ok.sum())), (rows[ok], cols[ok])), shape=(nf, nf))
    return connected_components(g, directed=False)[1]


def make_charts(vertices, faces, nbr, *, directions=6, min_faces=24, smooth_rounds=3):
    """Chart id per face and the chart's projection direction (C, 3)."""
    D = DIRECTIONS[directions]
    n = face_normals(vertices, faces)
    dots = n @ D.T                                          # (F, nd)
    d = np.argmax(dots, axis=1)
    nf = len(faces)
    rows = np.arange(nf)
    for _ in range(smooth_rounds):                          # majority of the three neighbours, if still facing
        votes = np.zeros((nf, len(D)))
        for k in range(3):
            has = nbr[:, k] >= 0
            votes[rows[has], d[nbr[has, k]]] += 1
        votes[rows, d] += 0.5                               # ties keep the face's own direction
        cand = np.argmax(votes, axis=1)
        ok = dots[rows, cand] > 0.2
        d = np.where(ok, cand, d)
    chart = _components(faces, nbr, d)
    for _ in range(3):                                      # merge small charts into a neighbour they face
        sizes = np.bincount(chart)
        small = sizes[chart] < min_faces
        if not np.any(small):
            break
        best_dir = d.copy()
        best_size = np.zeros(nf)
        for k in range(3):
            nb = nbr[:, k]
            has = (nb >= 0) & small
            cand_dir = d[nb[has]]
            cand_size = sizes[chart[nb[has]]]
            facing = dots[rows[has], cand_dir] > 0.05
            better = facing & (cand_size > best_size[has]) & (cand_size > sizes[chart[has]])
            idx = rows[has][better]
            best_dir[idx] = cand_dir[better]
            best_size[idx] = cand_size[better]
        if np.array_equal(best_dir, d):
            break
        d = best_dir
        chart = _components(faces, nbr, d)
    _, chart = np.unique(chart, return_inverse=True)
    chart_dir = np.zeros((chart.max() + 1 if nf else 0, 3))
    chart_dir[chart] = D[d]
    return chart.astype(np.int32), chart_dir


def _basis(d):
    a = np.array([1.0, 0, 0]) if abs(d[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(d, a)
    u /= np.linalg.norm(u)
    return u, np.cross(d, u)


def chart_uv(vertices, faces, chart, chart_dir) -> np.ndarray:
    """(F, 3, 2) chart-local coordinates (world units): orthographic projection along the chart direction,
    turned to the chart's principal axes, minimum at 0. All charts at once (per-chart sums by bincount: a loop
    over thousands of charts cost 0.4 s; ``chart_uv_reference`` is that loop, the same to rounding, except on a
    chart whose two principal spreads are equal, where either turn is a principal one)."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    chart = np.asarray(chart, np.int64)
    nC = len(chart_dir)
    if len(f) == 0:
        return np.zeros((0, 3, 2))
    dirs, inv = np.unique(np.asarray(chart_dir, np.float64), axis=0, return_inverse=True)
    bases = np.array([_basis(d) for d in dirs])                 # (D, 2, 3): a few distinct directions
    q = np.einsum("fcd,fkd->fck", v[f], bases[np.ravel(inv)[chart]])            # (F, 3, 2)
    n = 3.0 * np.bincount(chart, minlength=nC)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.stack([np.bincount(chart, q[..., k].sum(axis=1), nC) for k in range(2)], axis=1) / n[:, None]
        d = q - mean[chart][:, None, :]
        sxx = np.bincount(chart, (d[..., 0] * d[..., 0]).sum(axis=1), nC)
        sxy = np.bincount(chart, (d[..., 0] * d[..., 1]).sum(axis=1), nC)
        syy = np.bincount(chart, (d[..., 1] * d[..., 1]).sum(axis=1), nC)
    cov = np.stack([np.stack([sxx, sxy], -1), np.stack([sxy, syy], -1)], -2) / np.maximum(n - 1, 1)[:, None, None]
    cov = np.where(np.isfinite(cov), cov, np.eye(2))
    _, evecs = np.linalg.eigh(cov)
    R = evecs[:, :, ::-1].copy()
    R[np.linalg.det(R) < 0, :, 1] *= -1
    out = np.einsum("fck,fkl->fcl", d, R[chart])
    lo = np.full((nC, 2), np.inf)
    np.minimum.at(lo, chart, out.min(axis=1))
    return out - lo[chart][:, None, :]


def chart_uv_reference(vertices, faces, chart, chart_dir) -> np.ndarray:
    """chart_uv chart by chart (the plain form it is tested against)."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    P = v[f]                                                 # (F, 3, 3)
    out = np.zeros((len(f), 3, 2))
    nC = len(chart_dir)
    order = np.argsort(chart, kind="stable")
    bounds = np.searchsorted(chart[order], np.arange(nC + 1))
    for c in range(nC):
        idx = order[bounds[c]:bounds[c + 1]]
        if len(idx) == 0:
            continue
        u, w = _basis(chart_dir[c])
        q = np.stack([P[idx] @ u, P[idx] @ w], axis=-1)     # (n, 3, 2)
        pts = q.reshape(-1, 2)
        mean = pts.mean(axis=0)
        cov = np.cov((pts - mean).T) if len(pts) > 2 else np.eye(2)
        evals, evecs = np.linalg.eigh(cov)
        R = evecs[:, ::-1]
        if np.linalg.det(R) < 0:
            R[:, 1] = -R[:, 1]
        q = (q - mean) @ R
        q -= q.reshape(-1, 2).min(axis=0)
        out[idx] = q
    return out


def _chart_masks(local_uv, chart, order, scale, cell, pad):
    """Per chart: occupancy on a grid of ``cell`` texels (its triangles rasterised at ``scale`` texels per world
    unit, dilated by ``pad`` cells for the gutter). Every chart's triangles are scaled and their covering cells
    found in one pass over all faces; only the drawing is per chart."""
    import cv2

    if not order:
        return []
    idx = np.concatenate([i for _, i in order])
    start = np.cumsum([0] + [len(i) for _, i in order])
    pts = local_uv[idx] * (scale / cell)                         # (n, 3, 2) every chart's triangles, in cells
    p0, p1, p2 = pts[:, 0], pts[:, 1], pts[:, 2]                # (corner by corner: NumPy's reductions over an
    hi = np.maximum(np.maximum(p0, p1), p2)                      # axis of 3 are several times slower; the same values)
    top = np.maximum.reduceat(hi, start[:-1], axis=0)           # (charts, 2) largest x, y per chart
    w = np.ceil(top[:, 0]).astype(np.int64) + 1 + 2 * pad
    h = np.ceil(top[:, 1]).astype(np.int64) + 1 + 2 * pad
    span = hi - np.minimum(np.minimum(p0, p1), p2)
    big = np.maximum(span[:, 0], span[:, 1]) > 2                 # triangles over two cells wide are filled ...
    q = np.round((pts + pad) * 16).astype(np.int32)
    # ... smaller ones are covered by the cells of their corners, edge midpoints and centroid
    p7 = np.concatenate([pts, 0.5 * (pts + pts[:, [2, 0, 1]]), ((p0 + p1 + p2) / 3)[:, None]], axis=1)
    counts = np.diff(start)
    limit = np.repeat(np.stack([w - 1, h - 1], axis=1), counts * 7, axis=0)
    cor = np.clip(np.floor(p7.reshape(-1, 2) + pad).astype(np.int64), 0, limit)
    kernel = np.ones((2 * pad + 1, 2 * pad + 1), np.uint8) if pad > 0 else None
    masks = []
    for c in range(len(order)):
        a, b = start[c], start[c + 1]
        m = np.zeros((h[c], w[c]), np.uint8)
        fill = np.flatnonzero(big[a:b])
        if len(fill):
            cv2.fillPoly(m, list(q[a + fill]), 1, lineType=cv2.LINE_8, shift=4)
        cc = cor[7 * a:7 * b]
        m[cc[:, 1], cc[:, 0]] = 1
        if kernel is not None:
            m = cv2.dilate(m, kernel)
        masks.append(m)
    return masks


def _skyline_place(masks, width_cells, height_cells):
    """Tetris packing: each mask (largest first) drops to the lowest place over the current skyline, tried
    upright and turned 90 degrees. Returns per mask (x, y, turned) in cells, or None when it does not fit."""
    sky = np.zeros(width_cells, np.int64)
    out = []
    for m in masks:
        best = None
        for turned, mm in ((False, m), (True, np.ascontiguousarray(m.T[::-1]))):
            h, w = mm.shape
            if w > width_cells:
                continue
            filled = mm.any(axis=0)
            bottom = np.where(filled, np.argmax(mm, axis=0), h)          # first occupied row from the top
            top = np.where(filled, h - np.argmax(mm[::-1], axis=0), 0)   # one past the last occupied row
            win = np.ndarray((width_cells - w + 1, w), sky.dtype, sky, 0, sky.strides * 2)   # (W - w + 1, w) windows
            y = np.max(win - bottom if filled.all() else np.where(filled, win - bottom, -h), axis=1)
            y = np.maximum(y, 0)
            # the highest cell the mask reaches, y + its tallest column (y >= 0, top >= 1 where filled)
            peak = y + int(top.max()) if filled.any() else np.zeros_like(y)
            x = int(np.argmin(peak))
            if best is None or peak[x] < best[0]:
                best = (int(peak[x]), x, int(y[x]), turned, top, filled)
        if best is None or best[0] > height_cells:
            return None
        peak, x, y, turned, top, filled = best
        seg = sky[x:x + len(top)]
        sky[x:x + len(top)] = np.where(filled, y + top, seg)
        out.append((x, y, turned))
    return out


def pack_charts(local_uv, chart, size: int, gutter: int = 2):
    """Scale and place charts into a size x size atlas: charts rasterised on a grid of cells (gutter
    included) are dropped Tetris-like onto a skyline, largest first, upright or turned 90 degrees; the scale
    is the largest found (a few trials from an area estimate) at which all fit. Returns (face_uv (F, 3, 2)
    texel coordinates, scale in texels per world unit)."""
    nC = int(chart.max()) + 1 if len(chart) else 0
    if nC == 0:
        return np.zeros_like(local_uv, np.float32), 1.0
    cell = max(2, size // 512)
    pad = max(1, -(-gutter // cell))
    ncell = size // cell
    srt = np.argsort(chart, kind="stable")
    bounds = np.searchsorted(chart[srt], np.arange(nC + 1))
    groups = [(c, srt[bounds[c]:bounds[c + 1]]) for c in range(nC)]
    v = local_uv
    area = np.zeros(nC)
    tri = 0.5 * np.abs((v[:, 1, 0] - v[:, 0, 0]) * (v[:, 2, 1] - v[:, 0, 1]) - (v[:, 1, 1] - v[:, 0, 1]) * (v[:, 2, 0] - v[:, 0, 0]))
    np.add.at(area, chart, tri)
    groups.sort(key=lambda g: -area[g[0]])
    scale = 0.75 * size / np.sqrt(max(area.sum(), 1e-30))       # surface at 56 % of the atlas: a first guess
    best = None
    lo_fail = None
    for _ in range(6):
        masks = _chart_masks(v, chart, groups, scale, cell, pad)
        placed = _skyline_place(masks, ncell, ncell)
        if placed is not None:
            best = (scale, masks, placed)
            if lo_fail is not None and lo_fail / scale < 1.06:
                break
            scale = scale * 1.12 if lo_fail is None else np.sqrt(scale * lo_fail)
        else:
            lo_fail = scale
            scale = scale * 0.88 if best is None else np.sqrt(scale * best[0])
            if best is not None and lo_fail / best[0] < 1.06:
                break
    while best is None:                                           # tiny atlases: shrink until it fits
        scale *= 0.8
        masks = _chart_masks(v, chart, groups, scale, cell, pad)
        placed = _skyline_place(masks, ncell, ncell)
        if placed is not None:
            best = (scale, masks, placed)
    scale, masks, placed = best
    face_uv = np.zeros_like(local_uv, np.float64)
    for (c, idx), m, (x, y, turned) in zip(groups, masks, placed):
        q = local_uv[idx] * scale + pad * cell                   # texels inside the chart's own box
        if turned:                                                # (u, v) -> (v, W - u): the mask's turn
            wcell = m.shape[1] * cell
            q = np.stack([q[..., 1], wcell - q[..., 0]], axis=-1)
        face_uv[idx] = q + np.array([x * cell, y * cell])
    return face_uv.astype(np.float32), scale


def hidden_faces(face_uv, chart, chart_dir, vertices, faces, texel_face) -> np.ndarray:
    """(F,) bool: of two faces of one chart where one's centroid or one of three points towards its corners
    (texel coordinates) lies inside the other, the one further back along the chart's direction: the back side
    of a fold the orthographic projection laid under its front. ``texel_face`` is the layout's raster
    (bake.uv_raster: a face per texel centre), which names the candidate at each point; the test itself is exact
    (barycentric, 1 % inside the other face)."""
    uv = np.asarray(face_uv, np.float64)
    size = texel_face.shape[0]
    nf = len(uv)
    # the centroid and three points towards the corners (barycentric 2/3, 1/6, 1/6): a fold's border faces lie
    # partly under the front, often not at their centroid
    w = np.array([[1 / 3, 1 / 3, 1 / 3], [2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]])
    pts = np.einsum("pc,fcd->pfd", w, uv).reshape(-1, 2)          # (4 F, 2)
    own = np.tile(np.arange(nf), len(w))
    tx = np.clip(np.floor(pts[:, 0]).astype(np.int64), 0, size - 1)
    ty = np.clip(np.floor(pts[:, 1]).astype(np.int64), 0, size - 1)
    g = texel_face[ty, tx].astype(np.int64)
    k = np.flatnonzero((g >= 0) & (g != own))
    f, g, p = own[k], g[k], pts[k]
    same = chart[f] == chart[g]
    f, g, p = f[same], g[same], p[same]
    a, b, d = uv[g, 0], uv[g, 1], uv[g, 2]
    area = (b[:, 0] - a[:, 0]) * (d[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (d[:, 0] - a[:, 0])
    ok = np.abs(area) > 1e-12
    safe = np.where(ok, area, 1.0)
    w0 = ((d[:, 0] - b[:, 0]) * (p[:, 1] - b[:, 1]) - (d[:, 1] - b[:, 1]) * (p[:, 0] - b[:, 0])) / safe
    w1 = ((a[:, 0] - d[:, 0]) * (p[:, 1] - d[:, 1]) - (a[:, 1] - d[:, 1]) * (p[:, 0] - d[:, 0])) / safe
    inside = ok & (w0 > 0.01) & (w1 > 0.01) & (1.0 - w0 - w1 > 0.01)
    f, g = f[inside], g[inside]
    v = np.asarray(vertices, np.float64)
    fc = np.asarray(faces, np.int64)
    depth = np.einsum("fd,fd->f", v[fc].mean(axis=1), np.asarray(chart_dir)[chart])   # further out = larger
    back = np.where(depth[f] < depth[g], f, g)
    hidden = np.zeros(nf, bool)
    hidden[back] = True
    return hidden


def split_hidden(faces, nbr, chart, chart_dir, hidden):
    """The hidden faces leave their charts: the connected parts of each chart's hidden and kept faces become
    charts of their own (projected along the same direction). Returns (chart, chart_dir)."""
    group = 2 * chart.astype(np.int64) + hidden
    new = _components(faces, nbr, group)
    _, new = np.unique(new, return_inverse=True)
    new_dir = np.zeros((new.max() + 1, 3))
    new_dir[new] = chart_dir[chart]
    return new.astype(np.int32), new_dir


def shelf_layout(local_uv, chart, size: int) -> tuple[np.ndarray | None, int]:
    """Charts side by side in rows on a square as large as the atlas, at the atlas's first-guess density (pack_charts'
    56 % of its square) or, where they do not fit so, at 0.8, 0.64 ... of it: no chart touches another, so a raster
    of it shows each chart's own overlaps. Quick and wasteful; for checking only. Returns (face_uv (F, 3, 2) texel
    coordinates, canvas side); (None, canvas side) where they do not fit even at 1/200 of that density."""
    canvas = size
    v = np.asarray(local_uv, np.float64)
    nC = int(chart.max()) + 1
    e1, e2 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]
    tri = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    scale = 0.75 * size / np.sqrt(max(tri.sum(), 1e-30))
    ext = np.zeros((nC, 2))
    np.maximum.at(ext, chart, v.max(axis=1))
    for _ in range(24):                                             # 0.8^24: 1/200 of the first guess
        wh = np.ceil(ext * scale) + 2                               # a texel's gap on every side
        order = np.argsort(-wh[:, 1], kind="stable")
        off = np.zeros((nC, 2))
        x = y = row = 0.0
        for c in order:
            if x + wh[c, 0] > canvas:
                x, y, row = 0.0, y + row, 0.0
            off[c] = (x + 1, y + 1)
            x += wh[c, 0]
            row = max(row, wh[c, 1])
        if y + row <= canvas and wh[:, 0].max() <= canvas:
            return v * scale + off[chart][:, None, :], canvas
        scale *= 0.8
    return None, canvas                                             # too many charts for the square: no check


def make_atlas(vertices, faces, nbr, size=2048, *, directions=6, min_faces=24, gutter=2, rounds=4) -> Atlas:
    """Charts and their orthographic projection (module docstring), checked on a shelf layout for charts that lay
    a fold's back under its front: those are split, up to ``rounds`` times; then packed."""
    from .bake import uv_raster

    faces = np.asarray(faces, np.int32)
    chart, chart_dir = make_charts(vertices, faces, nbr, directions=directions, min_faces=min_faces)
    local = chart_uv(vertices, faces, chart, chart_dir)
    for _ in range(rounds if len(faces) else 0):
        uv, canvas = shelf_layout(local, chart, size)
        if uv is None:
            break
        hidden = hidden_faces(uv, chart, chart_dir, vertices, faces, uv_raster(uv, canvas))
        if not hidden.any():
            break
        chart, chart_dir = split_hidden(faces, nbr, chart, chart_dir, hidden)
        local = chart_uv(vertices, faces, chart, chart_dir)
    face_uv, _ = pack_charts(local, chart, size, gutter)
    return Atlas(face_uv, chart, int(size), faces.copy())


def atlas_stats(atlas: Atlas, texel_face: np.ndarray, vertices, faces) -> dict:
    """Charts, texel use (share of atlas texels covered by a face), and stretch (texel area / world area,
    relative to the median; its 95th percentile)."""
    a3 = face_areas(vertices, faces)
    uv = atlas.face_uv.astype(np.float64)
    a2 = 0.5 * np.abs((uv[:, 1, 0] - uv[:, 0, 0]) * (uv[:, 2, 1] - uv[:, 0, 1]) - (uv[:, 1, 1] - uv[:, 0, 1]) * (uv[:, 2, 0] - uv[:, 0, 0]))
    ok = a3 > 0
    ratio = a2[ok] / a3[ok]
    rel = ratio / np.median(ratio) if ok.any() else np.ones(1)
    return {"charts": atlas.n_charts, "texel_use": float(np.mean(texel_face >= 0)),
            "stretch_p05": float(np.percentile(rel, 5)), "area_stretch_min": float(rel.min())}
