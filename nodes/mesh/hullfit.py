"""The smooth silhouette field that refine and relax fit the mesh to, and the searches over it.

Each view's silhouette is read as a smooth function f(u, v) in [0, 1]: the quadratic B-spline of the mask
(binary masks: 0/1 per pixel; soft alpha: alpha per pixel, 8 bits), pixel centres at integers, pixels off
the image 0. Along a straight mask edge f is 0.5 exactly on the pixel edge (half-way between the last inside
and the first outside pixel centre) and rises with slope 1 per pixel into the mask; at staircase steps its
level curves round the corners. ``level_of(d)`` is the level d pixels inside a straight edge: 0.125 / 0.5 /
0.875 at d = -0.5 / 0 / +0.5.

A point is inside the hull *at level tau* when the hull's vote rule (nodes.common.silhouettes.vote) passes with
"inside" meaning f >= tau in a view (behind the camera or off the image: unseen). tau = 0.5 is the visual hull
of the pixel-edge outline (refine); the shell between level_of(+tol) and level_of(-tol) holds the surfaces
whose outlines stay within ``tol`` pixels of it (relax).

Searches run along short segments A -> B with A inside (``exit_interval``). Under the default vote ("carve":
every view must see the point inside) the hull's exit is the first exit over the views, found view by view:
a view that sees the current best exit point inside is skipped, the others are bisected alone. That costs
about one lookup per view plus one or two single-view bisections, instead of a bisection of the whole vote.

Kernels: kernels/hullfit.cl (``FieldCL``); NumPy references here (``view_states``, ``inside_at``,
``exit_interval``, ``cross_reference``, ``onto_reference``, ``shell_interval_reference``), float32 in the same
order of operations.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kernels import source
from nodegraph import NodeError
from nodegraph.clrt import Runner, round_up
from nodes.common.cameras import Cameras, project_packed_f32
from nodes.common.silhouettes import POLICIES, SilhouetteBits, check_masks, check_sizes, check_vote_inputs, vote

IN, BACKGROUND, UNSEEN = 1, 2, 3
RELAX_OUTSIDE_PX = 0.4  # relax's default outside_px (refine searches that level ahead for it)
ROOT_TOL = 1e-4         # a crossing stops at a point whose field is this close to the level (kernel ROOT_TOL)


def bspline2(x: float) -> float:
    """The quadratic B-spline kernel (support [-1.5, 1.5], integral 1)."""
    x = abs(x)
    return 0.75 - x * x if x <= 0.5 else (0.5 * (1.5 - x) ** 2 if x < 1.5 else 0.0)


def level_of(d: float) -> float:
    """The field's value ``d`` pixels inside a straight mask edge (negative: outside); 0.5 at d = 0."""
    return float(sum(bspline2(-d + 0.5 + k) for k in range(8)))


