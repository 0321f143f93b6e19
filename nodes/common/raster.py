"""Z-buffer triangle rasterization of meshes into calibrated views (kernels/raster.cl), with NumPy references.

Conventions (kernel and references alike): pixel (u, v) has its centre at integer coordinates, as
``Cameras.project``; a pixel is covered when its centre is inside or on an edge of the projected triangle;
lens distortion is applied per vertex (edges stay straight: fine for small triangles); faces with a vertex
behind the near plane, or beyond the radius where radial distortion folds back, are dropped; depth is
camera z, interpolated perspective-correctly; the nearest face wins and exact depth ties go to the lower
face id.

    tri_id, depth, bary = rasterize(vertices, faces, cameras, view)    # one view, arrays (H, W), (H, W, 3)
    masks = silhouette(vertices, faces, cameras)                        # uint8 0/255 per view
"""
from __future__ import annotations


import numpy as np

from kernels import source
from nodegraph import NodeError, clrt

from .cameras import Cameras


KERNELS = source("raster.cl")
_EMPTY_BOUNDS = np.array([2**31 - 1, 2**31 - 1, -2**31, -2**31], np.int32)   # x0 y0 x1 y1 of nothing
NEAR = 1e-6          # camera z below which a vertex counts as behind the camera
MATERIAL_FLOATS = 12  # colour A (3), colour B (3), pattern, period, lit, receives shadow, pad, pad
PLAIN, CHECKER, STRIPES = 0.0, 1.0, 2.0


