"""Keyframe tracking of a mesh sequence into a dynamic mesh (after Collet et al. 2015, "High-quality streamable
free-viewpoint video", section 7: tracked keyframe subsequences).

    1. Keyframe, by trial: each round the untracked frames best by ``keyframe_key`` (fewest connected
       components, then lowest genus, then the largest surface area) are candidates, up to ``tries`` new ones
       (none inside a segment already tried); each grows its segment (2.-3.) and the longest of these and of the
       earlier rounds' trials (cut where a kept segment took their frames) is kept. On child_rope the static
       ranking alone picks frames whose arms lie against the body (one blob in the hull): tracking from there
       cannot grow arms, tracking from arms apart can press them on (section "Temporal structuring" of the
       README). A segment that fills its whole stretch of untracked frames is kept at once.
    2. Its reconstruction is deformed forwards, frame by frame, onto each following reconstruction (deform.fit:
       embedded deformation graph + ARAP, point-to-plane both ways, silhouettes near their outline), then its
       surface detail is brought onto that frame (deform.detail) and its vertices put on that frame's surface
       (deform.snap; folds that leaves are smoothed open, deform.unfold); then backwards from the keyframe the
       same way.
    3. A frame whose fit fails (after a second try from the previous frame's state, without the motion
       prediction, with ``retry`` times the iterations) ends the segment (the topology changed, or the motion
       was too large): mean surface distance beyond ``fail_mean`` voxels either way (tracked ->
       reconstruction counting only tracked vertices outside the reconstruction: limbs pressed together are
       one blob in a visual hull, the tracked surfaces between them lie inside it), 95th percentile of reconstruction -> tracked or 99th
       of tracked (outside) -> reconstruction beyond ``fail_p95`` voxels (a part the tracked mesh does not
       reach, or a membrane across a new hole), or the tracked mesh's silhouette IoU more than
       ``max_iou_drop`` below the reconstruction's own. Unless the segment is *bridged*: tracking carries on
       through failed fits for up to ``bridge`` frames, and at the first frame that fits the frames between
       are fitted again backwards from it (each from its neighbour's state); the bridge holds when every one
       of them fits. On child_rope the arms lie against the body in some frames (one blob in the visual hull,
       nothing holds the tracked arm in place) and leave it a few frames later: the frames where they come
       out fail from the side where they were hidden and fit from the side where they are out.
    4. Repeat from 1 until every frame belongs to a segment. Within a segment every frame has the keyframe's
       faces: one connectivity, per-vertex trajectories; a texture atlas per segment serves all its frames.

Distances are in voxels (``voxel`` metres; 0 = twice the median edge length of the first reconstruction:
refined and relaxed marching-cubes meshes have about two edges per voxel, plain marching cubes one).
"""
from __future__ import annotations

import copy
import dataclasses
import logging
import time
from dataclasses import dataclass, field

import numpy as np

from nodes.common.closest import SurfaceQuery
from nodes.common.meshops import edge_face_pairs, face_normals, padded_rows, ring_operator, vertex_faces

from . import deform
from .deform import FitParams, Target
from .topology import mesh_topology

log = logging.getLogger("volcap.track")


@dataclass
class TrackParams:
    spacing: float = 4.0          # deformation graph node spacing (voxels)
    voxel: float = 0.0            # metres per voxel; 0 = twice the median edge length of the first reconstruction
    fail_mean: float = 1.0        # a fit fails beyond this mean surface distance (voxels), either direction
    fail_p95: float = 3.0         # ... or this 95th percentile of either distance
    max_iou_drop: float = 0.01    # ... or a silhouette IoU this far below the reconstruction's (with views)
    extrapolate: float = 0.7      # each frame starts from the last state plus this share of the last motion
    fit: FitParams = field(default_factory=FitParams)
    tries: int = 3                # keyframe candidates grown per round; the longest segment is kept
    bridge: int = 8               # after a failed fit, frames tracked on through failures to one that fits
    retry: int = 2                # a failed fit is tried again from the previous state (no motion prediction)
                                  # with this many times the iterations (0, 1: not)


@dataclass
class FrameResult:
    vertices: np.ndarray          # (V, 3) world
    segment: int
    keyframe: int                 # index of the segment's keyframe
    accuracy_mean: float          # tracked -> reconstruction, voxels
    accuracy_p95: float
    completeness_mean: float      # reconstruction -> tracked
    completeness_p95: float
    iou: float | None = None      # mean silhouette IoU of the tracked mesh
    iou_reconstruction: float | None = None
    seconds: float = 0.0
    bridged: bool = False         # fitted again backwards from a later frame after a failed fit (see ``bridge``)