# ---------------------------------------------------------------- host form
@dataclass
class SilhouetteField:
    """Packed cameras (relative to ``origin``), per-view masks (uint8: 0/255 binary or 8-bit alpha), whether
    they are soft, and the vote rule."""

    cams: np.ndarray                 # (N, 32) float32, Cameras.pack(origin)
    origin: np.ndarray               # (3,) float64: points are given to the searches relative to it
    masks: list[np.ndarray] | None   # uint8 (H, W): binary (> 127 inside) or alpha * 255; None: read from ``bits``
    soft: bool
    min_views: int = 0
    policy: str = "carve"
    bits: object = None              # the binary masks already on the device (SilhouetteBits), when the producer made them
    image_sizes: list | None = None  # (W, H) per view
    source: object = None            # the MaskSet it was made from (identity: what refine and relax may share)

    def key(self) -> tuple:
        """What makes two fields the same (the MaskSet by identity, the cameras by value, the vote rule)."""
        return (self.source, self.soft, self.min_views, self.policy, self.cams.tobytes())

    @classmethod
    def from_inputs(cls, masks, cameras: Cameras, origin, min_views: int = 0, outside: str = "carve",
                    use_alpha: bool = True, node: str = "refine") -> "SilhouetteField":
        """Check a MaskSet against the cameras (NodeError naming the camera) and pack both."""
        check_vote_inputs(masks, cameras, min_views, outside, node)
        origin = np.asarray(origin, np.float64).reshape(3)
        device = None if use_alpha else getattr(masks, "device", None)   # (a key makes its device's only when asked)
        if device is not None:  # the producer's device silhouettes: no host masks needed
            check_sizes([np.broadcast_to(np.uint8(0), (h, w)) for w, h in device.sizes], cameras, node)
            return cls(cameras.pack(origin), origin, None, False, int(min_views), outside, device, list(device.sizes),
                       masks)
        binary = check_masks(masks, cameras, node)
        eight = getattr(masks, "alpha8", None) if use_alpha else None   # (levels read back are made when read)
        soft = bool(use_alpha and (eight is not None or masks.alpha is not None))
        levels = binary
        if soft and eight is not None:   # the key's 8-bit levels: what rint(alpha * 255) gives back, bit for bit
            for cam, m, a in zip(cameras, binary, eight):
                if a.shape != m.shape:
                    raise NodeError(f"{node}: alpha of camera '{cam.name}' is {a.shape[1]}x{a.shape[0]}, its mask "
                                    f"{m.shape[1]}x{m.shape[0]}")
            levels = [np.ascontiguousarray(a, np.uint8) for a in eight]
        elif soft:
            levels = []
            for cam, m, a in zip(cameras, binary, masks.alpha):
                a = np.asarray(a, np.float32)
                if a.shape != m.shape:
                    raise NodeError(f"{node}: alpha of camera '{cam.name}' is {a.shape[1]}x{a.shape[0]}, its mask "
                                    f"{m.shape[1]}x{m.shape[0]}")
                if not np.all(np.isfinite(a)):
                    raise NodeError(f"{node}: alpha of camera '{cam.name}' contains NaN or infinity")
                levels.append(np.ascontiguousarray(np.clip(np.rint(a * 255), 0, 255).astype(np.uint8)))
        return cls(cameras.pack(origin), origin, levels, soft, int(min_views), outside, None,
                   [(m.shape[1], m.shape[0]) for m in binary], masks)

    @property
    def sizes(self) -> list[tuple[int, int]]:
        return self.image_sizes if self.image_sizes is not None else [(m.shape[1], m.shape[0]) for m in self.masks]

    def host_masks(self) -> list[np.ndarray]:
        """The per-view uint8 masks (read back from the device silhouettes when only those were given)."""
        if self.masks is None:
            self.masks = self.bits.masks()
        return self.masks

    def pixel_values(self, v: int) -> np.ndarray:
        """View ``v``'s per-pixel values as the kernel reads them: 0/1 (binary, > 127) or level / 255."""
        m = self.host_masks()[v]
        if self.soft:
            return m.astype(np.float32) * np.float32(1.0 / 255.0)
        return (m > 127).astype(np.float32)


# ---------------------------------------------------------------- NumPy reference
def _field(points, field: SilhouetteField, v: int, values, unseen_value):
    c = field.cams[v]
    f = np.float32
    u, w, front = project_packed_f32(c, np.asarray(points, f))
    W, H = int(c[22]), int(c[23])
    with np.errstate(invalid="ignore"):
        seen = front & (u >= f(-0.5)) & (u < f(W) - f(0.5)) & (w >= f(-0.5)) & (w < f(H) - f(0.5))
    out = unseen_value
    u, w = u[seen], w[seen]
    px, py = np.floor(u + f(0.5)), np.floor(w + f(0.5))
    ix, iy = px.astype(np.int64), py.astype(np.int64)
    vals = np.pad(field.pixel_values(v), 1) if values is None else values  # off the image: 0
    nine = np.stack([vals[iy + j, ix + k] for j in range(3) for k in range(3)], axis=1)
    lo, hi = nine.min(axis=1), nine.max(axis=1)
    tx, ty = u - px, w - py
    ax, bx, ay, by = f(0.5) - tx, f(0.5) + tx, f(0.5) - ty, f(0.5) + ty
    wx = (f(0.5) * (ax * ax), f(0.75) - tx * tx, f(0.5) * (bx * bx))
    wy = (f(0.5) * (ay * ay), f(0.75) - ty * ty, f(0.5) * (by * by))
    acc = np.zeros(len(u), f)
    for j in range(3):
        acc = acc + wy[j] * ((nine[:, 3 * j] * wx[0] + nine[:, 3 * j + 1] * wx[1]) + nine[:, 3 * j + 2] * wx[2])
    out[seen] = np.where(lo == hi, lo, acc)
    return out


