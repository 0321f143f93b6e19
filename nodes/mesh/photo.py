"""Photo-consistent refinement: each vertex moves along its normal to where the cameras that see it agree on
its colour.

A silhouette-built surface (the visual hull, refined and relaxed) is exact only on the outlines; elsewhere it
lies outside the true surface, so the views that see a point paint it with colours from different places and a
texture made from them is blurred where they are averaged and seamed where one is chosen. Like the depth
refinement of multi-view stereo, for every vertex a small patch (the vertex and its one-ring neighbours) is
moved through a range of offsets along the normal; at each offset the patch is projected into the
vertex's best views (z-buffer visible, inside the eroded mask, weight cos^2 of the viewing angle, the ``views``
highest) and the cost is the weighted colour variance across them. The offset of least cost, and how far that
cost lies below the vertex's median cost over the range (the confidence), go into a screened smoothing: a few Jacobi rounds of
d = (c * d* + mean of the neighbours' d) / (c + 1), so confident vertices pull and textureless ones follow
their neighbours. Only inward offsets are searched by default: the true surface is inside the hull.

Outline pixels the input covered stay covered (the vertices that held them are pinned), and no edge folds that
did not. Measured (README, Texturing): on the synthetic figure the Chamfer distance to the true surface 5.87 ->
4.76 mm (a uniform shrink by the same median offset: 5.68); held out, the texture on the refined mesh gains
+0.2 to +1.0 dB on the same pixels on the four real colour sets.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nodegraph import Node, NodeError, Param
from nodes.common import raster
from nodes.common.meshops import carried_vertex_colors, ring_average, vertex_normals
from nodes.common.types import CameraSet, Images, Masks, Mesh


@dataclass
class PhotoResult:
    offsets: np.ndarray        # (V,) along the normal (negative: inward), scene units
    best: np.ndarray           # (V,) each vertex's own least-cost offset, before smoothing
    confidence: np.ndarray     # (V,) how distinct the least cost is, 0 (no evidence) .. max_confidence
    views: np.ndarray          # (V,) number of views that see the vertex (of the `views` kept)
    pinned: np.ndarray | None = None   # (V,) bool: held in place because a view's outline needs them


def view_weights(vertices, faces, normals, cameras, masks, *, erode_px=2, min_cos=0.2, depth_tol=0.01):
    """(C, V) float32: cos^2 of the angle between the normal and the ray to each camera where the vertex is
    seen (not behind another part of the mesh: within depth_tol of the diagonal of the z-buffer; inside the
    mask eroded by erode_px; facing the camera by more than min_cos), else 0."""
    import cv2

    from nodes.common.raster import MeshRaster

    v = np.asarray(vertices, np.float64)
    tol = depth_tol * float(np.linalg.norm(np.ptp(v, axis=0)))
    raster = MeshRaster(v, faces, cameras)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * erode_px + 1,) * 2) if erode_px > 0 else None
    W = np.zeros((len(cameras), len(v)), np.float32)
    centers = cameras.centers
    for i in range(len(cameras)):
        _, depth, _ = raster.rasterize(i)
        uv, z = cameras.project(v, i)
        h, w = depth.shape
        x = np.round(uv[:, 0]).astype(np.int64)
        y = np.round(uv[:, 1]).astype(np.int64)
        ok = (x >= 0) & (y >= 0) & (x < w) & (y < h) & (z > 0)
        xs, ys = np.where(ok, x, 0), np.where(ok, y, 0)
        m = (np.asarray(masks[i]) > 127).astype(np.uint8)
        if kernel is not None:
            m = cv2.erode(m, kernel)
        ok &= (z <= depth[ys, xs] + tol) & (m[ys, xs] > 0)
        ray = centers[i] - v
        ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
        c = np.einsum("ij,ij->i", normals, ray)
        W[i] = np.where(ok & (c > min_cos), c * c, 0.0)
    return W


def outline_candidates(vertices, normals, cameras, masks, *, px=0.5, max_cos=0.2):
    """Per view (vertex indices, pixel x, pixel y) of the vertices that may hold that view's outline: the ray
    grazes the surface there (|cos| < max_cos), the vertex projects within px pixels of the mask's edge, and
    its pixel is inside the mask."""
    import cv2

    v = np.asarray(vertices, np.float64)
    out = []
    centers = cameras.centers
    for i in range(len(cameras)):
        m = (np.asarray(masks[i]) > 127).astype(np.uint8)
        # signed distance to the outline, pixels (inside > 0), the edge half-way between pixel centres
        sd = cv2.distanceTransform(m, cv2.DIST_L2, 5) - cv2.distanceTransform(1 - m, cv2.DIST_L2, 5)
        sd = np.where(sd > 0, sd - 0.5, sd + 0.5).astype(np.float32)[..., None]
        uv, z = cameras.project(v, i)
        near = (np.abs(_sample(sd, np.nan_to_num(uv).astype(np.float32))[:, 0]) <= px) & (z > 0)
        ray = centers[i] - v
        ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
        near &= np.abs(np.einsum("ij,ij->i", normals, ray)) < max_cos
        h, w = m.shape
        x = np.round(np.nan_to_num(uv[:, 0])).astype(np.int64)
        y = np.round(np.nan_to_num(uv[:, 1])).astype(np.int64)
        near &= (x >= 0) & (y >= 0) & (x < w) & (y < h)
        idx = np.nonzero(near)[0]
        keep = m[y[idx], x[idx]] > 0
        out.append((idx[keep], x[idx[keep]], y[idx[keep]]))
    return out


def rim_vertices(vertices, normals, cameras, masks, *, px=0.5, max_cos=0.2) -> np.ndarray:
    """(V,) bool: vertices that may hold some view's outline (outline_candidates)."""
    rim = np.zeros(len(vertices), bool)
    for idx, _, _ in outline_candidates(vertices, normals, cameras, masks, px=px, max_cos=max_cos):
        rim[idx] = True
    return rim


