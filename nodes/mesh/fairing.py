"""Mesh fairing inside a silhouette shell (kernels/fairing.cl, NumPy references here).

The fairing smooths normals before positions (Sun et al., "Fast and effective feature-preserving mesh
denoising", TVCG 2007; Taubin, "Linear anisotropic mesh filtering", 2001): face normals are replaced by the
mean of their corners' normals (``filter_rounds`` times), then every vertex moves towards the planes of its
faces with those filtered normals (the mean of m (m . (centroid - p))), which flattens the marching-cubes
staircase and the silhouettes' pixel steps without the shrinkage of Laplacian smoothing, and tangentially
towards the mean of its neighbours (``lam_t``), which evens out the triangles (no slivers). A vertex with a
face turned against its filtered normal (a fold) takes half an umbrella step instead, which opens the fold. Positions are then
clamped to the shell of the silhouettes along fixed lines (``shell_clamp``).

Vertex -> face incidence is a CSR table (``vertex_faces``) built once per mesh.
"""
from __future__ import annotations

import numpy as np

from kernels import source
from nodegraph.clrt import Runner, round_up


def vertex_faces(faces: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR of each vertex's faces: (off (count + 1,) int32, idx int32), faces in increasing order."""
    flat = np.asarray(faces, np.int64).reshape(-1)
    order = np.argsort(flat, kind="stable")
    off = np.zeros(count + 1, np.int64)
    off[1:] = np.cumsum(np.bincount(flat, minlength=count))
    return off.astype(np.int32), (order // 3).astype(np.int32)


# ---------------------------------------------------------------- NumPy references (float32, kernel order)
def _unit(x: np.ndarray) -> np.ndarray:
    n = np.sqrt((x[:, 0] * x[:, 0] + x[:, 1] * x[:, 1]) + x[:, 2] * x[:, 2])
    out = x.copy()
    ok = n > 0
    out[ok] = x[ok] / n[ok, None]
    return out


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]) + a[:, 2] * b[:, 2]


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                     a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)


def face_normals_reference(v, f) -> np.ndarray:
    v = np.asarray(v, np.float32)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return _cross(b - a, c - a)


def _per_vertex_sum(fv, off, idx) -> np.ndarray:
    """Sum of face vectors per vertex, in CSR order (the kernel's loop)."""
    counts = np.diff(off)
    out = np.zeros((len(counts), 3), np.float32)
    gathered = np.asarray(fv, np.float32)[idx]
    for j in range(int(counts.max(initial=0))):
        rows = np.flatnonzero(counts > j)
        out[rows] = out[rows] + gathered[off[rows] + j]
    return out


def vertex_normals_reference(fv, off, idx) -> np.ndarray:
    return _unit(_per_vertex_sum(fv, off, idx))


def face_filter_reference(vn, f) -> np.ndarray:
    vn = np.asarray(vn, np.float32)
    return _unit((vn[f[:, 0]] + vn[f[:, 1]]) + vn[f[:, 2]])


def fair_step_reference(v, f, off, idx, m, vn, lam_t: float) -> np.ndarray:
    v = np.asarray(v, np.float32)
    m = np.asarray(m, np.float32)
    corners = (v[f[:, 0]] + v[f[:, 1]]) + v[f[:, 2]]
    counts = np.diff(off)
    flipped = _dot(face_normals_reference(v, f), m) < 0
    dn = np.zeros_like(v)
    ring = np.zeros_like(v)
    folded = np.zeros(len(v), bool)
    for j in range(int(counts.max(initial=0))):
        rows = np.flatnonzero(counts > j)
        k = idx[off[rows] + j]
        mf = m[k]
        dn[rows] = dn[rows] + mf * _dot(mf, corners[k] / np.float32(3.0) - v[rows])[:, None]
        ring[rows] = ring[rows] + corners[k]
        folded[rows] |= flipped[k]
    out = v.copy()
    has = counts > 0
    cnt = counts[has].astype(np.float32)[:, None]
    p = v[has]
    t = (ring[has] - cnt * p) / (np.float32(2.0) * cnt) - p
    umbrella = p + np.float32(0.5) * t
    n = np.asarray(vn, np.float32)[has]
    t = t - _dot(t, n)[:, None] * n
    out[has] = np.where(folded[has, None], umbrella, (p + dn[has] / cnt) + np.float32(lam_t) * t)
    return out


