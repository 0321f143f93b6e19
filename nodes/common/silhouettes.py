"""Silhouettes and the visual hull's point test, shared by every stage that asks "is this point inside the
silhouettes?" (hull, bounds, refine, relax, carve): one vote rule, one host form, one device form.

The vote (``vote``; kernels/silhouette.h ``hull_vote``): a point's projection into each view is inside the
silhouette, on background, or unseen (behind the camera or outside the image). min_views > 0 tolerates
t = nviews - min_views background votes (t = 0 when min_views is 0), and the outside policy holds either way:
policy "carve" needs every view to see the point and at most t to see it on background; policy "ignore"
needs at most t views to see it on background, at least one to see it inside, and at least ``min_seen`` views
to see it at all (inside or on background; 0 or 1 = no more than that one).

Host forms: uint8 masks checked against the cameras (``check_masks``), ``Silhouettes`` (packed cameras,
binary masks, optional soft alpha or a signed-distance outline: the sub-pixel point test of refine and relax).
Device form: ``SilhouetteBits`` (one bit per pixel + 8x8-block summed-area tables, the hull's layout, also
written straight from the images by key.chroma). NumPy references: ``centre_states``, ``view_states``,
``inside_hull``, ``block_table_reference``. The seed's point test on the device (kernels/refine.cl: inside, exit,
clamp) is benchmark-only code: bench/legacy_hulltest.py.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kernels import source
from nodegraph import NodeError, clrt

from .cameras import Cameras, project_packed_f32

POLICIES = ("carve", "ignore")   # views a point projects outside of: not inside, or no vote
OUTLINES = ("distance", "pixels")  # how binary masks are read: signed distance outline or nearest pixel
IN, BACKGROUND, UNSEEN = 1, 2, 3


# ---------------------------------------------------------------- checks
def check_sizes(arrays, cameras: Cameras, node: str, kind: str = "mask"):
    """A NodeError naming the camera when there is not one array per camera or an array's (H, W) is not its
    camera's image size."""
    if len(arrays) != len(cameras):
        raise NodeError(f"{node}: {len(arrays)} {kind}s for {len(cameras)} cameras")
    for a, cam in zip(arrays, cameras):
        h, w = np.shape(a)[:2]
        if (h, w) != (cam.height, cam.width):
            raise NodeError(f"{node}: {kind} of camera '{cam.name}' is {w}x{h} but the camera is {cam.width}x{cam.height}")


def check_vote_inputs(masks, cameras, min_views: int, outside: str, node: str):
    """A NodeError when masks or cameras are missing, min_views exceeds the cameras, or the policy is unknown."""
    if masks is None or cameras is None:
        raise NodeError(f"{node}: needs both 'masks' and 'cameras' inputs")
    if min_views > len(cameras):
        raise NodeError(f"{node}: min_views {min_views} is more than the {len(cameras)} cameras")
    if outside not in POLICIES:
        raise NodeError(f"{node}: outside must be one of {', '.join(POLICIES)}, got {outside!r}")


def check_masks(masks, cameras: Cameras, node: str = "hull") -> list[np.ndarray]:
    """The masks (a MaskSet or a list) as contiguous uint8 (H, W) arrays, one per camera, or a NodeError
    naming the camera."""
    arrays = [np.asarray(m) for m in (masks.masks if hasattr(masks, "masks") else masks)]
    for m, cam in zip(arrays, cameras):
        if m.dtype != np.uint8 or m.ndim != 2:
            raise NodeError(f"{node}: mask of camera '{cam.name}' must be an (H, W) uint8 array, got {m.dtype} {m.shape}")
    check_sizes(arrays, cameras, node)
    return [np.ascontiguousarray(m) for m in arrays]