def _sample(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear colours (N, C) (the image's dtype) at pixel positions (N, 2) (pixel centres at
    integers); outside the image the border is repeated."""
    import cv2

    n = len(uv)
    cols = 4096                                    # cv2.remap wants maps below 32767 on each side
    rows = max(1, -(-n // cols))
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:n] = uv[:, 0]
    my[:n] = uv[:, 1]
    out = cv2.remap(img, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1, img.shape[2])[:n]


def _project_sample(cam, img, base, normals, ds):
    """Colours (S, P, n, 3) float32 of the points base (P, n, 3) + d * normals (n, 3) for every d in ds, in
    one camera: the points move linearly in camera coordinates, so the rotation is applied once."""
    from nodes.common.cameras import distort

    R, t = cam.Rt[:, :3], cam.Rt[:, 3]
    xc = (base @ R.T + t).astype(np.float32)                     # (P, n, 3)
    rn = (normals @ R.T).astype(np.float32)                      # (n, 3)
    X = xc[None] + ds.astype(np.float32)[:, None, None, None] * rn[None, None]   # (S, P, n, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        xn = (X[..., :2] / X[..., 2:3]).reshape(-1, 2)
    if cam.has_distortion:
        xn = distort(xn, cam.dist)
    K = cam.K.astype(np.float32)
    uv = np.nan_to_num(np.stack([K[0, 0] * xn[:, 0] + K[0, 1] * xn[:, 1] + K[0, 2], K[1, 1] * xn[:, 1] + K[1, 2]], 1))
    return _sample(img, uv).reshape(*X.shape[:3], 3).astype(np.float32) * np.float32(1.0 / 255)


def ring_patches(vertices, faces, size=7) -> np.ndarray:
    """(V, size) vertex indices: each vertex and its first size - 1 one-ring neighbours (the vertex again where
    it has fewer). Points on the mesh itself: a patch in the tangent plane would stand off a curved surface by
    its sagitta (e^2 / 2r), and the search would find the surface that much too far in."""
    from nodes.common.meshops import padded_rows, vertex_neighbours

    nv = len(vertices)
    rows = padded_rows(*vertex_neighbours(faces, nv), fill=-1)[:, : size - 1]
    if rows.shape[1] < size - 1:
        rows = np.pad(rows, ((0, 0), (0, size - 1 - rows.shape[1])), constant_values=-1)
    own = np.arange(nv)[:, None]
    return np.hstack([own, np.where(rows < 0, own, rows)])


def offset_costs(vertices, normals, images, cameras, W, offsets, *, views=6, faces=None, chunk=20000) -> np.ndarray:
    """(S, V) weighted colour variance across each vertex's `views` best views of its one-ring patch
    (ring_patches) moved by each of the S offsets along the vertex's normal (colours 0..1; mean over the
    patch's points and the channels)."""
    v = np.asarray(vertices, np.float64)
    nv = len(v)
    patch = ring_patches(v, faces)                                    # (V, P)
    P = patch.shape[1]
    k = min(views, len(cameras))
    order = np.argsort(-W, axis=0, kind="stable")[:k]          # (k, V) the best views per vertex
    wk = np.take_along_axis(W, order, axis=0)                  # (k, V)
    imgs = [np.ascontiguousarray(np.asarray(im)[..., :3]) for im in images]   # sampled as uint8 (1/255 steps: far below the noise floor)
    ds = np.asarray(offsets, np.float64)
    costs = np.zeros((len(ds), nv), np.float64)
    for lo in range(0, nv, chunk):
        hi = min(nv, lo + chunk)
        m = hi - lo
        s0 = wk[:, lo:hi].sum(0)                                             # (m,)
        s1 = np.zeros((len(ds), P, m, 3), np.float32)
        s2 = np.zeros((len(ds), P, m), np.float32)
        base = np.moveaxis(v[patch[lo:hi]], 1, 0)                           # (P, m, 3)
        for view in range(len(cameras)):
            kk, idx = np.nonzero(order[:, lo:hi] == view)
            if len(idx) == 0:
                continue
            w = wk[kk, lo + idx]
            keep = w > 0
            if not keep.any():
                continue
            idx, w = idx[keep], w[keep]
            c = _project_sample(cameras[view], imgs[view], base[:, idx], normals[lo + idx], ds)   # (S, P, n, 3)
            s1[:, :, idx] += w[None, None, :, None] * c             # a vertex is at most once in a view's list
            s2[:, :, idx] += w[None, None, :] * (c * c).sum(-1)
        inv = (1.0 / np.maximum(s0, 1e-12)).astype(np.float32)
        var = s2 * inv - (s1 * s1).sum(-1) * inv * inv                      # (S, P, m)
        costs[:, lo:hi] = np.maximum(var, 0.0).mean(axis=1) / 3.0
    return costs


def photo_offsets(vertices, faces, images, masks, cameras, *, search=0.01, steps=21, views=6, rounds=30,
                  inward_only=True, erode_px=2, max_confidence=3.0, keep_outlines=True,
                  noise=3.0 / 255, strength=4.0, rim_px=0.5, rim_cos=0.2, rim_weight=6.0,
                  outline_rounds=6, power=3.0) -> PhotoResult:
    """Offsets along the vertex normals to the photo-consistent surface (module docstring). ``search`` is the
    range as a fraction of the bounding-box diagonal (inward, or both ways when not inward_only)."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    nv = len(v)
    n = vertex_normals(v, f)
    W = view_weights(v, f, n, cameras, masks, erode_px=erode_px)
    R = search * float(np.linalg.norm(np.ptp(v, axis=0)))
    ds = np.linspace(-R, 0.0, steps) if inward_only else np.linspace(-R, R, steps)
    costs = offset_costs(v, n, images, cameras, W, ds, views=views, faces=f)
    best = np.argmin(costs, axis=0)
    col = np.arange(nv)
    # sub-step: the vertex of the parabola through the least cost and its neighbours
    b = np.clip(best, 1, steps - 2)
    c0, c1, c2 = costs[b - 1, col], costs[b, col], costs[b + 1, col]
    den = c0 - 2.0 * c1 + c2
    shift = np.where((den > 1e-12) & (best == b), 0.5 * (c0 - c2) / np.where(den > 1e-12, den, 1.0), 0.0)
    step = ds[1] - ds[0] if steps > 1 else 0.0
    d_star = ds[best] + np.clip(shift, -0.5, 0.5) * step
    # confidence: how far the least cost lies below the vertex's typical cost over the range (against an
    # image-noise floor), cubed: flat colour, where every offset agrees, and noise, whose least cost is a
    # chance dip, give (almost) none; a distinct minimum gives up to max_confidence
    c_ref = np.median(costs, axis=0)
    conf = (np.clip(c_ref - costs[best, col], 0.0, None) / (c_ref + noise ** 2)) ** power
    k = min(views, len(cameras))
    seen = (np.sort(W, axis=0)[::-1][:k] > 0).sum(0)
    conf = np.where(seen >= 2, conf, 0.0)
    if not np.any(conf > 0):
        return PhotoResult(np.zeros(nv), d_star, conf, seen)
    conf = np.minimum(strength * conf, max_confidence)
    A = ring_average(f, nv)

    def solve(pinned):
        target = np.where(pinned, 0.0, d_star)
        c = np.where(pinned, rim_weight, conf)
        d = np.where(c > 0, target, 0.0)
        for _ in range(rounds):
            d = (c * target + A @ d) / (c + 1.0)
        return unfold(v, f, n, np.minimum(d, 0.0) if inward_only else d)

    pinned = np.zeros(nv, bool)
    d = solve(pinned)
    if keep_outlines:
        # an outline pixel the mesh covered must stay covered: the vertices that held one the moved mesh lost
        # are pinned where they are, and the offsets solved again, until no outline is lost
        from nodes.common.raster import MeshRaster

        cands = outline_candidates(v, n, cameras, masks, px=rim_px, max_cos=rim_cos)
        before = MeshRaster(v, f, cameras)
        covered = [before.coverage(i)[y, x] > 0 for i, (_, x, y) in enumerate(cands)]
        for _ in range(outline_rounds):
            after = MeshRaster(v + d[:, None] * n, f, cameras)
            lost = np.zeros(nv, bool)
            for i, (idx, x, y) in enumerate(cands):
                lost[idx[covered[i] & (after.coverage(i)[y, x] == 0)]] = True
            lost &= ~pinned
            if not lost.any():
                break
            pinned |= lost
            d = solve(pinned)
    return PhotoResult(d, d_star, conf, seen, pinned)


def unfold(vertices, faces, normals, d, rounds=12) -> np.ndarray:
    """The offsets halved around every edge they fold (its faces' vertices and their one-rings), round by round,
    until the moved mesh folds no more edges than the input did."""
    from nodes.common.meshops import edge_face_pairs, folded_edges, ring_operator

    pairs = edge_face_pairs(faces)
    allowed = len(folded_edges(vertices, faces, pairs))
    S = ring_operator(faces, len(vertices))
    d = d.copy()
    for _ in range(rounds):
        folded = folded_edges(vertices + d[:, None] * normals, faces, pairs)
        if len(folded) <= allowed:
            break
        hit = np.zeros(len(vertices))
        hit[np.unique(faces[pairs[1][folded]].ravel())] = 1.0
        d[(S @ hit) > 0] *= 0.5
    return d


class Photo(Node):
    """Photo-consistent refinement (this module's docstring): every vertex moves along its normal to where the
    views that see it best agree on the colour of its one-ring patch (weighted variance over its best views), the
    offsets smoothed over the mesh by how distinct that agreement is; inward only by default, since
    the true surface is inside the visual hull. Place it after relax and before texture: the views then paint
    each point with the same place, so the texture is sharper and lands where the held-out camera sees it."""

    type_name = "photo"
    version = 1
    inputs = {"mesh": Mesh, "images": Images, "masks": Masks, "cameras": CameraSet}
    outputs = {"mesh": Mesh}
    params = {
        "search": Param(float, 0.01, range=(0.0, 0.1), doc="offsets searched, a fraction of the bounding-box diagonal"),
        "steps": Param(int, 21, range=(3, 101), doc="offsets tried within the search range"),
        "views": Param(int, 6, range=(2, 64), doc="best views per vertex compared (cos^2 of the viewing angle)"),
        "rounds": Param(int, 30, range=(0, 500), doc="smoothing rounds (confident vertices pull their neighbours)"),
        "inward_only": Param(bool, True, doc="search inside the surface only (a silhouette-built mesh is outside the "
                                             "true surface); false: both ways"),
        "margin": Param(int, 2, range=(0, 64), doc="mask erosion before sampling, pixels"),
        "keep_outlines": Param(bool, True, doc="vertices on a view's outline (the ray grazes them at the mask's edge) "
                                               "stay: the silhouettes fix the surface there"),
    }
    kernels = [raster.KERNELS]   # the z-buffer of the visibility test

    def run(self, mesh, images, masks, cameras, *, search, steps, views, rounds, inward_only, margin, keep_outlines):
        import trimesh

        if len(images.images) != len(cameras) or len(masks.masks) != len(cameras):
            raise NodeError(f"photo: {len(images.images)} images and {len(masks.masks)} masks for {len(cameras)} "
                            "cameras: connect one image and one mask per camera")
        v = np.asarray(mesh.vertices, np.float64)
        if len(mesh.faces) == 0:
            return {"mesh": mesh}
        r = photo_offsets(v, mesh.faces, images.images, masks.masks, cameras, search=search, steps=steps,
                          views=views, rounds=rounds, inward_only=inward_only, erode_px=margin,
                          keep_outlines=keep_outlines)
        diag = float(np.linalg.norm(np.ptp(v, axis=0)))
        moved = r.confidence > 0
        self.log.info("photo: %d of %d vertices with evidence (seen by >= 2 views and a colour agreement off the "
                      "surface); offset median %.3g %% of the diagonal, 90th percentile %.3g %%", int(moved.sum()),
                      len(v), 100 * np.median(np.abs(r.offsets)) / diag, 100 * np.percentile(np.abs(r.offsets), 90) / diag)
        out = v + r.offsets[:, None] * vertex_normals(v, mesh.faces)
        return {"mesh": trimesh.Trimesh(out, np.asarray(mesh.faces), vertex_colors=carried_vertex_colors(mesh, out),
                                        process=False)}
