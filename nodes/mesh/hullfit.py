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
from nodes.common.silhouettes import POLICIES, check_masks, vote

IN, BACKGROUND, UNSEEN = 1, 2, 3


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
    masks: list[np.ndarray]          # uint8 (H, W): binary (> 127 inside) or alpha * 255
    soft: bool
    min_views: int = 0
    policy: str = "carve"

    @classmethod
    def from_inputs(cls, masks, cameras: Cameras, origin, min_views: int = 0, outside: str = "carve",
                    use_alpha: bool = True, node: str = "refine") -> "SilhouetteField":
        """Check a MaskSet against the cameras (NodeError naming the camera) and pack both."""
        if masks is None or cameras is None:
            raise NodeError(f"{node}: needs both 'masks' and 'cameras' inputs")
        binary = check_masks(masks, cameras, node)
        if min_views > len(cameras):
            raise NodeError(f"{node}: min_views {min_views} is more than the {len(cameras)} cameras")
        if outside not in POLICIES:
            raise NodeError(f"{node}: outside must be one of {', '.join(POLICIES)}, got {outside!r}")
        soft = bool(use_alpha and masks.alpha is not None)
        levels = binary
        if soft:
            levels = []
            for cam, m, a in zip(cameras, binary, masks.alpha):
                a = np.asarray(a, np.float32)
                if a.shape != m.shape:
                    raise NodeError(f"{node}: alpha of camera '{cam.name}' is {a.shape[1]}x{a.shape[0]}, its mask "
                                    f"{m.shape[1]}x{m.shape[0]}")
                if not np.all(np.isfinite(a)):
                    raise NodeError(f"{node}: alpha of camera '{cam.name}' contains NaN or infinity")
                levels.append(np.ascontiguousarray(np.clip(np.rint(a * 255), 0, 255).astype(np.uint8)))
        origin = np.asarray(origin, np.float64).reshape(3)
        return cls(cameras.pack(origin), origin, levels, soft, int(min_views), outside)

    @property
    def sizes(self) -> list[tuple[int, int]]:
        return [(m.shape[1], m.shape[0]) for m in self.masks]

    def pixel_values(self, v: int) -> np.ndarray:
        """View ``v``'s per-pixel values as the kernel reads them: 0/1 (binary, > 127) or level / 255."""
        m = self.masks[v]
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
        s = side[idx]
        a0[idx] = np.where(up, t, A)
        b0[idx] = np.where(up, B, t)
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
        f1 = view_values(a + hi1[:, None] * d, field, v, vals)
        f2 = f1.copy()
        differ = np.flatnonzero(hi2 != hi1)
        f2[differ] = view_values(a[differ] + hi2[differ, None] * d[differ], field, v, vals)
        cut1 = ~dead1 & (f1 < f(tau_hi))
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


def pack_bits_reference(mask: np.ndarray) -> np.ndarray:
    """Kernel ``pack_bits`` for one view: (H, ceil(W/8)) uint8, pixel x in bit x % 8 of byte x // 8."""
    return np.packbits(np.asarray(mask) > 127, axis=1, bitorder="little")


