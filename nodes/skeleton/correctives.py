"""Corrective shapes: what linear blend skinning leaves of a tracked sequence, kept as K blend shapes (morph
targets) and their weights per frame, so that an exported rig reproduces the sequence it was fitted to.

A glTF player and UsdSkel both add blend shapes to the rest points *before* skinning, so a frame's correction
of vertex v is the residual taken back through that vertex's blended LBS transform: with A_fv = sum_k w_vk R_fj
and b_fv = sum_k w_vk t_fj (j = the vertex's k-th joint), the file skins A_fv (x_v + d_fv) + b_fv, which is the
tracked point y_fv exactly when d_fv = A_fv^-1 (y_fv - b_fv) - x_v (a pose-space corrective, one per frame).
K >= the frame count keeps every frame exactly that way (the (F, 3V) matrix of these displacements, its SVD).
Fewer shapes are fitted where the error counts, in the posed space: minimise sum_fv |A_fv (W_f . D_v) - r_fv|^2
(r = y - LBS) over K rest-space shapes D and an (F, K) weight curve W. A_fv is far from a rotation where the
blended joints turn apart (a T-pose rest of a moving arm: on child_rope 13 % of the (frame, vertex) pairs have
det A < 0.3, some ~0), so the exact rest residuals there are huge, and their truncated SVD spends its shapes on
them: 8 shapes made a segment's worst vertex 1.27 m off, where plain LBS left 0.23 m. So the start is the SVD of
the damped residuals (A^T A + DAMPING I)^-1 A^T r, then ``ROUNDS`` of alternating least squares in the posed
space: the shapes per vertex (3K normal equations over the frames), the weights per frame (K x K); the weights
last, so no frame's rms is above plain LBS's. Given a per-frame goal (rms, max: skeleton.export's ``goal``, 1 % / 5 %
of the height), further rounds weigh the frames and vertices beyond it more (``_towards_goal``): least squares
minimises the total and leaves a few frames just beyond (child_rope, 32 shapes: 172 -> 198 of 200 frames within). The weights are then made what a DCC slider holds, 0..1: a shape
whose weights take both signs is kept as two (itself on its positive side, its negation on the negative side;
the same deformation), one of one sign turned positive, each scaled so its weights reach 1. Blender's glTF
importer (4.5) clamps a shape key to [slider_min, 1] and takes slider_min from the first key only, so negative
weights came out clamped: on child_rope frame 40 the mesh 10.0 mm (median) from the tracked surface in Blender
against 6.3 read by us. The error after correction is measured in the posed (skinned) space, per frame.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

LOG = logging.getLogger("volcap.skeleton")

DAMPING = 0.01     # the start's rest residuals: (A^T A + DAMPING I)^-1 A^T r (A ~ a rotation: 1 on its diagonal)
ROUNDS = 1         # alternating least squares rounds (shapes, then weights) after the start
GOAL_ROUNDS = 5    # further rounds towards a per-frame goal, frames and vertices beyond it weighing more (``goal``)
GOAL_MARGIN = (0.9, 0.5)   # ... a frame's weight grows once its rms passes 0.9 x the goal's, a vertex's at half its max

@dataclass
class Correctives:
    """K shapes (K, V, 3) rest-space displacements, weights (F, K), and the per-frame posed error (rms and max,
    metres) of plain LBS and of LBS with the shapes."""

    shapes: np.ndarray
    weights: np.ndarray
    lbs_rms: np.ndarray
    lbs_max: np.ndarray
    rms: np.ndarray
    max: np.ndarray
    fitted: int = 0          # the shapes fitted (each one or two of ``shapes``: its sides)
    goal: tuple | None = None   # (rms, max) metres each frame was fitted towards, or None
    goal_rounds: int = 0     # the reweighted rounds of the kept fit (0: the least-squares fit)
    own: tuple = ()          # rows (frames of the fit) that got a shape of their own (``frame_shapes``), the last shapes
    asked: bool = False      # frame shapes were asked for (the report then lists them, also none)
    beyond: tuple = ()       # per row still beyond the goal: (row, worst vertex, its blended transform's smallest
                             # singular value: near 0 where two of its bones turn apart, which no shape can undo)

    def table(self, frames=None) -> dict:
        """The report's record; ``frames``: the frame number of each row (for ``frame_shapes``; default the rows)."""
        r = lambda a: [round(float(x), 7) for x in a]  # noqa: E731
        return {"shapes": int(len(self.shapes)), "fitted": int(self.fitted), "lbs_rms": r(self.lbs_rms), "lbs_max": r(self.lbs_max),
                "corrected_rms": r(self.rms), "corrected_max": r(self.max),
                "lbs_rms_total": float(np.sqrt((self.lbs_rms ** 2).mean())),
                "corrected_rms_total": float(np.sqrt((self.rms ** 2).mean())),
                "corrected_max_total": float(self.max.max()) if len(self.max) else 0.0,
                **({"frame_shapes": [int(i if frames is None else frames[i]) for i in self.own]} if self.asked else {}),
                **({"beyond_goal": [{"frame": int(i if frames is None else frames[i]), "vertex": int(v),
                                     "sigma_min": round(float(sv), 4)} for i, v, sv in self.beyond]}
                   if self.goal is not None and self.fitted else {}),
                **({} if self.goal is None else {
                    "goal_m": [round(float(g), 7) for g in self.goal], "goal_rounds": int(self.goal_rounds),
                    "frames_within_goal": {"lbs": int(np.sum((self.lbs_rms <= self.goal[0]) & (self.lbs_max <= self.goal[1]))),
                                           "corrected": int(np.sum((self.rms <= self.goal[0]) & (self.max <= self.goal[1])))}})}