def view_states(points: np.ndarray, field: SilhouetteField, v: int, tau: float,
                values: np.ndarray | None = None) -> np.ndarray:
    """Per point (N, 3 float32, relative to the origin) in view v at level tau: IN, BACKGROUND or UNSEEN.
    ``values``: view v's padded pixel values (``np.pad(field.pixel_values(v), 1)``) when already made."""
    f = _field(points, field, v, values, np.full(len(points), -1.0, np.float32))
    return np.where(f < 0, UNSEEN, np.where(f >= np.float32(tau), IN, BACKGROUND)).astype(np.uint8)


def inside_at(points: np.ndarray, field: SilhouetteField, tau: float) -> np.ndarray:
    """Boolean per point (N, 3, relative to the origin): inside the hull at level ``tau``."""
    points = np.asarray(points, np.float32).reshape(-1, 3)
    n_in = np.zeros(len(points), np.int32)
    n_bg = np.zeros(len(points), np.int32)
    for v in range(len(field.cams)):
        s = view_states(points, field, v, tau)
        n_in += s == IN
        n_bg += s == BACKGROUND
    return vote(n_in, n_bg, len(field.cams), field.min_views, field.policy)


def view_values(points: np.ndarray, field: SilhouetteField, v: int, values: np.ndarray | None = None) -> np.ndarray:
    """Kernel ``view_value``: f of view v at the points, -1 where unseen."""
    state_any = np.full(len(points), -1.0, np.float32)
    return _field(points, field, v, values, state_any)


def _crossing(a, d, field, v, vals, tau, ga, hi, gb, steps):
    """Kernel ``view_crossing`` (vectorised): Illinois regula falsi on [0, hi] in view v."""
    f = np.float32
    a0, b0 = np.zeros(len(a), f), hi.copy()
    ga, gb = ga.copy(), gb.copy()
    side = np.zeros(len(a), np.int8)
    go = np.ones(len(a), bool)
    for _ in range(steps):
        go &= (b0 - a0) > f(2.4414062e-04)
        idx = np.flatnonzero(go)
        if not len(idx):
            break
        A, B, GA, GB = a0[idx], b0[idx], ga[idx], gb[idx]
        with np.errstate(all="ignore"):
            t = B - GB * ((B - A) / (GB - GA))
        bad = ~((t > A) & (t < B))
        t[bad] = f(0.5) * (A[bad] + B[bad])
        g = view_values(a[idx] + t[:, None] * d[idx], field, v, vals) - f(tau)
        up = g >= 0
        on = np.abs(g) < f(ROOT_TOL)
        s = side[idx]
        a0[idx] = np.where(up | on, t, A)
        b0[idx] = np.where(up & ~on, B, t)
        go[idx[on]] = False
        ga[idx] = np.where(up, g, np.where(s == -1, f(0.5) * GA, GA))
        gb[idx] = np.where(up, np.where(s == 1, f(0.5) * GB, GB), g)
        side[idx] = np.where(up, 1, -1)
    return a0, b0