@dataclass
class Segment:
    index: int
    keyframe: int
    start: int
    stop: int                     # inclusive
    faces: np.ndarray
    nodes: int
    reason_start: str = ""
    reason_stop: str = ""


def median_edge(vertices, faces) -> float:
    f = np.asarray(faces, np.int64)
    if len(f) == 0:
        return 0.0
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    return float(np.median(np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1)))


def keyframe_key(stats: dict) -> tuple:
    """Sort key of a keyframe candidate (smaller is better): components, genus, then larger area."""
    return (stats["components"], stats["genus"], -stats["area"])


def surface_residuals(x: np.ndarray, faces: np.ndarray, target: Target, vf=None, samples: int = 4000, seed: int = 0) -> dict:
    """Distances (voxels) from tracked vertices to the reconstruction's surface (accuracy) and from the
    reconstruction's vertices to the tracked surface (completeness): mean and 95th percentile over ``samples``
    vertices drawn at random each way (0 = all); ``outside_*``: the accuracy distances counting only tracked
    vertices outside the reconstruction (inside: 0), what the failure test reads (limbs that touch are one
    blob in a visual hull, the tracked mesh keeps them apart: its surfaces between them lie inside), with the
    99th percentile (a membrane across a new hole is a few % of the vertices)."""
    rng = np.random.default_rng(seed)
    pick = lambda n: np.arange(n) if not samples or n <= samples else rng.choice(n, samples, replace=False)  # noqa: E731
    xs = x[pick(len(x))]
    c, d_acc, f = target.query.closest(xs, with_faces=True)
    fn = face_normals(target.vertices, target.faces[f])
    d_out = np.where(np.einsum("ij,ij->i", xs - c, fn) > 0, d_acc, 0.0)   # inside the reconstruction: 0
    tracked = SurfaceQuery(x, faces, vf=vf, with_normals=False)
    rec = target.vertices[target.query.used]
    _, d_comp = tracked.closest(rec[pick(len(rec))])
    return {"accuracy_mean": float(d_acc.mean()), "accuracy_p95": float(np.percentile(d_acc, 95)),
            "completeness_mean": float(d_comp.mean()), "completeness_p95": float(np.percentile(d_comp, 95)),
            "outside_mean": float(d_out.mean()), "outside_p99": float(np.percentile(d_out, 99))}


def silhouette_iou(vertices, faces, cameras, masks) -> float:
    """Mean over views of the IoU between the mesh's silhouette (OpenCL rasterizer) and the mask (> 127)."""
    from nodes.common import raster

    views = raster.silhouette_iou(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), cameras, masks)
    return float(np.mean([v["iou"] for v in views]))


class Frames:
    """The input sequence: reconstructions (trimesh) and optional masks + cameras per frame, with the targets
    and silhouette IoUs computed on demand (a few kept)."""

    def __init__(self, meshes, masks=None, cameras=None, voxel: float = 0.0, min_views: int = 0, numbers=None):
        self.meshes = meshes
        self.numbers = list(numbers) if numbers is not None else list(range(len(meshes)))  # frame numbers: what a user reads
        self.masks = masks
        self.cameras = cameras
        self.min_views = min_views
        first = next((m for m in meshes if len(m.faces)), None)
        self.voxel = voxel or (2.0 * median_edge(np.asarray(first.vertices), first.faces) if first is not None else 1.0)
        self.origin = np.asarray(first.vertices).min(axis=0) if first is not None else np.zeros(3)
        self.stats = []
        for m in meshes:
            s = mesh_topology(m.vertices, m.faces)
            s["area"] = float(m.area) if len(m.faces) else 0.0
            self.stats.append(s)
        self._targets: dict[int, Target] = {}
        self._iou: dict[int, float] = {}

    def __len__(self):
        return len(self.meshes)

    @property
    def has_views(self) -> bool:
        return self.masks is not None and self.cameras is not None

    def views(self, i: int):
        from nodes.common.silhouettes import Silhouettes

        if not self.has_views:
            return None
        return Silhouettes.from_inputs(self.masks[i], self.cameras[i], min_views=self.min_views, node="track").distance_outline()

    def target(self, i: int) -> Target:
        if i not in self._targets:
            if len(self._targets) > 4:
                self._targets.pop(next(iter(self._targets)))
            m = self.meshes[i]
            self._targets[i] = Target(m.vertices, m.faces, self.origin, self.voxel, self.views(i))
        return self._targets[i]

    def iou_reconstruction(self, i: int) -> float | None:
        if not self.has_views:
            return None
        if i not in self._iou:
            m = self.meshes[i]
            self._iou[i] = silhouette_iou(m.vertices, m.faces, self.cameras[i], self.masks[i].masks)
        return self._iou[i]