# ---------------------------------------------------------------- the vote
def centre_states(mask: np.ndarray, cam_row: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Per point (N, 3 float32): 1 = inside the silhouette, 2 = background, 3 = behind / outside the image.
    ``cam_row`` is one row of Cameras.pack(); float32 operations in the order of kernels/camera.h."""
    c = cam_row.astype(np.float32)
    u, v, front = project_packed_f32(c, X)
    with np.errstate(invalid="ignore"):
        fu, fv = u + np.float32(0.5), v + np.float32(0.5)
        seen = front & (fu >= 0) & (fu < c[22]) & (fv >= 0) & (fv < c[23])
    state = np.full(len(X), 3, np.uint8)
    px, py = fu[seen].astype(np.int64), fv[seen].astype(np.int64)
    state[seen] = np.where(mask[py, px] > 127, 1, 2)
    return state


def vote(n_in: np.ndarray, n_out: np.ndarray, nviews: int, min_views: int, policy: str, min_seen: int = 0) -> np.ndarray:
    """The hull's vote rule (see the module docstring): ``n_in`` / ``n_out`` views see the point inside / on
    background, of ``nviews``; ``min_seen``: views that must see it (carve: all of them do)."""
    tolerance = nviews - min_views if min_views > 0 else 0
    if policy == "carve":
        return (n_in + n_out == nviews) & (n_out <= tolerance)
    return (n_out <= tolerance) & (n_in >= 1) & (n_in + n_out >= min_seen)


# ---------------------------------------------------------------- OpenCL: silhouette bits
class SilhouetteCL(clrt.Runner):
    """kernels/silhouette.cl: bits and block tables from uint8 masks."""

    source = source("silhouette.cl")


class OutlineFieldCL(clrt.Runner):
    """kernels/edt.cl: the distance outline (double precision: a file of its own, so the silhouette bits that
    the hull builds need no fp64)."""

    source = source("edt.cl")


class SilhouetteBits:
    """Silhouettes on the OpenCL device in the layout of kernels/silhouette.h, one per view: one bit per pixel
    (rows of Wb = ceil(W/8) bytes, pixel x in bit x % 8 of byte x // 8) and the (Hb+1) x (Wb+1) int32
    summed-area table of its 8x8 pixel block counts (zero first row and column).

    Written from host masks (``from_masks``) or straight from the camera images by a key kernel
    (``nodes.key.keying.chroma_key_bits``): both write the bits and the block counts prefixed along rows,
    then ``prefix_columns`` completes the tables. Allocated once per list of image sizes; hand it back as
    ``out=`` to the next frame's producer to reuse its buffers (its contents are then overwritten)."""

    def __init__(self, sizes: list[tuple[int, int]]):
        run = SilhouetteCL.get()
        self.sizes = [(int(w), int(h)) for w, h in sizes]
        wb = [(w + 7) // 8 for w, _ in self.sizes]
        hb = [(h + 7) // 8 for _, h in self.sizes]
        self.bit_off = np.concatenate([[0], np.cumsum([b * h for b, (_, h) in zip(wb, self.sizes)])]).astype(np.int64)
        self.sat_off = np.concatenate([[0], np.cumsum([(a + 1) * (b + 1) for a, b in zip(wb, hb)])]).astype(np.int64)
        if self.bit_off[-1] >= 2**31 or self.sat_off[-1] >= 2**31:
            raise NodeError(f"{len(sizes)} silhouettes are too large for 32-bit offsets")
        import pyopencl as cl

        rw = cl.mem_flags.READ_WRITE
        self.bits = cl.Buffer(run.ctx, rw, max(int(self.bit_off[-1]), 4))
        self.sat = cl.Buffer(run.ctx, rw, max(int(self.sat_off[-1]) * 4, 4))
        self.bit_off_buf = clrt.to_device(self.bit_off[:-1].astype(np.int32))
        self.sat_off_buf = clrt.to_device(self.sat_off[:-1].astype(np.int32))
        self.sizes_buf = clrt.to_device(np.array(self.sizes, np.int32).reshape(-1, 2))

    def __len__(self) -> int:
        return len(self.sizes)

    @classmethod
    def reuse(cls, out: "SilhouetteBits | None", sizes) -> "SilhouetteBits":
        """``out`` when it was made for these image sizes, else a new one."""
        sizes = [(int(w), int(h)) for w, h in sizes]
        return out if out is not None and out.sizes == sizes else cls(sizes)

    @classmethod
    def from_masks(cls, masks: list[np.ndarray], out: "SilhouetteBits | None" = None,
                   opaque: bool = False) -> "SilhouetteBits":
        """Host uint8 (H, W) masks (inside when > 127; with ``opaque`` when 255: an alpha's fully opaque pixels,
        without a host pass over the masks) to device bits and block tables (into ``out`` when it fits these
        sizes). Returns when the device is done with the masks."""
        run = SilhouetteCL.get()
        sil = cls.reuse(out, [(m.shape[1], m.shape[0]) for m in masks])
        host = []  # keep the zero-copy host buffers alive until the queue is done
        for v, m in enumerate(masks):
            src = run.host(m)
            host.append(src)
            rows = (m.shape[0] + 7) // 8 + 1  # work items: rows of the block table, in groups of 8 (PoCL's own
            # choice ran them on one thread)
            run.launch("pack_block_rows", rows, 8, src, np.int32(m.shape[1]), np.int32(m.shape[0]), np.int32(opaque),
                       sil.bits, np.int32(sil.bit_off[v]), sil.sat, np.int32(sil.sat_off[v]))
        sil.prefix_columns()
        run.finish()
        return sil

    def prefix_columns(self):
        """Enqueue the column prefix that turns the row-prefixed block counts into summed-area tables."""
        wb = max(w for w, _ in self.sizes) // 8 + 2
        SilhouetteCL.get().launch("block_cols", (wb, len(self)), None, self.sat, self.sat_off_buf, self.sizes_buf)

    def masks(self) -> list[np.ndarray]:
        """The silhouettes back on the host as uint8 (H, W) 0/255 masks (for checks; a read-back)."""
        raw = SilhouetteCL.get().read(self.bits, int(self.bit_off[-1]), np.uint8)
        out = []
        for v, (w, h) in enumerate(self.sizes):
            rows = raw[self.bit_off[v]:self.bit_off[v + 1]].reshape(h, -1)
            out.append(np.unpackbits(rows, axis=1, bitorder="little")[:, :w] * np.uint8(255))
        return out

    def block_tables(self) -> list[np.ndarray]:
        """The (Hb+1, Wb+1) int32 summed-area tables back on the host (for checks; a read-back)."""
        raw = SilhouetteCL.get().read(self.sat, int(self.sat_off[-1]), np.int32)
        return [raw[self.sat_off[v]:self.sat_off[v + 1]].reshape((h + 7) // 8 + 1, (w + 7) // 8 + 1)
                for v, (w, h) in enumerate(self.sizes)]


def block_table_reference(mask: np.ndarray, opaque: bool = False) -> np.ndarray:
    """Summed-area table (Hb+1, Wb+1) int32 of the 8x8 pixel block counts of (mask > 127), or of (mask == 255)
    with ``opaque``."""
    h, w = mask.shape
    m = np.zeros((-(-h // 8) * 8, -(-w // 8) * 8), np.int32)
    m[:h, :w] = mask == 255 if opaque else mask > 127
    counts = m.reshape(m.shape[0] // 8, 8, m.shape[1] // 8, 8).sum(axis=(1, 3))
    return np.pad(counts.cumsum(0).cumsum(1), ((1, 0), (1, 0))).astype(np.int32)


def check_silhouettes(sil: SilhouetteBits, cameras: Cameras, node: str = "hull"):
    """A NodeError naming the camera when the device silhouettes do not fit the cameras."""
    if len(sil) != len(cameras):
        raise NodeError(f"{node}: {len(sil)} silhouettes for {len(cameras)} cameras")
    for (w, h), cam in zip(sil.sizes, cameras):
        if (w, h) != (cam.width, cam.height):
            raise NodeError(f"{node}: silhouette of camera '{cam.name}' is {w}x{h} but the camera is "
                            f"{cam.width}x{cam.height}")


def block_window(counts: np.ndarray, width: int, height: int) -> tuple[int, int, int, int]:
    """(x0, y0, w, h): the pixels of the 8x8 blocks from the first to the last row and column of blocks with a
    silhouette pixel (``counts``: (Hb, Wb) pixel counts per block), clipped to the image; (0, 0, 0, 0) when
    the silhouette is empty. Every silhouette pixel lies inside it."""
    rows, cols = np.flatnonzero(counts.any(axis=1)), np.flatnonzero(counts.any(axis=0))
    if len(rows) == 0:
        return 0, 0, 0, 0
    x0, y0 = 8 * int(cols[0]), 8 * int(rows[0])
    return x0, y0, min(width, 8 * (int(cols[-1]) + 1)) - x0, min(height, 8 * (int(rows[-1]) + 1)) - y0


def mask_window(mask: np.ndarray) -> tuple[int, int, int, int]:
    """``block_window`` of a host mask (inside when > 127)."""
    inside = mask > 127
    rows, cols = np.flatnonzero(inside.any(axis=1)), np.flatnonzero(inside.any(axis=0))
    if len(rows) == 0:
        return 0, 0, 0, 0
    h, w = mask.shape
    x0, y0 = 8 * (int(cols[0]) // 8), 8 * (int(rows[0]) // 8)
    return x0, y0, min(w, 8 * (int(cols[-1]) // 8 + 1)) - x0, min(h, 8 * (int(rows[-1]) // 8 + 1)) - y0


def silhouette_windows(sil: SilhouetteBits) -> np.ndarray:
    """(V, 4) int32 ``block_window`` per view of device silhouettes, from their block tables."""
    return np.array([block_window(np.diff(np.diff(t, axis=0), axis=1), w, h)
                     for t, (w, h) in zip(sil.block_tables(), sil.sizes)], np.int32).reshape(-1, 4)


def border_views(masks) -> list[int]:
    """The views whose silhouette touches the image border: a mask (host uint8, inside when > 127) with an
    inside pixel in its first or last row or column; device ``SilhouetteBits``: an inside pixel in the 8x8
    blocks along the border (their block tables; no read-back of the bits)."""
    if isinstance(masks, SilhouetteBits):
        # the four border strips of blocks straight from each summed-area table T (zero first row and column):
        # first block row T[1, Wb], first column T[Hb, 1], last row T[Hb, Wb] - T[Hb-1, Wb], last column
        # T[Hb, Wb] - T[Hb, Wb-1] (the same views as silhouette_windows' block_window touching a border, without
        # differencing every table: 1.8 -> 0.4 ms for 24 HD views)
        raw = SilhouetteCL.get().read(masks.sat, int(masks.sat_off[-1]), np.int32)
        out = []
        for v, (w, h) in enumerate(masks.sizes):
            wb, hb = (w + 7) // 8, (h + 7) // 8
            t = raw[masks.sat_off[v]:masks.sat_off[v + 1]].reshape(hb + 1, wb + 1)
            total = t[hb, wb]
            if total > 0 and (t[1, wb] > 0 or t[hb, 1] > 0 or total > t[hb - 1, wb] or total > t[hb, wb - 1]):
                out.append(v)
        return out
    out = []
    for v, m in enumerate(masks):
        m = np.asarray(m)
        if (m[0] > 127).any() or (m[-1] > 127).any() or (m[:, 0] > 127).any() or (m[:, -1] > 127).any():
            out.append(v)
    return out


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
        check_vote_inputs(masks, cameras, min_views, outside, node)
        binary = check_masks(masks, cameras, node)
        soft = []
        use_alpha = use_alpha and masks.alpha is not None
        for i, (cam, m) in enumerate(zip(cameras, binary)):
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
        inside; exact Euclidean distance between pixel centres, minus half a pixel), Gaussian-blurred by
        ``sigma`` pixels when > 0 (a smoother outline through the staircase). Bilinear >= 0.5 is then the
        pixel edge along straight runs and a rounded corner at steps. Soft alpha is kept as is.
        An exact transform (``outline_field``: on the device, bit for bit scipy's), not
        cv2.distanceTransform(DIST_MASK_PRECISE): OpenCV's gives values that differ in the last bit from call to
        call (mirror-image pixels swap them), which made the tracker's fits, and a test, differ from run to run.
        With ``sigma`` the blur of scipy's transform."""
        if self.alpha is not None:
            return self
        import cv2

        fields = []
        for m in self.masks:
            if sigma > 0:
                fields.append(cv2.GaussianBlur(signed_distance_reference(m), (0, 0), sigma) + np.float32(0.5))
            else:
                fields.append(outline_field(m))
        return Silhouettes(self.cams, self.masks, fields, self.min_views, self.policy)


def outline_field(mask: np.ndarray) -> np.ndarray:
    """``distance_outline``'s field of one uint8 mask (inside > 127): float32 0.5 + the signed distance between
    pixel centres to the other class minus half a pixel. On the OpenCL device (kernels/edt.cl edt_columns,
    edt_rows: Meijster's linear-time transform in integers), bit for bit ``outline_field_reference`` (scipy's exact
    transform); child_rope's ten 0.17 Mpx crops 175 ms a frame with scipy. A mask of one class: the reference's."""
    m = np.ascontiguousarray(mask, np.uint8)
    inside = m > 127
    if inside.all() or not inside.any():
        return outline_field_reference(m)
    H, W = m.shape
    run = OutlineFieldCL.get()
    n = H * W
    g_in, g_out = run.buffer("edt_g_in", 4 * n), run.buffer("edt_g_out", 4 * n)
    dev_mask = run.upload("edt_mask", m)
    run.launch("edt_columns", W, 16, dev_mask, np.int32(W), np.int32(H), g_in, g_out)
    field = run.buffer("edt_field", 4 * n)
    run.launch("edt_rows", H, 16, dev_mask, np.int32(W), np.int32(H), g_in, g_out, run.buffer("edt_scratch", 8 * n),
               run.buffer("edt_d2", 16 * n), field)
    return run.read(field, (H, W), np.float32)


def outline_field_reference(mask: np.ndarray) -> np.ndarray:
    """``outline_field`` by scipy's exact Euclidean distance transform."""
    return signed_distance_reference(mask) + np.float32(0.5)


def signed_distance_reference(mask: np.ndarray) -> np.ndarray:
    """float32 distance between pixel centres to the other class minus half a pixel, positive inside (scipy's
    exact transform per class; a class absent from the mask: the image's width + height)."""
    from scipy.ndimage import distance_transform_edt

    fg = np.asarray(mask) > 127
    far = np.full(fg.shape, float(sum(fg.shape)))               # no pixel of the other class
    to_bg = distance_transform_edt(fg) if not fg.all() else far
    to_fg = distance_transform_edt(~fg) if fg.any() else far
    return np.where(fg, to_bg - 0.5, 0.5 - to_fg).astype(np.float32)


# ---------------------------------------------------------------- NumPy reference
def view_states(points: np.ndarray, views: Silhouettes, v: int) -> np.ndarray:
    """Per point (N, 3 float32) in view ``v``: IN, BACKGROUND or UNSEEN (behind the camera or outside the
    image). Binary masks: the hull's centre test (``centre_states``); soft alpha: bilinear, inside at >= 0.5.
    Float32 in the kernel's order (kernels/refine.cl view_state)."""
    if views.alpha is None:
        return centre_states(views.masks[v], views.cams[v], np.asarray(points, np.float32))
    c = views.cams[v]
    f = np.float32
    u, w, front = project_packed_f32(c, points)
    W, H = int(c[22]), int(c[23])
    with np.errstate(invalid="ignore"):
        fu, fv = u + f(0.5), w + f(0.5)
        seen = front & (fu >= 0) & (fu < c[22]) & (fv >= 0) & (fv < c[23])
    state = np.full(len(points), UNSEEN, np.uint8)
    u, w = u[seen], w[seen]
    a = views.alpha[v]
    fx0, fy0 = np.floor(u), np.floor(w)
    fx, fy = u - fx0, w - fy0
    x0, x1 = np.clip(fx0.astype(np.int64), 0, W - 1), np.clip(fx0.astype(np.int64) + 1, 0, W - 1)
    y0, y1 = np.clip(fy0.astype(np.int64), 0, H - 1), np.clip(fy0.astype(np.int64) + 1, 0, H - 1)
    top = (f(1) - fx) * a[y0, x0] + fx * a[y0, x1]
    bottom = (f(1) - fx) * a[y1, x0] + fx * a[y1, x1]
    state[seen] = np.where((f(1) - fy) * top + fy * bottom >= f(0.5), IN, BACKGROUND)
    return state


def inside_hull(points: np.ndarray, views: Silhouettes) -> np.ndarray:
    """Boolean per point: inside the visual hull under the vote rule (kernels/refine.cl hull_inside)."""
    points = np.asarray(points, np.float32).reshape(-1, 3)
    n_in = np.zeros(len(points), np.int32)
    n_bg = np.zeros(len(points), np.int32)
    for v in range(len(views.cams)):
        s = view_states(points, views, v)
        n_in += s == IN
        n_bg += s == BACKGROUND
    return vote(n_in, n_bg, len(views.cams), views.min_views, views.policy)