def exit_interval(a, b, field: SilhouetteField, tau: float, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Kernel ``exit_interval``: per segment a[i] -> b[i] the parameter bracket (lo, hi) of the first exit at
    level tau; (1, 1) where the segment does not leave the hull, (0, 0) where a[i] is not inside."""
    f = np.float32
    a, b = np.asarray(a, f).reshape(-1, 3), np.asarray(b, f).reshape(-1, 3)
    d = b - a
    lo, hi = np.ones(len(a), f), np.ones(len(a), f)
    dead = np.zeros(len(a), bool)
    if field.min_views == 0 and field.policy == "carve":
        for v in range(len(field.cams)):
            vals = np.pad(field.pixel_values(v), 1)
            live = np.flatnonzero(~dead)
            gb = view_values(a[live] + hi[live, None] * d[live], field, v, vals) - f(tau)
            idx = live[gb < 0]
            gb = gb[gb < 0]
            ga = view_values(a[idx], field, v, vals) - f(tau)
            out = ga < 0
            dead[idx[out]] = True
            lo[idx[out]] = hi[idx[out]] = 0
            idx, ga, gb = idx[~out], ga[~out], gb[~out]
            lo[idx], hi[idx] = _crossing(a[idx], d[idx], field, v, vals, tau, ga, hi[idx], gb, steps)
        return lo, hi
    ins = inside_at(a, field, tau)
    lo[~ins] = hi[~ins] = 0
    idx = np.flatnonzero(ins)
    idx = idx[~inside_at(b[idx], field, tau)]
    s0, s1 = np.zeros(len(idx), f), np.ones(len(idx), f)
    for _ in range(steps + 8):
        t = f(0.5) * (s0 + s1)
        inside = inside_at(a[idx] + t[:, None] * d[idx], field, tau)
        s0, s1 = np.where(inside, t, s0), np.where(inside, s1, t)
    lo[idx], hi[idx] = s0, s1
    return lo, hi


def exit_two_levels(a, b, field: SilhouetteField, tau_hi: float, tau_lo: float, steps: int):
    """Kernel ``exit_two_levels`` (carve vote, tau_hi > tau_lo): ((lo, hi) at tau_hi, (lo, hi) at tau_lo)."""
    f = np.float32
    a, b = np.asarray(a, f).reshape(-1, 3), np.asarray(b, f).reshape(-1, 3)
    d = b - a
    lo1, hi1, lo2, hi2 = (np.ones(len(a), f) for _ in range(4))
    dead1, dead2 = np.zeros(len(a), bool), np.zeros(len(a), bool)
    for v in range(len(field.cams)):
        vals = np.pad(field.pixel_values(v), 1)
        f2 = view_values(a + hi2[:, None] * d, field, v, vals)
        f1 = f2.copy()
        differ = np.flatnonzero((hi2 != hi1) & (f2 < f(tau_hi)))
        f1[differ] = view_values(a[differ] + hi1[differ, None] * d[differ], field, v, vals)
        cut1 = ~dead1 & (f1 < f(tau_hi)) & (f2 < f(tau_hi))
        cut2 = ~dead2 & (f2 < f(tau_lo))
        idx = np.flatnonzero(cut1 | cut2)
        if not len(idx):
            continue
        fa = np.zeros(len(a), f)
        fa[idx] = view_values(a[idx], field, v, vals)
        for cut, dead, lo, hi, fx, tau in ((cut1, dead1, lo1, hi1, f1, tau_hi), (cut2, dead2, lo2, hi2, f2, tau_lo)):
            sel = np.flatnonzero(cut)
            out = fa[sel] < f(tau)
            dead[sel[out]] = True
            lo[sel[out]] = hi[sel[out]] = 0
            sel = sel[~out]
            lo[sel], hi[sel] = _crossing(a[sel], d[sel], field, v, vals, tau, fa[sel] - f(tau), hi[sel],
                                         fx[sel] - f(tau), steps)
    return (lo1, hi1), (lo2, hi2)


def cross_reference(a, b, keep, field: SilhouetteField, tau: float, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Kernel ``cross_level``: (points, found)."""
    f = np.float32
    a, b = np.asarray(a, f).reshape(-1, 3), np.asarray(b, f).reshape(-1, 3)
    out = np.asarray(keep, f).reshape(-1, 3).copy()
    lo, hi = exit_interval(a, b, field, tau, steps)
    found = (hi > 0) & (lo < 1)
    t = f(0.5) * (lo[found] + hi[found])
    out[found] = a[found] + t[:, None] * (b[found] - a[found])
    return out, found


def onto_reference(p, d, reach: float, field: SilhouetteField, tau: float, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Kernel ``onto_level``: (points, found)."""
    f = np.float32
    P = np.asarray(p, f).reshape(-1, 3)
    D = f(reach) * np.asarray(d, f).reshape(-1, 3)
    A = P - D
    lo, hi = exit_interval(A, P + D, field, tau, steps)
    found = (hi > 0) & (lo < 1)
    out = P.copy()
    out[found] = A[found] + (f(0.5) * (lo[found] + hi[found]))[:, None] * (f(2.0) * D[found])
    return out, found


def shell_interval_reference(p, d, reach: float, field: SilhouetteField, tau_in: float, tau_out: float,
                             steps: int) -> np.ndarray:
    """Kernel ``shell_interval``: (N, 4) float32 (in_lo, in_hi, out_lo, out_hi)."""
    f = np.float32
    P = np.asarray(p, f).reshape(-1, 3)
    D = f(reach) * np.asarray(d, f).reshape(-1, 3)
    A, B = P - D, P + D
    if tau_out == tau_in:
        r_in = r_out = exit_interval(A, B, field, tau_in, steps)
    elif field.min_views == 0 and field.policy == "carve" and tau_in > tau_out:
        r_in, r_out = exit_two_levels(A, B, field, tau_in, tau_out, steps)
    else:
        r_in, r_out = exit_interval(A, B, field, tau_in, steps), exit_interval(A, B, field, tau_out, steps)
    return np.stack([*r_in, *r_out], axis=1)


def active_views_reference(cull, field: SilhouetteField) -> np.ndarray:
    """Kernel ``active_views``: (N, ceil(views / 32)) uint32, bit v of a point's words 0 when view v sees its
    whole ball cull[i] = (centre relative to the origin, radius) exactly inside (``ball_all_in``)."""
    f = np.float32
    cull = np.asarray(cull, f).reshape(-1, 4)
    X, R = cull[:, :3], cull[:, 3]
    nv = len(field.cams)
    words = np.zeros((len(cull), -(-nv // 32)), np.uint32)
    for v in range(nv):
        c = field.cams[v].astype(f)
        full = field_ones(field, v)
        sat = np.pad(full.reshape(-(-full.shape[0] // 8), 8, -1, 8).sum(axis=(1, 3)).cumsum(0).cumsum(1),
                     ((1, 0), (1, 0))) if full.size else np.zeros((1, 1), np.int64)
        active = ~_ball_all_in(c, sat, X, R, full.shape)
        words[:, v // 32] |= active.astype(np.uint32) << np.uint32(v % 32)
    return words


def field_ones(field: SilhouetteField, v: int) -> np.ndarray:
    """View v's pixels whose value is exactly 1, padded with zeros to whole 8x8 blocks."""
    ones = field.pixel_values(v) == 1.0
    h, w = ones.shape
    out = np.zeros((-(-h // 8) * 8, -(-w // 8) * 8), bool)
    out[:h, :w] = ones
    return out


def _ball_all_in(c, sat, X, R, padded_shape) -> np.ndarray:
    f = np.float32
    xc = np.stack([((c[4 * k] * X[:, 0] + c[4 * k + 1] * X[:, 1]) + c[4 * k + 2] * X[:, 2]) + c[4 * k + 3]
                   for k in range(3)], axis=1)
    r0, r1, r2 = c[0:3], c[4:7], c[8:11]
    zr = R * np.sqrt(np.sum(r2 * r2))
    with np.errstate(all="ignore"):
        ok = xc[:, 2] * c[24] > f(1.001) * zr
        nx, ny = xc[:, 0] / xc[:, 2], xc[:, 1] / xc[:, 2]
        k = R / (np.abs(xc[:, 2]) - zr)
        dx = k * np.linalg.norm(r0[None] - nx[:, None] * r2[None], axis=1)
        dy = k * np.linalg.norm(r1[None] - ny[:, None] * r2[None], axis=1)
        d = c[17:22]
        if np.any(d != 0):
            r = np.sqrt(nx * nx + ny * ny) + dx + dy
            rr = r * r
            g = 1 + 2 * ((3 * abs(d[0]) + (5 * abs(d[1]) + 7 * abs(d[4]) * rr) * rr) * rr) + 12 * (abs(d[2]) + abs(d[3])) * r
            dx = dy = g * np.maximum(dx, dy)
        u, v, _ = project_packed_f32(c, X)
        ru = f(1.01) * (abs(c[12]) * dx + abs(c[13]) * dy) + f(0.01)
        rv = f(1.01) * abs(c[15]) * dy + f(0.01)
        W, H = int(c[22]), int(c[23])
        ok &= (u - ru >= -0.5) & (u + ru < W - 0.5) & (v - rv >= -0.5) & (v + rv < H - 0.5)
        x0 = np.floor(u - ru + f(0.5)) - 1
        x1 = np.floor(u + ru + f(0.5)) + 1
        y0 = np.floor(v - rv + f(0.5)) - 1
        y1 = np.floor(v + rv + f(0.5)) + 1
    ok &= (x0 >= 0) & (y0 >= 0) & (x1 < W) & (y1 < H)
    out = np.zeros(len(X), bool)
    i = np.flatnonzero(ok)
    bx0, bx1 = x0[i].astype(np.int64) >> 3, x1[i].astype(np.int64) >> 3
    by0, by1 = y0[i].astype(np.int64) >> 3, y1[i].astype(np.int64) >> 3
    count = (sat[by1 + 1, bx1 + 1] - sat[by0, bx1 + 1]) - (sat[by1 + 1, bx0] - sat[by0, bx0])
    full = (np.minimum((bx1 + 1) * 8, W) - bx0 * 8) * (np.minimum((by1 + 1) * 8, H) - by0 * 8)
    out[i] = count == full
    return out


def ball_cull(centres, radius, words: np.ndarray | None = None) -> dict:
    """A cull for the searches: per point a ball (centre relative to the origin, radius) and the words of its
    active views (None: to be computed by ``FieldCL.active``)."""
    c = np.asarray(centres, np.float32).reshape(-1, 3)
    r = np.broadcast_to(np.asarray(radius, np.float32), (len(c),))
    return {"cull": np.ascontiguousarray(np.column_stack([c, r]), np.float32), "act": words}


def split_cull(cull: dict, edges: np.ndarray) -> dict:
    """The cull of new vertices at points of ``edges`` (E, 2): the ball centred between the ends' centres that lies in
    both ends' balls (radius min(ra, rb) - |ca - cb| / 2, at least 0), with the views active for both."""
    c = cull["cull"][edges]                               # (E, 2, 4)
    gap = np.linalg.norm(c[:, 0, :3] - c[:, 1, :3], axis=1)
    r = np.maximum(np.minimum(c[:, 0, 3], c[:, 1, 3]) - np.float32(0.5) * gap, 0)
    new = np.column_stack([0.5 * (c[:, 0, :3] + c[:, 1, :3]), r]).astype(np.float32)
    act = cull["act"][edges[:, 0]] & cull["act"][edges[:, 1]]
    return {"cull": np.vstack([cull["cull"], new]), "act": np.vstack([cull["act"], act])}


# ---------------------------------------------------------------- OpenCL
class FieldCL(Runner):
    """The field on the device (kernels/hullfit.cl) and the searches over it. ``prepare`` puts the masks there:
    binary masks as SilhouetteBits (the device's one form of binary silhouettes: the producer's own when the
    MaskSet carries them, else packed here), soft masks one byte per pixel plus the block tables of their opaque
    pixels (for view culling). The searches then run on device buffers of float3 points relative to the field's
    origin, optionally with a cull (``ball_cull``: per point a ball and its active views)."""

    source = source("hullfit.cl")
    _packed: tuple = ()  # the mask arrays (kept alive) whose pixels are on the device now
    _own: SilhouetteBits | None = None  # what host masks are packed into, reused from frame to frame

    def prepare(self, field: SilhouetteField) -> "FieldCL":
        """Upload the cameras and the masks. The masks are not packed again when the field holds the very same
        mask arrays (identity) as the last call, as when refine and relax run on one MaskSet in one process; the
        arrays must not be changed in place in between."""
        import pyopencl as cl

        self.field = field
        self.cams = self.upload("cams", field.cams)
        key = (field.bits,) if field.bits is not None else (field.soft, *field.masks)
        if field.soft and field.source is not None:  # soft levels are made anew from the alpha: the MaskSet decides
            key = (True, field.source)
        if len(key) == len(self._packed) and all(a is b for a, b in zip(key, self._packed)):
            return self
        if field.bits is not None:
            self.sil = field.bits
            self.pix, self.pix_off = self.sil.bits, self.sil.bit_off_buf
            self._packed = key
            return self
        if field.soft:
            per_view = [w * h for w, h in field.sizes]
            off = np.concatenate([[0], np.cumsum(per_view)]).astype(np.int64)
            if off[-1] >= 2**31:
                raise NodeError("the masks are too large for 32-bit offsets")
            self.pix_off = self.upload("pix_off", off[:-1].astype(np.int32))
            self.pix = self.buffer("pix", max(int(off[-1]), 4))
            for v, m in enumerate(field.masks):
                cl.enqueue_copy(self.queue, self.pix, m, dst_offset=int(off[v]), is_blocking=False)
            self.sil = self._own = SilhouetteBits.from_masks(field.masks, out=self._own, opaque=True)  # of f == 1
        else:
            self.sil = self._own = SilhouetteBits.from_masks(field.masks, out=self._own)
            self.pix, self.pix_off = self.sil.bits, self.sil.bit_off_buf
        self.queue.finish()
        self._packed = key
        return self

    def field_args(self) -> tuple:
        f = self.field
        return (self.cams, np.int32(len(f.cams)), self.pix, self.pix_off, np.int32(f.soft), np.int32(f.min_views),
                np.int32(POLICIES.index(f.policy)))

    @property
    def nwords(self) -> int:
        return -(-len(self.field.cams) // 32)

    def active(self, cull: dict) -> dict:
        """``cull`` with its active views' words computed (kernel ``active_views``)."""
        c = cull["cull"]
        n = len(c)
        d_c = self.upload("cull", c if n else np.zeros((1, 4), np.float32))
        out = self.buffer("act", max(n * self.nwords * 4, 4))
        self.launch("active_views", *self._groups(n), d_c, np.int32(n), self.cams, np.int32(len(self.field.cams)),
                    self.sil.sat, self.sil.sat_off_buf, np.int32(self.nwords), out)
        return {"cull": c, "act": self.read(out, (n, self.nwords), np.uint32)}

    def cull_args(self, cull: dict | None, sub=None) -> tuple:
        """Kernel arguments of a cull (rows ``sub`` of it when given), or of none: every view visited."""
        if cull is None or cull.get("act") is None or max(self._levels, default=0) >= 0.9999:
            return (self.buffer("no_cull", 16), self.buffer("no_act", 4), np.int32(self.nwords), np.int32(0))
        c, a = cull["cull"], cull["act"]
        if sub is not None:
            c, a = c[sub], a[sub]
        if len(c) == 0:
            return (self.buffer("no_cull", 16), self.buffer("no_act", 4), np.int32(self.nwords), np.int32(0))
        return (self.upload("cull_c", c), self.upload("cull_a", np.ascontiguousarray(a, np.uint32)),
                np.int32(self.nwords), np.int32(1))

    _levels: tuple = ()

    @staticmethod
    def _groups(n: int) -> tuple:
        return (round_up(max(n, 1), 64),), (64,)

    def inside(self, d_p, n: int, tau: float, d_out):
        self.launch("inside_level", *self._groups(n), d_p, np.int32(n), np.float32(tau), *self.field_args(), d_out)

    def cross(self, d_a, d_b, d_keep, n: int, tau: float, steps: int, d_out, d_found, cull=None):
        self._levels = (tau,)
        self.launch("cross_level", *self._groups(n), d_a, d_b, d_keep, np.int32(n), np.float32(tau), np.int32(steps),
                    *self.field_args(), *self.cull_args(cull), d_out, d_found)

    def onto(self, d_p, d_dir, reach: float, n: int, tau: float, steps: int, d_out, d_found, cull=None):
        self._levels = (tau,)
        self.launch("onto_level", *self._groups(n), d_p, d_dir, np.float32(reach), np.int32(n), np.float32(tau),
                    np.int32(steps), *self.field_args(), *self.cull_args(cull), d_out, d_found)

    def shell(self, d_p, d_dir, reach: float, n: int, tau_in: float, tau_out: float, steps: int, d_out, cull=None):
        self._levels = (tau_in, tau_out)
        self.launch("shell_interval", *self._groups(n), d_p, d_dir, np.float32(reach), np.int32(n), np.float32(tau_in),
                    np.float32(tau_out), np.int32(steps), *self.field_args(), *self.cull_args(cull), d_out)

    # host-array conveniences (tests, small inputs)
    def _pts(self, role: str, x) -> tuple:
        x = np.ascontiguousarray(x, np.float32).reshape(-1, 3)
        return self.upload(role, x), len(x)

    def inside_host(self, points, tau: float) -> np.ndarray:
        d, n = self._pts("h_p", points)
        out = self.buffer("h_u8", max(n, 4))
        self.inside(d, n, tau, out)
        return self.read(out, (n,), np.uint8).astype(bool)

    def cross_host(self, a, b, keep, tau: float, steps: int, cull=None):
        (da, n), (db, _), (dk, _) = self._pts("h_a", a), self._pts("h_b", b), self._pts("h_k", keep)
        out, found = self.buffer("h_out", max(n * 12, 4)), self.buffer("h_u8", max(n, 4))
        self.cross(da, db, dk, n, tau, steps, out, found, cull)
        return self.read(out, (n, 3), np.float32), self.read(found, (n,), np.uint8).astype(bool)

    def onto_host(self, p, d, reach: float, tau: float, steps: int, cull=None):
        (dp, n), (dd, _) = self._pts("h_a", p), self._pts("h_b", d)
        out, found = self.buffer("h_out", max(n * 12, 4)), self.buffer("h_u8", max(n, 4))
        self.onto(dp, dd, reach, n, tau, steps, out, found, cull)
        return self.read(out, (n, 3), np.float32), self.read(found, (n,), np.uint8).astype(bool)

    def shell_host(self, p, d, reach: float, tau_in: float, tau_out: float, steps: int, cull=None):
        (dp, n), (dd, _) = self._pts("h_a", p), self._pts("h_b", d)
        out = self.buffer("h_out4", max(n * 16, 4))
        self.shell(dp, dd, reach, n, tau_in, tau_out, steps, out, cull)
        return self.read(out, (n, 4), np.float32)

    def pixels(self) -> np.ndarray:
        """The binary masks' bits back on the host (for checks)."""
        return self.read(self.sil.bits, (int(self.sil.bit_off[-1]),), np.uint8)