def predict(before: deform.GraphState, now: deform.GraphState, factor: float) -> deform.GraphState:
    """The graph state one frame ahead at ``factor`` times the last frame's motion (0: stay): translations
    extrapolated linearly, rotations by the same relative turn (R_now R_before^T R_now for factor 1, through
    the nearest rotation for other factors)."""
    if factor <= 0:
        return now
    t = now.t + factor * (now.t - before.t)
    turn = np.einsum("nab,ncb->nac", now.R, before.R)                  # R_now R_before^T
    turn = np.eye(3) + factor * (turn - np.eye(3))
    U, _, Vt = np.linalg.svd(turn)
    D = np.ones((len(U), 3))
    D[:, 2] = np.sign(np.linalg.det(np.einsum("nab,nbc->nac", U, Vt)))
    turn = np.einsum("nab,nb,nbc->nac", U, D, Vt)
    return deform.GraphState(np.einsum("nab,nbc->nac", turn, now.R), t)


def _failure(res: dict, iou: float | None, iou_rec: float | None, p: TrackParams) -> str:
    if max(res["outside_mean"], res["completeness_mean"]) > p.fail_mean:
        return (f"mean surface distance {max(res['outside_mean'], res['completeness_mean']):.2f} voxels "
                f"> {p.fail_mean}")
    if res["completeness_p95"] > p.fail_p95:
        return f"95th percentile reconstruction -> tracked {res['completeness_p95']:.2f} voxels > {p.fail_p95}"
    if res["outside_p99"] > p.fail_p95:
        return f"99th percentile tracked -> reconstruction (outside it) {res['outside_p99']:.2f} voxels > {p.fail_p95}"
    if iou is not None and iou_rec is not None and iou_rec - iou > p.max_iou_drop:
        return f"silhouette IoU {iou:.4f} is {iou_rec - iou:.4f} below the reconstruction's {iou_rec:.4f}"
    return ""


@dataclass
class _Trial:
    """One keyframe's segment as far as it grew: its results per frame (index -> FrameResult)."""
    seg: Segment
    results: dict

    def truncate(self, done: np.ndarray, numbers=None) -> bool:
        """Cut the segment at the first frame on either side that another segment has taken since (the growth
        is sequential outwards from the keyframe, so the part before that frame is exactly what a new trial
        would give); False when the keyframe itself is taken."""
        seg = self.seg
        if done[seg.keyframe]:
            return False
        taken = [i for i in range(seg.keyframe + 1, seg.stop + 1) if done[i]]
        if taken:
            seg.stop = taken[0] - 1
            seg.reason_stop = f"frame {taken[0] if numbers is None else numbers[taken[0]]}: already tracked"
        taken = [i for i in range(seg.keyframe - 1, seg.start - 1, -1) if done[i]]
        if taken:
            seg.start = taken[0] + 1
            seg.reason_start = f"frame {taken[0] if numbers is None else numbers[taken[0]]}: already tracked"
        self.results = {i: r for i, r in self.results.items() if seg.start <= i <= seg.stop}
        return True

    @property
    def length(self) -> int:
        return self.seg.stop - self.seg.start + 1