def shell_clamp_reference(v, centre, axis, shell, reach: float, across: float, onto: bool = False) -> np.ndarray:
    f = np.float32
    n, p = np.asarray(axis, f), np.asarray(v, f)
    A = np.asarray(centre, f) - f(reach) * n
    shell = np.asarray(shell, f)
    lo, hi = shell[:, 1].copy(), shell[:, 0 if onto else 2].copy()
    none = shell[:, 1 if onto else 3] == 0
    lo[none], hi[none] = 0, 1
    swap = lo > hi
    lo[swap] = hi[swap] = f(0.5) * (lo[swap] + hi[swap])
    d = p - A
    length = f(2.0) * f(reach)
    s = _dot(d, n) / length
    t = d - (s * length)[:, None] * n
    tl = np.sqrt(_dot(t, t))
    big = tl > f(across)
    t[big] = t[big] * (f(across) / tl[big])[:, None]
    s = np.minimum(np.maximum(s, lo), hi)
    return (A + (s * length)[:, None] * n) + t


def unfold_step_reference(v, f, off, idx) -> tuple[np.ndarray, int]:
    """Kernel ``unfold_step``: (vertices, how many moved). A vertex is at a fold when two of its faces that share an
    edge have unit normals more than 150 degrees apart."""
    v = np.asarray(v, np.float32)
    fn = _unit(face_normals_reference(v, f))
    corners = (v[f[:, 0]] + v[f[:, 1]]) + v[f[:, 2]]
    out = v.copy()
    moved = 0
    for i in range(len(v)):
        faces = idx[off[i]:off[i + 1]]
        if not len(faces):
            continue
        n = fn[faces]
        cos = (n[:, None, 0] * n[None, :, 0] + n[:, None, 1] * n[None, :, 1]) + n[:, None, 2] * n[None, :, 2]
        corner = f[faces]
        others = [set(c.tolist()) - {i} for c in corner]
        share = np.array([[bool(a & b) for b in others] for a in others])
        if ((cos < np.float32(-0.8660254)) & share).any():
            ring = np.zeros(3, np.float32)
            for k in faces:
                ring = ring + corners[k]
            cnt = np.float32(len(faces))
            out[i] = v[i] + np.float32(0.5) * ((ring - cnt * v[i]) / (np.float32(2.0) * cnt) - v[i])
            moved += 1
    return out, moved


# ---------------------------------------------------------------- OpenCL
class FairCL(Runner):
    """The fairing kernels on device buffers (kernels/fairing.cl)."""

    source = source("fairing.cl")

    @staticmethod
    def _groups(n: int) -> tuple:
        return (round_up(max(n, 1), 64),), (64,)

    def face_normals(self, d_v, d_f, nf: int, d_out):
        self.launch("face_normals", *self._groups(nf), d_v, d_f, np.int32(nf), d_out)

    def vertex_normals(self, d_fv, d_off, d_idx, nv: int, d_out):
        self.launch("vertex_normals", *self._groups(nv), d_fv, d_off, d_idx, np.int32(nv), d_out)

    def face_filter(self, d_vn, d_f, nf: int, d_out):
        self.launch("face_filter", *self._groups(nf), d_vn, d_f, np.int32(nf), d_out)

    def fair_step(self, d_v, d_f, d_off, d_idx, d_m, d_vn, lam_t: float, nv: int, d_out):
        self.launch("fair_step", *self._groups(nv), d_v, d_f, d_off, d_idx, d_m, d_vn, np.float32(lam_t), np.int32(nv),
                    d_out)

    def unfold_step(self, d_v, d_f, d_off, d_idx, nv: int, d_out) -> int:
        count = self.upload("unfold_count", np.zeros(1, np.int32))
        self.launch("unfold_step", *self._groups(nv), d_v, d_f, d_off, d_idx, np.int32(nv), d_out, count)
        return int(self.read(count, (1,), np.int32)[0])

    def shell_clamp(self, d_v, d_centre, d_axis, d_shell, reach: float, across: float, nv: int, d_out,
                    onto: bool = False):
        self.launch("shell_clamp", *self._groups(nv), d_v, d_centre, d_axis, d_shell, np.float32(reach),
                    np.float32(across), np.int32(onto), np.int32(nv), d_out)