def blended_transforms(indices, weights, rotations, translations) -> tuple[np.ndarray, np.ndarray]:
    """(A (F, V, 3, 3), b (F, V, 3)): each vertex's blended LBS transform per frame from sparse influences
    (``formats.sparse_influences``) and (F, J, 3, 3) rotations, (F, J, 3) translations."""
    r = np.asarray(rotations, np.float64)[:, indices]             # (F, V, k, 3, 3)
    t = np.asarray(translations, np.float64)[:, indices]          # (F, V, k, 3)
    return np.einsum("vk,fvkab->fvab", weights, r), np.einsum("vk,fvka->fva", weights, t)


def rest_residuals(vertices, indices, weights, rotations, translations, targets) -> np.ndarray:
    """(F, V, 3) per-frame rest-space displacements d with A (x + d) + b = target (the module docstring); a
    vertex whose blended transform is singular (opposed rotations cancelling) gets the least-squares one."""
    a, b = blended_transforms(indices, weights, rotations, translations)
    rhs = np.asarray(targets, np.float64) - b
    try:
        local = np.linalg.solve(a, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:
        local = np.einsum("fvab,fvb->fva", np.linalg.pinv(a), rhs)
    return local - np.asarray(vertices, np.float64)[None]


def _posed_weights(a, r, shapes, omega=None, frames=None) -> np.ndarray:
    """(F, K) per frame the weights of ``shapes`` (K, V, 3) that minimise the posed error |A (W . D) - r|^2
    (each vertex's term times ``omega`` (F, V) where given); ``frames``: only these rows are solved (others 0)."""
    f, k = len(r), len(shapes)
    w = np.zeros((f, k))
    by_vertex = np.ascontiguousarray(np.transpose(shapes, (1, 2, 0)))          # (V, 3, K)
    for i in range(f) if frames is None else frames:
        s = np.matmul(a[i], by_vertex)                                        # (V, 3, K): A_v D_v per shape
        rhs = r[i]
        if omega is not None:
            root = np.sqrt(omega[i])[:, None]
            s, rhs = s * root[:, :, None], rhs * root
        s = s.reshape(-1, k)
        m = s.T @ s
        m[np.diag_indices(k)] += 1e-9 * np.trace(m) / k + 1e-15
        w[i] = np.linalg.solve(m, s.T @ rhs.ravel())
    return w


def _posed(a, w, shapes) -> np.ndarray:
    """(F, V, 3) the shapes' displacement A_fv (sum_k w_fk D_kv) in the posed space (one product, then batched 3x3)."""
    d = (w @ shapes.reshape(len(shapes), 3 * shapes.shape[1])).reshape(len(w), shapes.shape[1], 3, 1)
    return np.matmul(a, d)[..., 0]


def _posed_shapes(ata, atr, w) -> np.ndarray:
    """(K, V, 3) the shapes that minimise the posed error for weights ``w`` (F, K): per vertex the normal
    equations sum_f (w_f w_f^T) kron (A_fv^T A_fv) over its 3K unknowns, in chunks of vertices (~200 MB)."""
    f, v = atr.shape[:2]
    k = w.shape[1]
    outer = np.einsum("fk,fl->fkl", w, w).reshape(f, k * k)
    rhs = (w.T @ atr.reshape(f, -1)).reshape(k, v, 3).transpose(1, 0, 2).reshape(v, 3 * k)   # sum_f w_fk atr_fv
    out = np.zeros((v, k, 3))
    step = max(1, int(2e8 / (k * k * 9 * 8)))
    for s in range(0, v, step):
        n = (outer.T @ ata[:, s:s + step].reshape(f, -1)).reshape(k, k, -1, 3, 3)
        n = n.transpose(2, 0, 3, 1, 4).reshape(-1, 3 * k, 3 * k)
        n += (1e-6 * np.trace(n, axis1=1, axis2=2) / (3 * k) + 1e-15)[:, None, None] * np.eye(3 * k)
        out[s:s + step] = np.linalg.solve(n, rhs[s:s + step, :, None])[..., 0].reshape(-1, k, 3)
    return out.transpose(1, 0, 2)


def _non_negative(w, shapes):
    """The same deformation sum_k w_fk D_k with weights in [0, 1]: per shape its positive side, and its negated
    shape for the negative side where the weights go below 0 (shapes with no weight dropped)."""
    ws, ds = [], []
    for k in range(w.shape[1]):
        for sign in (1.0, -1.0):
            side = np.maximum(sign * w[:, k], 0.0)
            top = side.max(initial=0.0)
            if top > 0:
                ws.append(side / top)
                ds.append(sign * top * shapes[k])
    if not ws:
        return np.zeros((len(w), 0)), np.zeros((0,) + shapes.shape[1:])
    return np.stack(ws, 1), np.stack(ds)


def fit_correctives(vertices, indices, weights, rotations, translations, targets, k: int,
                    goal: tuple[float, float] | None = None, frame_shapes: int = 0) -> Correctives:
    """``k`` corrective shapes and their weights per frame (the module docstring: exact per frame when k >= the
    frame count, else fitted in the posed space), with the posed error per frame before and after
    (``Correctives``); k is capped at the frame count. Each comes out as one or two shapes with weights in
    [0, 1] (its two sides), so up to 2k. ``goal`` (rms, max; metres): what each frame's corrected error should
    stay within (``_towards_goal``); None, a 0 in it or a frame count of shapes: the least-squares fit alone.
    ``frame_shapes`` (with a goal): up to that many frames still beyond it after the fit, the farthest first, get
    one more shape each (``_own_shapes``), weighing 1 in that frame and 0 in every other (nothing to add where k >=
    the frame count: exact)."""
    x = np.asarray(vertices, np.float64)
    y = np.asarray(targets, np.float64)
    a, b = blended_transforms(indices, weights, rotations, translations)
    lbs = np.einsum("fvab,vb->fva", a, x) + b
    f, v = y.shape[:2]
    k = int(min(k, f))
    rounds = 0
    if goal is not None and not (goal[0] > 0 and goal[1] > 0):
        goal = None
    if k == f:
        d = rest_residuals(x, indices, weights, rotations, translations, y)
        u, s, vt = np.linalg.svd(d.reshape(f, -1), full_matrices=False)
        w, shapes = u[:, :k] * s[:k], vt[:k].reshape(k, v, 3)
    elif k:
        r = y - lbs
        ata = np.einsum("fvca,fvcb->fvab", a, a)
        atr = np.einsum("fvca,fvc->fva", a, r)
        d = np.linalg.solve(ata + DAMPING * np.eye(3), atr[..., None])[..., 0]
        _, _, vt = np.linalg.svd(d.reshape(f, -1), full_matrices=False)
        shapes = vt[:k].reshape(k, v, 3)
        w = _posed_weights(a, r, shapes)
        for _ in range(ROUNDS):
            shapes = _posed_shapes(ata, atr, w)
            w = _posed_weights(a, r, shapes)
        if goal is not None:
            w, shapes, rounds = _towards_goal(a, r, ata, atr, w, shapes, np.linalg.norm(r, axis=2), goal)
    else:
        w, shapes = np.zeros((f, 0)), np.zeros((0, v, 3))
    w, shapes = _non_negative(w, shapes)
    # the errors of the rest points and shapes as the files hold them (float32; the joints' transforms as computed):
    # a vertex whose blended transform is singular needs a huge rest displacement to be exact (child_rope, K =
    # frames: 238 km at sigma_min 6e-8), which float32 cannot carry
    f32 = lambda z: np.asarray(z, np.float32).astype(np.float64)  # noqa: E731
    rest = np.einsum("fvab,vb->fva", a, f32(x)) + b
    err0 = np.linalg.norm(rest - y, axis=2)
    off = rest + _posed(a, f32(w), f32(shapes)) - y
    own: list[int] = []
    if goal is not None and frame_shapes > 0 and k < f:
        w, shapes, own = _own_shapes(a, -off, w, shapes, goal, frame_shapes)
        if own:          # only those frames change (every other one's extra weights are 0: its error as it was)
            off[own] = rest[own] + _posed(a[own], f32(w[own]), f32(shapes)) - y[own]
    err = np.linalg.norm(off, axis=2)
    rms, top = np.sqrt((err ** 2).mean(1)), err.max(1)
    beyond = ()
    if goal is not None and k:   # what is left beyond the goal, and whether a shape could reach it (the worst vertex's
        rows = np.flatnonzero((rms > goal[0]) | (top > goal[1]))   # blended transform; see the module docstring)
        worst = err[rows].argmax(1)
        beyond = tuple((int(i), int(v), float(np.linalg.svd(a[i, v], compute_uv=False)[-1])) for i, v in zip(rows, worst))
    return Correctives(shapes, w, np.sqrt((err0 ** 2).mean(1)), err0.max(1), rms, top,
                       fitted=k, goal=goal, goal_rounds=rounds, own=tuple(own), beyond=beyond,
                       asked=goal is not None and frame_shapes > 0 and k > 0)


def _own_shapes(a, left, w, shapes, goal, most: int):
    """The frames whose posed error ``left`` (F, V, 3) is beyond ``goal`` (rms, max), the farthest (by the larger
    of rms / goal's and max / goal's) first, up to ``most``: each gets one more shape, what is left of it taken back
    to the rest space as the fit's start takes its residuals, (A^T A + DAMPING I)^-1 A^T left, twice (the second on
    what the first left: a vertex whose blended transform is a rotation comes within 1e-4 of exact, one whose
    transform is nearly singular gets a bounded displacement, at most 1 / sqrt(DAMPING) = 10x its error, not the
    huge exact one), weighing 1 in that frame and 0 in every other: the weights stay in [0, 1] and no other frame
    changes. (Between keys a player ramps such a weight 0 -> 1 against a transform that has not collapsed: there a
    large displacement can show for an instant.) Returns (weights (F, K + n), shapes (K + n, V, 3), the frames' rows)."""
    e = np.linalg.norm(left, axis=2)
    far = np.maximum(np.sqrt((e ** 2).mean(1)) / goal[0], e.max(1) / goal[1])
    rows = [int(i) for i in np.argsort(-far, kind="stable") if far[i] > 1.0][:most]
    if not rows:
        return w, shapes, []
    ar, rest = a[rows], left[rows]
    damped = np.einsum("fvca,fvcb->fvab", ar, ar) + DAMPING * np.eye(3)
    extra = np.zeros(rest.shape)
    for _ in range(2):       # once more on what the damping left: a well-conditioned vertex to 1e-4 of its error
        step = np.linalg.solve(damped, np.einsum("fvca,fvc->fva", ar, rest)[..., None])[..., 0]         # (n, V, 3)
        extra += step
        rest = rest - np.matmul(ar, step[..., None])[..., 0]
    ew = np.zeros((len(w), len(rows)))
    ew[rows, np.arange(len(rows))] = 1.0
    LOG.info("correctives: %d frame(s) beyond the goal after the fit get a shape of their own", len(rows))
    return np.hstack([w, ew]), np.concatenate([shapes, extra]), rows


def _towards_goal(a, r, ata, atr, w, shapes, err0, goal):
    """Up to ``GOAL_ROUNDS`` more rounds (shapes, then weights) on a reweighted posed error, while some frame is
    beyond ``goal`` (rms, max): the least-squares fit spends its shapes on the bulk of the frames and leaves a few
    just beyond a goal (child_rope: 28 of 200 frames at 32 shapes, most 12.3-13.5 mm rms for a ~12 mm goal, the
    rest a vertex or two past the max, at near-singular blended transforms). Each round multiplies the weight of
    a frame whose rms is beyond ``GOAL_MARGIN[0]`` of the goal's by rms / that, and of a (frame, vertex) whose error
    is beyond ``GOAL_MARGIN[1]`` of the goal's max by its error / that (weights that accumulate over the rounds, as in
    Lawson's minimax iteration: recomputed from one round's errors alone they oscillated). The round with the most
    frames within the goal is kept (then the lowest total rms; the least-squares fit is round 0), and two rounds
    without a frame more within end it; a frame whose
    corrected rms would exceed plain LBS's takes its unweighted least-squares weights."""
    f, v = r.shape[:2]
    t_rms, t_max = goal

    def score(w, shapes):
        e = np.linalg.norm(_posed(a, w, shapes) - r, axis=2)
        rms = np.sqrt((e ** 2).mean(1))
        return e, rms, (int(np.sum((rms <= t_rms) & (e.max(1) <= t_max))), -float(np.sqrt((rms ** 2).mean())))

    e, rms, sc = score(w, shapes)
    best, used, gained, first = (sc, w, shapes), 0, 0, sc[0]
    omega = np.ones((f, v))
    for it in range(GOAL_ROUNDS):
        if best[0][0] == f or it - gained >= 2:       # all within, or two rounds without a frame more within
            break
        omega *= (np.maximum(1.0, rms / (GOAL_MARGIN[0] * t_rms))[:, None]
                  * np.maximum(1.0, e / (GOAL_MARGIN[1] * t_max)))
        omega /= omega.mean()
        shapes = _posed_shapes(ata * omega[..., None, None], atr * omega[..., None], w)
        w = _posed_weights(a, r, shapes, omega)
        e, rms, sc = score(w, shapes)
        worse = np.flatnonzero(rms > np.sqrt((err0 ** 2).mean(1)))
        if len(worse):
            w[worse] = _posed_weights(a, r, shapes, frames=worse)[worse]
            e, rms, sc = score(w, shapes)
        LOG.info("correctives towards the goal (rms %.1f mm, max %.1f mm): round %d: %d of %d frames within (least "
                 "squares: %d)", 1000 * t_rms, 1000 * t_max, it + 1, sc[0], f, first)
        if sc[0] > best[0][0]:
            gained = it + 1
        if sc > best[0]:
            best, used = (sc, w, shapes), it + 1
    return best[1], best[2], used