def grow_segment(frames: Frames, params: TrackParams, k: int, done: np.ndarray, progress=None) -> _Trial:
    """Deform keyframe ``k``'s reconstruction forwards, then backwards, frame by frame, until a fit fails, a
    frame another segment holds (``done``) or the sequence ends (see the module docstring)."""
    n = len(frames)
    fit_p = params.fit
    key_mesh = frames.meshes[k]
    faces = np.asarray(key_mesh.faces, np.int64)
    if len(faces) == 0:  # nothing reconstructed: a segment of its own, empty
        log.warning("frame %d: empty reconstruction, a segment of its own", k)
        res = FrameResult(np.asarray(key_mesh.vertices, np.float64), -1, k, 0.0, 0.0, 0.0, 0.0,
                          frames.iou_reconstruction(k), frames.iou_reconstruction(k))
        return _Trial(Segment(-1, k, k, k, faces, 0, "empty reconstruction", "empty reconstruction"), {k: res})
    t0 = time.perf_counter()
    target_k = frames.target(k)
    graph = deform.build_graph(target_k.vertices, faces, params.spacing, seed=fit_p.seed)
    reg = deform.Registration(graph, faces, fit_p)
    rings = ring_operator(faces, len(graph.rest))
    vf = padded_rows(*vertex_faces(faces, len(graph.rest)))
    pairs = edge_face_pairs(faces)
    iou_k = frames.iou_reconstruction(k)
    results = {k: FrameResult(np.asarray(key_mesh.vertices, np.float64), -1, k, 0.0, 0.0, 0.0, 0.0, iou_k, iou_k,
                              time.perf_counter() - t0)}
    seg = Segment(-1, k, k, k, faces, len(graph.nodes), "keyframe")

    slow = None
    if params.retry > 1:                     # the same fit with ``retry`` times the iterations
        slow = copy.copy(reg)
        slow.params = dataclasses.replace(fit_p, iterations=params.retry * fit_p.iterations)

    def fit_frame(init, i, start=None):
        """(state, FrameResult, failure reason) of frame i's fit from the graph state ``init``; when it fails and
        ``start`` is given, once more from ``start`` (the previous frame's state) with more iterations."""
        new_state, r, why = fit_once(reg, init, i)
        if why and start is not None and slow is not None:
            again = fit_once(slow, start, i)
            if not again[2]:
                log.debug("keyframe %d: frame %d fitted on the second try (first: %s)", k, i, why)
                return again
        return new_state, r, why

    def fit_once(reg, init, i):
        t0 = time.perf_counter()
        target = frames.target(i)
        new_state, _ = reg.fit(init, target)
        x = graph.deform(new_state)
        if not np.isfinite(x).all():        # a diverged fit: a failure like any other (the closest points refuse NaN)
            inf = float("inf")
            return new_state, FrameResult(target.world(x), -1, k, inf, inf, inf, inf,
                                          seconds=time.perf_counter() - t0), "the fit diverged (vertices not finite)"
        offsets = deform.laplacian_offsets(graph, new_state, rings)
        x = deform.detail(x, faces, target, fit_p, rings, offsets=offsets)
        x = deform.snap(x, faces, target, fit_p, rings, offsets=offsets)
        x = deform.unfold(x, faces, pairs, rings, fit_p.unfold, target, fit_p.snap_reach)
        res = surface_residuals(x, faces, target, vf)
        world = target.world(x)
        iou = silhouette_iou(world, faces, frames.cameras[i], frames.masks[i].masks) if frames.has_views else None
        iou_rec = frames.iou_reconstruction(i)
        why = _failure(res, iou, iou_rec, params)
        res = {key: v for key, v in res.items() if not key.startswith("outside")}
        return new_state, FrameResult(world, -1, k, **res, iou=iou, iou_reconstruction=iou_rec,
                                      seconds=time.perf_counter() - t0), why

    def bridge(state, failed, i, direction):
        """After the fit of frame i (from ``state``, giving ``failed``) failed: carry on through failed fits up
        to ``params.bridge`` frames; at the first frame j that fits, fill j - 1 .. i backwards from j's state
        (each from its neighbour's). Returns (the states at j - 1 and j, {frame: result}) when every frame of
        i .. j fits, else None."""
        tb, ts = state, failed
        for g in range(1, params.bridge + 1):
            j = i + g * direction
            if not (0 <= j < n) or done[j] or len(frames.meshes[j].faces) == 0:
                return None
            tb, (ts, r, why) = ts, fit_frame(predict(tb, ts, params.extrapolate), j)
            if why:
                continue
            got, st, states = {j: r}, ts, []
            for m in range(j - direction, i - direction, -direction):
                st, got[m], why = fit_frame(st, m, start=st)
                if why:
                    log.debug("keyframe %d: frame %d bridged from %d but %s", k, m, j, why)
                    return None
                states.append(st)
            return states[0], ts, got
        return None

    for direction in (1, -1):
        state = deform.GraphState.identity(graph)
        before = state                       # the state one frame earlier, for the motion prediction
        i = k + direction
        reason = "end of sequence"
        while 0 <= i < n and not done[i]:
            if len(frames.meshes[i].faces) == 0:
                reason = f"frame {frames.numbers[i]}: empty reconstruction"
                break
            new_state, r, why = fit_frame(predict(before, state, params.extrapolate), i, start=state)
            got = {i: r}
            if why:
                bridged = bridge(state, new_state, i, direction) if params.bridge > 0 else None
                if bridged is None:
                    reason = f"frame {frames.numbers[i]}: {why}"
                    break
                state, new_state, got = bridged
                for r in got.values():
                    r.bridged = True
                log.debug("keyframe %d: frame %d (%s) bridged from frame %d", k, i, why, max(got, key=lambda f: f * direction))
            for f, r in got.items():
                results[f] = r
            last = max(got, key=lambda f: f * direction)
            before, state = (state, new_state)
            if direction > 0:
                seg.stop = last
            else:
                seg.start = last
            if progress:
                progress(len(results))
            i = last + direction
        else:
            if 0 <= i < n:
                reason = f"frame {frames.numbers[i]}: already tracked"
        if direction > 0:
            seg.reason_stop = reason
        else:
            seg.reason_start = reason
    return _Trial(seg, results)