# ---------------------------------------------------------------- the fairing loop, on either backend
class NumPyOps:
    """The fairing loop's operations on host arrays (the references above and in hullfit). ``role`` names the
    output (it matters for the device backend only)."""

    def __init__(self, vertices, faces, field=None, cull=None):
        from . import hullfit

        self.h = hullfit
        self.f = np.ascontiguousarray(faces, np.int32).reshape(-1, 3)
        self.off, self.idx = vertex_faces(self.f, len(vertices))
        self.field = field
        self.cull = cull  # (the reference visits every view: the cull changes nothing)
        self.v = np.asarray(vertices, np.float32).reshape(-1, 3)

    def face_normals(self, v, role):
        return face_normals_reference(v, self.f)

    def vertex_normals(self, fv, role):
        return vertex_normals_reference(fv, self.off, self.idx)

    def face_filter(self, vn, role):
        return face_filter_reference(vn, self.f)

    def fair_step(self, v, m, vn, lam_t, role):
        return fair_step_reference(v, self.f, self.off, self.idx, m, vn, lam_t)

    def shell(self, v, axis, reach, tau_in, tau_out, steps, role):
        return self.h.shell_interval_reference(v, axis, reach, self.field, tau_in, tau_out, steps)

    def clamp(self, v, centre, axis, shell, reach, across, role, onto=False):
        return shell_clamp_reference(v, centre, axis, shell, reach, across, onto)

    def unfold(self, v, role):
        return unfold_step_reference(v, self.f, self.off, self.idx)

    def put(self, x, role, width=3):
        return np.asarray(x, np.float32).reshape(-1, width)

    def get(self, x, width=3) -> np.ndarray:
        return np.asarray(x, np.float32).reshape(-1, width).copy()

    def copy(self, v, role):
        return np.array(v, copy=True)

    def read(self, v) -> np.ndarray:
        return np.asarray(v, np.float32)


class CLOps:
    """The same operations on device buffers (FairCL, FieldCL); each output goes to the runner's buffer called
    ``role`` (kept between calls); ``read`` brings vertices back."""

    def __init__(self, vertices, faces, field_cl=None, cull=None):
        import pyopencl as cl

        self.cl = cl
        self.k = FairCL.get()
        self.fc = field_cl
        self.cull = cull  # hullfit.ball_cull with its active views: the shell searches visit only those
        f = np.ascontiguousarray(faces, np.int32).reshape(-1, 3)
        self.nv, self.nf = len(vertices), len(f)
        off, idx = vertex_faces(f, self.nv)
        k = self.k
        self.d_f = k.upload("faces", f if len(f) else np.zeros(3, np.int32))
        self.d_off = k.upload("off", off)
        self.d_idx = k.upload("idx", idx if len(idx) else np.zeros(1, np.int32))
        self.v = k.upload("v_in", np.ascontiguousarray(vertices, np.float32).reshape(-1, 3))

    def _out(self, role: str, items: int, width: int = 3):
        return self.k.buffer(role, max(items * width * 4, 16))

    def face_normals(self, v, role):
        out = self._out(role, self.nf)
        self.k.face_normals(v, self.d_f, self.nf, out)
        return out

    def vertex_normals(self, fv, role):
        out = self._out(role, self.nv)
        self.k.vertex_normals(fv, self.d_off, self.d_idx, self.nv, out)
        return out

    def face_filter(self, vn, role):
        out = self._out(role, self.nf)
        self.k.face_filter(vn, self.d_f, self.nf, out)
        return out

    def fair_step(self, v, m, vn, lam_t, role):
        out = self._out(role, self.nv)
        self.k.fair_step(v, self.d_f, self.d_off, self.d_idx, m, vn, lam_t, self.nv, out)
        return out

    def shell(self, v, axis, reach, tau_in, tau_out, steps, role):
        out = self._out(role, self.nv, 4)
        self.fc.shell(v, axis, reach, self.nv, tau_in, tau_out, steps, out, self.cull)
        return out

    def clamp(self, v, centre, axis, shell, reach, across, role, onto=False):
        out = self._out(role, self.nv)
        self.k.shell_clamp(v, centre, axis, shell, reach, across, self.nv, out, onto)
        return out

    def unfold(self, v, role):
        out = self._out(role, self.nv)
        return out, self.k.unfold_step(v, self.d_f, self.d_off, self.d_idx, self.nv, out)

    def copy(self, v, role):
        out = self._out(role, self.nv)
        self.cl.enqueue_copy(self.k.queue, out, v, byte_count=self.nv * 12)
        return out

    def read(self, v) -> np.ndarray:
        return self.k.read(v, (self.nv, 3), np.float32)

    def put(self, x, role, width=3):
        return self.k.upload(role, np.ascontiguousarray(x, np.float32).reshape(-1, width))

    def get(self, x, width=3) -> np.ndarray:
        return self.k.read(x, (self.nv, width), np.float32)