def _mesh_arrays(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    v = np.ascontiguousarray(np.asarray(vertices, dtype=np.float32).reshape(-1, 3))
    f = np.ascontiguousarray(np.asarray(faces, dtype=np.int32).reshape(-1, 3))
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise NodeError(f"mesh faces index vertices outside 0..{len(v) - 1}")
    if not np.all(np.isfinite(v)):
        raise NodeError("mesh vertices contain NaN or infinity")
    return v, f


# ---------------------------------------------------------------- NumPy references
def project_vertices_reference(vertices, cameras: Cameras, view: int) -> np.ndarray:
    """(N, 4): u, v, depth, valid — what kernel ``project_vertices`` computes. A vertex is valid when it is
    in front of the near plane and inside the radius where radial distortion still grows (beyond it the
    model folds far-away points back into the image)."""
    uv, z = cameras.project(vertices, view)
    cam = cameras[view]
    X = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    xc = X @ cam.Rt[:, :3].T + cam.Rt[:, 3]
    k1, k2, _, _, k3 = cam.dist
    with np.errstate(divide="ignore", invalid="ignore"):      # a vertex on the camera's plane: not imaged
        r2 = (xc[:, 0] ** 2 + xc[:, 1] ** 2) / xc[:, 2] ** 2
        slope = 1 + r2 * (3 * k1 + r2 * (5 * k2 + r2 * 7 * k3))
    return np.column_stack([uv, z, ((z > NEAR) & (slope > 0)).astype(np.float64)])


def _edge(a, b, px, py):
    return (b[..., 0] - a[..., 0]) * (py - a[..., 1]) - (b[..., 1] - a[..., 1]) * (px - a[..., 0])


def rasterize_reference(vertices, faces, cameras: Cameras, view: int, batch: int = 1 << 22):
    """NumPy z-buffer with the kernel's rules (vectorised over the pixel centres of all faces' bounding
    boxes, ``batch`` candidates at a time). Same outputs as ``rasterize``."""
    v, f = _mesh_arrays(vertices, faces)
    cam = cameras[view]
    w, h = cam.width, cam.height
    proj = project_vertices_reference(v.astype(np.float64), cameras, view)
    best_z = np.full(h * w, np.inf)
    best_f = np.full(h * w, -1, np.int64)
    a, b, c = proj[f[:, 0]], proj[f[:, 1]], proj[f[:, 2]]
    with np.errstate(invalid="ignore", over="ignore"):
        area = _edge(a, b, c[:, 0], c[:, 1])
        xs, ys = np.stack([a[:, 0], b[:, 0], c[:, 0]]), np.stack([a[:, 1], b[:, 1], c[:, 1]])
        x0 = np.ceil(np.clip(xs.min(0), 0, w)).astype(np.int64)
        x1 = np.floor(np.clip(xs.max(0), -1, w - 1)).astype(np.int64)
        y0 = np.ceil(np.clip(ys.min(0), 0, h)).astype(np.int64)
        y1 = np.floor(np.clip(ys.max(0), -1, h - 1)).astype(np.int64)
    ok = (a[:, 3] > 0) & (b[:, 3] > 0) & (c[:, 3] > 0) & (area != 0) & np.isfinite(area) & (x1 >= x0) & (y1 >= y0)
    fids = np.nonzero(ok)[0]
    nx = (x1 - x0 + 1)[fids]
    count = nx * (y1 - y0 + 1)[fids]
    ends = np.cumsum(count)
    lo = 0
    while lo < len(fids):
        hi = max(lo + 1, int(np.searchsorted(ends, (ends[lo - 1] if lo else 0) + batch, side="right")))
        sel = fids[lo:hi]
        cnt = count[lo:hi]
        rep = np.repeat(np.arange(len(sel)), cnt)
        local = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        fr = sel[rep]
        px = (x0[fr] + local % nx[lo:hi][rep]).astype(np.float64)
        py = (y0[fr] + local // nx[lo:hi][rep]).astype(np.float64)
        fa, fb, fc = a[fr], b[fr], c[fr]
        w0 = _edge(fb, fc, px, py) / area[fr]
        w1 = _edge(fc, fa, px, py) / area[fr]
        w2 = _edge(fa, fb, px, py) / area[fr]
        inside = (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
        z = 1.0 / (w0[inside] / fa[inside, 2] + w1[inside] / fb[inside, 2] + w2[inside] / fc[inside, 2])
        pix = (py[inside] * w + px[inside]).astype(np.int64)
        fid = fr[inside]
        order = np.lexsort((fid, z, pix))                     # per pixel: nearest, then lowest face id
        pix, z, fid = pix[order], z[order], fid[order]
        first = np.ones(len(pix), bool)
        first[1:] = pix[1:] != pix[:-1]
        pix, z, fid = pix[first], z[first], fid[first]
        win = (z < best_z[pix]) | ((z == best_z[pix]) & (fid < best_f[pix]))
        best_z[pix[win]], best_f[pix[win]] = z[win], fid[win]
        lo = hi
    tri_id = best_f.reshape(h, w).astype(np.int32)
    bary = np.zeros((h * w, 3))
    hit = np.nonzero(best_f >= 0)[0]
    fh = best_f[hit]
    px, py = (hit % w).astype(np.float64), (hit // w).astype(np.float64)
    fa, fb, fc = a[fh], b[fh], c[fh]
    persp = np.stack([_edge(fb, fc, px, py) / fa[:, 2], _edge(fc, fa, px, py) / fb[:, 2],
                      _edge(fa, fb, px, py) / fc[:, 2]], axis=-1)
    bary[hit] = persp / persp.sum(axis=1, keepdims=True)
    return tri_id, best_z.reshape(h, w).astype(np.float32), bary.reshape(h, w, 3).astype(np.float32)


def shade_colours(tri, bary, faces, normals, texcoords, face_material, materials, light, ambient, shadow) -> np.ndarray:
    """Colours (N, 3) float64 in 0..255 (before rounding) that kernel ``shade`` gives surface points: faces
    ``tri`` (N,) at barycentric coordinates ``bary`` (N, 3)."""
    f = np.asarray(tri)
    b = np.asarray(bary, np.float64)
    corners = np.asarray(faces)[f]                                              # (P, 3)
    t = np.einsum("pk,pkc->pc", b, np.asarray(texcoords, np.float64)[corners])
    m = np.asarray(materials, np.float64).reshape(-1, MATERIAL_FLOATS)[np.asarray(face_material)[f]]
    period = m[:, 7:8]
    k = np.where(m[:, 6] == CHECKER, np.floor(t / period).sum(axis=1), np.floor(t[:, 2] / period[:, 0]))
    sel = np.where(m[:, 6] == PLAIN, 0.0, k - 2 * np.floor(k / 2))[:, None]
    c = (1 - sel) * m[:, 0:3] + sel * m[:, 3:6]
    n = np.einsum("pk,pkc->pc", b, np.asarray(normals, np.float64)[corners])
    ln = np.linalg.norm(n, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        lam = np.where(ln > 0, np.maximum(0, (n @ np.asarray(light, np.float64)[:3]) / ln), 0.0)
    c = np.where(m[:, 8:9] != 0, c * (ambient + (1 - ambient) * lam)[:, None], c)
    d2 = (t[:, 0] - shadow[0]) ** 2 + (t[:, 1] - shadow[1]) ** 2
    dark = 1 - shadow[3] * np.exp(-d2 / (2 * shadow[2] ** 2))
    c = np.where(m[:, 9:10] != 0, c * dark[:, None], c)
    return c * 255


def shade_reference(tri_id, bary, faces, normals, texcoords, face_material, materials, light, ambient,
                    shadow, empty_rgb, n_object):
    """NumPy version of kernel ``shade``: (rgb (H, W, 3) uint8, mask (H, W) uint8)."""
    tri_id = np.asarray(tri_id)
    hit = tri_id >= 0
    col = np.empty(tri_id.shape + (3,), np.float64)
    col[:] = np.asarray(empty_rgb, np.float64)[:3] * 255
    col[hit] = shade_colours(tri_id[hit], np.asarray(bary, np.float64)[hit], faces, normals, texcoords,
                             face_material, materials, light, ambient, shadow)
    rgb = np.clip(col + 0.5, 0, 255).astype(np.uint8)
    mask = np.where(hit & (tri_id < n_object), 255, 0).astype(np.uint8)
    return rgb, mask


# ---------------------------------------------------------------- OpenCL
class RasterCL(clrt.Runner):
    """kernels/raster.cl: vertex projection, z-buffer, resolve, coverage, shading."""

    source = KERNELS
    GROUP = 64


class MeshRaster:
    """One mesh uploaded once, rasterized into any view of ``cameras``. Device buffers are kept."""

    def __init__(self, vertices, faces, cameras: Cameras):
        import pyopencl as cl

        self.v, self.f = _mesh_arrays(vertices, faces)
        self.cameras = cameras
        self.run = RasterCL.get()
        self.ctx, self.queue = self.run.ctx, self.run.queue
        self._cl = cl
        self.d_verts = clrt.to_device(self.v if len(self.v) else np.zeros((1, 3), np.float32))
        self.d_faces = clrt.to_device(self.f if len(self.f) else np.zeros((1, 3), np.int32))
        self.d_cams = clrt.to_device(cameras.pack())
        self.d_proj = cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE, 16 * max(1, len(self.v)))
        self._zbuf = {}

    def _pixels(self, role: str, n: int, nbytes: int):
        """The device buffer of ``n`` pixels of ``nbytes`` each for ``role``, made once per image size."""
        buf = self._zbuf.get((role, n))
        if buf is None:
            buf = self._zbuf[(role, n)] = self._cl.Buffer(self.ctx, self._cl.mem_flags.READ_WRITE, nbytes * n)
        return buf

    def zbuffer(self, view: int):
        """Rasterize all faces into ``view``; returns the device z-buffer (uint64 keys per pixel)."""
        cl = self._cl
        cam = self.cameras[view]
        n = cam.width * cam.height
        zbuf = self._pixels("keys", n, 8)
        cl.enqueue_fill_buffer(self.queue, zbuf, np.uint64(0xFFFFFFFFFFFFFFFF), 0, 8 * n)
        if len(self.f) == 0:
            return zbuf
        g = self.run.GROUP
        self.run.launch("project_vertices", len(self.v), g, self.d_verts, self.d_cams, np.int32(view), np.int32(len(self.v)),
                        np.float32(NEAR), self.d_proj)
        self.run.launch("raster_triangles", len(self.f), g, self.d_faces, self.d_proj, np.int32(len(self.f)),
                        np.int32(cam.width), np.int32(cam.height), zbuf)
        return zbuf

    def depth_box(self, view: int, cull: bool = False):
        """The depths alone, on the box of the mesh's projection: (device uint32 buffer, box (x0, y0, width,
        height)). Pixel (x, y) of the box is item (y - y0) * width + (x - x0), holding the nearest depth's float
        bits (0xFFFFFFFF: no face), the depth of ``zbuffer``'s key there; every pixel outside the box is empty
        (the depth of ``rasterize_reference``). Only the box is cleared: a person's box is a fifth of an HD frame or
        less. ``cull``: skip the faces turned away from the camera (kernel raster_depth), only where the caller
        knows the depths stay the same (``culls``)."""
        cl = self._cl
        cam = self.cameras[view]
        zbuf = self._pixels("depths", cam.width * cam.height, 4)
        box = self._box(view)
        cl.enqueue_fill_buffer(self.queue, zbuf, np.uint32(0xFFFFFFFF), 0, 4 * box[2] * box[3])
        if len(self.f):
            self.run.launch("raster_depth", len(self.f), self.run.GROUP, self.d_faces, self.d_proj, np.int32(len(self.f)),
                            np.int32(cam.width), np.int32(cam.height), cl.cltypes.make_int4(*box), np.int32(bool(cull)), zbuf)
        return zbuf, box

    def _box(self, view: int) -> tuple[int, int, int, int]:
        """(x0, y0, width, height) of the pixels the faces can cover in ``view`` (kernel project_bounds, which also
        projects the vertices); (0, 0, 1, 1) when there are none."""
        if len(self.f) == 0:
            return (0, 0, 1, 1)
        bounds = self.run.buffer("proj_bounds", 16)
        self._cl.enqueue_fill_buffer(self.queue, bounds, _EMPTY_BOUNDS, 0, 16)   # a fill: no wait for the queue
        self.run.launch("project_bounds", len(self.v), self.run.GROUP, self.d_verts, self.d_cams, np.int32(view),
                        np.int32(len(self.v)), np.float32(NEAR), self.d_proj, bounds)
        x0, y0, x1, y1 = (int(b) for b in self.run.read(bounds, 4, np.int32))
        return (x0, y0, x1 - x0 + 1, y1 - y0 + 1) if x1 >= x0 and y1 >= y0 else (0, 0, 1, 1)

    def cover_box(self, view: int) -> tuple[np.ndarray, tuple[int, int, int, int]]:
        """``coverage`` on the box of the mesh's projection only: (uint8 (height, width) 0/255 of the box's pixels,
        box (x0, y0, width, height)); every pixel outside the box is uncovered. The same pixels as ``coverage``
        (the same inside test per face), without a z-buffer: no full-image fill, no atomics, the box read back."""
        cam = self.cameras[view]
        box = self._box(view)
        n = box[2] * box[3]
        mask = self._pixels("cover", cam.width * cam.height, 1)
        self._cl.enqueue_fill_buffer(self.queue, mask, np.uint8(0), 0, n)
        if len(self.f):
            self.run.launch("raster_cover", len(self.f), self.run.GROUP, self.d_faces, self.d_proj, np.int32(len(self.f)),
                            np.int32(cam.width), np.int32(cam.height), self._cl.cltypes.make_int4(*box), mask)
        return self.run.read(mask, (box[3], box[2]), np.uint8), box

    def culls(self, parts) -> list[bool]:
        """Per view whether culling the faces turned away from it keeps every depth (``depth_box(cull=True)``):
        ``parts`` (per face, ``Topology.closed_parts``; None for a mesh that is not closed and consistently
        oriented) each enclose a positive volume (outward faces), and the camera is metric with a proper rotation
        (its screen keeps the turn of what faces it), outside the mesh's bounding box (seen from outside, the
        nearest surface along any ray faces the camera), with the whole box in front of it (no face dropped at the
        near plane, whose hole would show a back face) and within its lens distortion's monotone radius (none
        dropped where the distortion folds back). In exact arithmetic the depths are then the same; a pixel centre
        on a silhouette edge may round either way (none in 320 random views of a cube and 12 of a bumpy sphere)."""
        nv = len(self.cameras)
        if parts is None or len(self.f) == 0:
            return [False] * nv
        v = self.v.astype(np.float64)
        v -= v.mean(axis=0)
        a, b, c = v[self.f[:, 0]], v[self.f[:, 1]], v[self.f[:, 2]]
        if np.any(np.bincount(parts, np.einsum("ij,ij->i", a, np.cross(b, c))) <= 0):
            return [False] * nv
        used = self.v[self.f.ravel()]                       # the faces' box (an unused vertex draws nothing)
        lo, hi = used.min(axis=0).astype(np.float64), used.max(axis=0).astype(np.float64)
        pad = 1e-6 * float(np.linalg.norm(hi - lo)) + 1e-9
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        out = []
        for cam, centre in zip(self.cameras, self.cameras.centers):
            ok = bool(cam.metric and np.linalg.det(cam.Rt[:, :3]) > 0 and np.any((centre < lo - pad) | (centre > hi + pad)))
            if ok:
                xc = corners @ cam.Rt[:, :3].T + cam.Rt[:, 3]
                ok = bool(np.all(xc[:, 2] > NEAR))
                if ok and cam.has_distortion:   # the box's projection is convex: its widest radius is a corner's
                    r2 = np.linspace(0.0, float(np.max((xc[:, 0] ** 2 + xc[:, 1] ** 2) / xc[:, 2] ** 2)), 257)
                    k1, k2, k3 = cam.dist[0], cam.dist[1], cam.dist[4]
                    ok = bool(np.all(1.0 + r2 * (3 * k1 + r2 * (5 * k2 + r2 * 7 * k3)) > 0))
            out.append(ok)
        return out

    def resolve(self, view: int, zbuf):
        """Device buffers (tri_id int32, depth float32, bary float32 x3) for the z-buffer of ``view``."""
        cl = self._cl
        cam = self.cameras[view]
        n = cam.width * cam.height
        rw = cl.mem_flags.READ_WRITE
        tri = cl.Buffer(self.ctx, rw, 4 * n)
        depth = cl.Buffer(self.ctx, rw, 4 * n)
        bary = cl.Buffer(self.ctx, rw, 12 * n)
        self.run.launch("resolve", (cam.width, cam.height), None, zbuf, self.d_faces, self.d_proj, np.int32(cam.width),
                        np.int32(cam.height), tri, depth, bary)
        return tri, depth, bary

    def rasterize(self, view: int):
        cam = self.cameras[view]
        tri, depth, bary = self.resolve(view, self.zbuffer(view))
        out = (np.empty((cam.height, cam.width), np.int32), np.empty((cam.height, cam.width), np.float32),
               np.empty((cam.height, cam.width, 3), np.float32))
        for host, dev in zip(out, (tri, depth, bary)):
            self.run.read(dev, host.shape, host.dtype, out=host)
        return out

    def coverage(self, view: int) -> np.ndarray:
        cl = self._cl
        cam = self.cameras[view]
        n = cam.width * cam.height
        zbuf = self.zbuffer(view)
        d_mask = cl.Buffer(self.ctx, cl.mem_flags.WRITE_ONLY, n)
        self.run.launch("coverage", n, self.run.GROUP, zbuf, np.int32(n), d_mask)
        return self.run.read(d_mask, (cam.height, cam.width), np.uint8)


def rasterize(mesh_vertices, faces, cameras: Cameras, view: int):
    """Rasterize a mesh into one view. Returns (tri_id (H, W) int32, -1 = empty; depth (H, W) float32
    camera z, inf = empty; bary (H, W, 3) float32 perspective-correct barycentrics of the face's corners)."""
    return MeshRaster(mesh_vertices, faces, cameras).rasterize(view)


def silhouette(vertices, faces, cameras: Cameras) -> list[np.ndarray]:
    """Binary silhouette (uint8 0/255) of a mesh in every view."""
    out = []
    for cam, (box, (x0, y0, w, h)) in zip(cameras, silhouette_boxes(vertices, faces, cameras)):
        full = np.zeros((cam.height, cam.width), np.uint8)
        full[y0:y0 + h, x0:x0 + w] = box
        out.append(full)
    return out


def silhouette_boxes(vertices, faces, cameras: Cameras) -> list[tuple[np.ndarray, tuple[int, int, int, int]]]:
    """``silhouette`` per view as (uint8 0/255 of the mesh's box, box (x0, y0, width, height)): nothing is covered
    outside the box (``MeshRaster.cover_box``)."""
    r = MeshRaster(vertices, faces, cameras)
    return [r.cover_box(i) for i in range(len(cameras))]


def silhouette_iou(vertices, faces, cameras: Cameras, masks) -> list[dict]:
    """Per view the mesh's silhouette against a mask (> 127): {"iou", "mesh_outside_mask", "mask_not_covered"}
    (IoU 1 where both are empty), counted on the mesh's box and the mask's pixel count (no full-image
    silhouette)."""
    masks = [np.asarray(m) for m in masks]
    for cam, m in zip(cameras, masks):
        if m.shape != (cam.height, cam.width):
            raise NodeError(f"camera '{cam.name}': mask {m.shape[1]}x{m.shape[0]} is not its image's "
                            f"{cam.width}x{cam.height}")
    out = []
    for (sil, (x0, y0, w, h)), m in zip(silhouette_boxes(vertices, faces, cameras), masks):
        a = sil > 0
        inside = m > 127                                  # thresholded once: counted whole, then read on the box
        mask_count = int(np.count_nonzero(inside))
        both = int(np.count_nonzero(a & inside[y0:y0 + h, x0:x0 + w])) if a.any() else 0
        mesh_count = int(np.count_nonzero(a))
        union = mask_count + mesh_count - both
        out.append({"iou": 1.0 if union == 0 else both / union, "mesh_outside_mask": mesh_count - both,
                    "mask_not_covered": mask_count - both})
    return out


def render(vertices, faces, normals, texcoords, face_material, materials, cameras: Cameras, *, n_object: int,
           light=(0.0, 0.0, 1.0), ambient: float = 0.3, shadow=(0.0, 0.0, 1.0, 0.0), empty_rgb=(0.0, 0.0, 0.0)):
    """Shade a mesh in every view (Lambert + procedural pattern, see kernel ``shade``).

    Returns (images: list of (H, W, 3) uint8, masks: list of uint8 0/255 where faces < n_object are seen).
    """
    light = np.asarray(light, np.float64)
    light = light / np.linalg.norm(light)
    import pyopencl as cl

    r = MeshRaster(vertices, faces, cameras)
    d_norm = clrt.to_device(np.asarray(normals, np.float32).reshape(-1, 3))
    d_tex = clrt.to_device(np.asarray(texcoords, np.float32).reshape(-1, 3))
    d_fmat = clrt.to_device(np.asarray(face_material, np.int32).reshape(-1))
    d_mat = clrt.to_device(np.asarray(materials, np.float32).reshape(-1, MATERIAL_FLOATS))
    f4 = cl.cltypes.make_float4
    images, masks = [], []
    for view, cam in enumerate(cameras):
        n = cam.width * cam.height
        tri, _, bary = r.resolve(view, r.zbuffer(view))
        d_rgb = cl.Buffer(r.ctx, cl.mem_flags.WRITE_ONLY, 3 * n)
        d_mask = cl.Buffer(r.ctx, cl.mem_flags.WRITE_ONLY, n)
        r.run.launch("shade", n, r.run.GROUP, tri, bary, r.d_faces, d_norm, d_tex, d_fmat, d_mat, f4(*light, 0),
                     np.float32(ambient), f4(*shadow), f4(*empty_rgb, 0), np.int32(n_object), np.int32(n), d_rgb, d_mask)
        rgb = np.empty((cam.height, cam.width, 3), np.uint8)
        mask = np.empty((cam.height, cam.width), np.uint8)
        cl.enqueue_copy(r.queue, rgb, d_rgb)
        cl.enqueue_copy(r.queue, mask, d_mask)
        images.append(rgb)
        masks.append(mask)
    return images, masks


def sample_texture(texture: np.ndarray, uv01: np.ndarray) -> np.ndarray:
    """Bilinear lookup of an (S, S, 3) uint8 texture at texture coordinates (N, 2) in [0, 1], v up (OBJ /
    trimesh convention; texel centres at (i + 0.5) / S). Returns (N, 3) float32 0..255."""
    import cv2

    uv = np.asarray(uv01, np.float32).reshape(-1, 2)
    h, w = texture.shape[:2]
    n = len(uv)
    cols = 4096                                   # cv2.remap wants maps below 32767 on each side
    rows = max(1, -(-n // cols))
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:n] = uv[:, 0] * w - 0.5
    my[:n] = (1.0 - uv[:, 1]) * h - 0.5
    out = cv2.remap(np.ascontiguousarray(texture), mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1, texture.shape[2])[:n].astype(np.float32)


def render_texture(vertices, faces, face_uv, texture, cameras: Cameras, view: int, *, face_colours=None,
                   background=(0, 0, 0)):
    """Render a textured mesh into one view (no lighting: the texture is the colour). ``face_uv`` (F, 3, 2)
    texture coordinates in [0, 1] (v up) of each face corner and ``texture`` (S, S, 3) uint8; or
    ``face_colours`` (F, 3, 3) per-corner colours (vertex colours), interpolated. Returns (rgb (H, W, 3)
    uint8, coverage (H, W) bool)."""
    tri, _, bary = rasterize(vertices, faces, cameras, view)
    hit = tri >= 0
    f = tri[hit]
    b = bary[hit].astype(np.float32)
    if face_colours is not None:
        col = np.einsum("nc,ncd->nd", b, np.asarray(face_colours, np.float32)[f])
    else:
        uv = np.einsum("nc,ncd->nd", b, np.asarray(face_uv, np.float32)[f])
        col = sample_texture(texture, uv)
    out = np.empty(tri.shape + (3,), np.uint8)
    out[:] = np.asarray(background, np.uint8)
    out[hit] = np.clip(col + 0.5, 0, 255).astype(np.uint8)
    return out, hit