def track_sequence(frames: Frames, params: TrackParams, progress=None, keyframe: int | None = None
                   ) -> tuple[list[FrameResult | None], list[Segment]]:
    """Segments of tracked meshes covering every frame (see the module docstring). ``keyframe``: the first
    segment's keyframe (index) instead of the automatic choice.

    Keyframes are chosen by trial: each round grows segments from up to ``params.tries`` new candidates (the
    untracked frames best by ``keyframe_key``, none inside a segment already tried) and keeps the longest of
    these and of the earlier rounds' trials (cut where a kept segment took their frames; a trial is never
    grown twice). A segment that fills its whole stretch of untracked frames is kept at once, so a sequence
    one keyframe explains costs one trial. ``progress(done, total, what)``: frames tracked so far (the current
    trial's included), as it grows."""
    n = len(frames)
    results: list[FrameResult | None] = [None] * n
    segments: list[Segment] = []
    done = np.zeros(n, bool)
    trials: dict[int, _Trial] = {}
    while not done.all():
        trials = {k: t for k, t in trials.items() if t.truncate(done, frames.numbers)}
        if keyframe is not None and not segments:
            order = [int(keyframe)]
        else:
            order = sorted(np.flatnonzero(~done).tolist(), key=lambda i: keyframe_key(frames.stats[i]))
        fresh = 0
        best = None
        for k in order:
            if fresh >= max(1, params.tries) or (keyframe is not None and not segments and fresh):
                break
            if any(t.seg.start <= k <= t.seg.stop for t in trials.values()):
                continue
            t = grow_segment(frames, params, k, done,
                             (lambda m: progress(int(done.sum()) + m, n, "frames")) if progress else None)
            trials[k] = t
            fresh += 1
            lo, hi = k, k                                  # the stretch of untracked frames around k
            while lo > 0 and not done[lo - 1]:
                lo -= 1
            while hi < n - 1 and not done[hi + 1]:
                hi += 1
            if t.seg.start == lo and t.seg.stop == hi:
                best = t
                break
        if best is None:
            pool = [trials[int(keyframe)]] if keyframe is not None and not segments else list(trials.values())
            best = max(pool, key=lambda t: (t.length, tuple(-np.asarray(keyframe_key(frames.stats[t.seg.keyframe])))))
        seg = best.seg
        seg.index = len(segments)
        for i, r in best.results.items():
            r.segment = seg.index
            results[i] = r
            done[i] = True
        del trials[seg.keyframe]
        num = frames.numbers
        log.info("segment %d: keyframe %d, frames %d..%d (%d nodes); before: %s; after: %s", seg.index, num[seg.keyframe],
                 num[seg.start], num[seg.stop], seg.nodes, seg.reason_start, seg.reason_stop)
        if progress:
            progress(int(done.sum()), n, "frames")
        segments.append(seg)
    segments.sort(key=lambda s: s.start)
    renumber = {s.index: i for i, s in enumerate(segments)}
    for s in segments:
        s.index = renumber[s.index]
    for r in results:
        r.segment = renumber[r.segment]
    return results, segments