def smoothed_normals(ops, v, filter_rounds: int, prefix: str = ""):
    """(vertex normals of the filtered face normals, filtered face normals, plain vertex normals)."""
    plain = ops.vertex_normals(ops.face_normals(v, "fn"), prefix + "plain")
    vn, m = plain, ops.face_filter(plain, "m0")
    for r in range(filter_rounds - 1):
        vn = ops.vertex_normals(m, f"vn{r % 2}")
        m = ops.face_filter(vn, f"m{(r + 1) % 2}")
    return ops.vertex_normals(m, prefix + "smooth"), m, plain


def fair(ops, *, rounds: int = 2, iterations: int = 5, filter_rounds: int = 2, lam_t: float = 0.5,
         shell=None, reach: float = 0.0, across: float = 0.0, steps: int = 8, clamp_steps: bool = True,
         unfold: int = 12, final: str = "none"):
    """The fairing loop: ``rounds`` x (lines along the smoothed normals and their shell intervals, then
    ``iterations`` fairing steps each clamped to the shell: along the line to its interval, across it to at
    most ``across``; with ``clamp_steps`` false the steps run free). ``shell`` = (tau_in, tau_out) or None;
    ``final``: "none", "clamp" (a last clamp along fresh lines through the final positions, nothing across: every
    vertex exactly into the shell) or "onto" (the same onto the deep level tau_in). Then at most ``unfold`` fold
    repair steps move the vertices at a fold (faces more than 150 degrees apart), if any. Returns (vertices,
    the final lines (centre, axis, shell) or None) as backend handles, and how many vertices were still at a
    fold before the last repair step (0: no fold left)."""
    v = ops.v
    k = 0

    def search(v):
        axis, _, _ = smoothed_normals(ops, v, filter_rounds, "axis_")
        centre = ops.copy(v, "centre")
        sh = ops.shell(centre, axis, reach, shell[0], shell[1], steps, "shell")
        return centre, axis, sh

    last = None
    for r in range(rounds):
        if shell is not None and clamp_steps:
            centre, axis, sh = search(v)
        for _ in range(iterations):
            _, m, plain = smoothed_normals(ops, v, filter_rounds)
            k += 1
            v = ops.fair_step(v, m, plain, lam_t, f"v{k % 2}")
            if shell is not None and clamp_steps:
                k += 1
                v = ops.clamp(v, centre, axis, sh, reach, across, f"v{k % 2}")
    if shell is not None and final != "none":
        last = search(v)
        k += 1
        v = ops.clamp(v, *last, reach, 0.0, f"v{k % 2}", onto=final == "onto")
    moved = 0
    for _ in range(unfold):  # folds the clamp left: half umbrella steps on the vertices at a fold
        k += 1
        v, moved = ops.unfold(v, f"v{k % 2}")
        if not moved:
            break
    return v, last, moved