# ---------------------------------------------------------------- OpenCL
class FieldCL(Runner):
    """The field on the device (kernels/hullfit.cl) and the searches over it. ``prepare`` puts the masks there
    (binary: packed bits, from the host arrays without a copy; soft: one byte per pixel); the searches then run
    on device buffers of float3 points relative to the field's origin."""

    source = source("hullfit.cl")
    _packed: tuple = ()  # the mask arrays (kept alive) whose pixels are on the device now

    def prepare(self, field: SilhouetteField) -> "FieldCL":
        """Upload the cameras and pack the masks. Packing is skipped when the field holds the very same mask
        arrays (identity) as the last call, as when refine and relax run on one MaskSet in one process; the
        arrays must not be changed in place in between."""
        import pyopencl as cl

        self.field = field
        sizes = field.sizes
        self.cams = self.upload("cams", field.cams)
        if len(self._packed) == len(field.masks) + 1 and self._packed[0] == field.soft and all(
                a is b for a, b in zip(self._packed[1:], field.masks)):
            return self
        per_view = [(w * h if field.soft else -(-w // 8) * h) for w, h in sizes]
        off = np.concatenate([[0], np.cumsum(per_view)]).astype(np.int64)
        if off[-1] >= 2**31:
            raise NodeError("the masks are too large for 32-bit offsets")
        self.pix_off = self.upload("pix_off", off[:-1].astype(np.int32))
        self.pix = self.buffer("pix", max(int(off[-1]), 4))
        host = []  # zero-copy views of the host masks, alive until the queue is done
        for v, m in enumerate(field.masks):
            if field.soft:
                cl.enqueue_copy(self.queue, self.pix, m, dst_offset=int(off[v]), is_blocking=False)
                continue
            src = self.host(m)
            host.append(src)
            h, w = m.shape
            self.launch("pack_bits", (round_up(-(-w // 8), 16), round_up(h, 4)), (16, 4), src, np.int32(w), np.int32(h),
                        self.pix, np.int32(off[v]))
        self.queue.finish()
        self._packed = (field.soft, *field.masks)
        return self

    def field_args(self) -> tuple:
        f = self.field
        return (self.cams, np.int32(len(f.cams)), self.pix, self.pix_off, np.int32(f.soft), np.int32(f.min_views),
                np.int32(POLICIES.index(f.policy)))

    @staticmethod
    def _groups(n: int) -> tuple:
        return (round_up(max(n, 1), 64),), (64,)

    def inside(self, d_p, n: int, tau: float, d_out):
        self.launch("inside_level", *self._groups(n), d_p, np.int32(n), np.float32(tau), *self.field_args(), d_out)

    def cross(self, d_a, d_b, d_keep, n: int, tau: float, steps: int, d_out, d_found):
        self.launch("cross_level", *self._groups(n), d_a, d_b, d_keep, np.int32(n), np.float32(tau), np.int32(steps),
                    *self.field_args(), d_out, d_found)

    def onto(self, d_p, d_dir, reach: float, n: int, tau: float, steps: int, d_out, d_found):
        self.launch("onto_level", *self._groups(n), d_p, d_dir, np.float32(reach), np.int32(n), np.float32(tau),
                    np.int32(steps), *self.field_args(), d_out, d_found)

    def shell(self, d_p, d_dir, reach: float, n: int, tau_in: float, tau_out: float, steps: int, d_out):
        self.launch("shell_interval", *self._groups(n), d_p, d_dir, np.float32(reach), np.int32(n), np.float32(tau_in),
                    np.float32(tau_out), np.int32(steps), *self.field_args(), d_out)

    # host-array conveniences (tests, small inputs)
    def _pts(self, role: str, x) -> tuple:
        x = np.ascontiguousarray(x, np.float32).reshape(-1, 3)
        return self.upload(role, x), len(x)

    def inside_host(self, points, tau: float) -> np.ndarray:
        d, n = self._pts("h_p", points)
        out = self.buffer("h_u8", max(n, 4))
        self.inside(d, n, tau, out)
        return self.read(out, (n,), np.uint8).astype(bool)

    def cross_host(self, a, b, keep, tau: float, steps: int):
        (da, n), (db, _), (dk, _) = self._pts("h_a", a), self._pts("h_b", b), self._pts("h_k", keep)
        out, found = self.buffer("h_out", max(n * 12, 4)), self.buffer("h_u8", max(n, 4))
        self.cross(da, db, dk, n, tau, steps, out, found)
        return self.read(out, (n, 3), np.float32), self.read(found, (n,), np.uint8).astype(bool)

    def onto_host(self, p, d, reach: float, tau: float, steps: int):
        (dp, n), (dd, _) = self._pts("h_a", p), self._pts("h_b", d)
        out, found = self.buffer("h_out", max(n * 12, 4)), self.buffer("h_u8", max(n, 4))
        self.onto(dp, dd, reach, n, tau, steps, out, found)
        return self.read(out, (n, 3), np.float32), self.read(found, (n,), np.uint8).astype(bool)

    def shell_host(self, p, d, reach: float, tau_in: float, tau_out: float, steps: int):
        (dp, n), (dd, _) = self._pts("h_a", p), self._pts("h_b", d)
        out = self.buffer("h_out4", max(n * 16, 4))
        self.shell(dp, dd, reach, n, tau_in, tau_out, steps, out)
        return self.read(out, (n, 4), np.float32)

    def pixels(self) -> np.ndarray:
        """The packed masks back on the host (for checks)."""
        return self.read(self.pix, (int(sum((w * h if self.field.soft else -(-w // 8) * h) for w, h in self.field.sizes)),),
                         np.uint8)
