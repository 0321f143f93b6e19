"""Temporal structuring (track): quality on the synthetic walking figure with ground-truth correspondences, the
whole child_rope sequence, and speed at ~20k vertices, each against trimesh.registration.nricp_amberg (the
baseline a user would otherwise pick, REFERENCES.md) in the same run. Prints tables; writes pictures to docs/ (child_rope's
meshes to out/: that data may not be published with the project).

    python bench/track.py synth [--nricp-frames 3]    # graphs/track_synth.yaml, 100 frames at 128^3
    python bench/track.py synth --set stage.scene=touch --frames 0:24   # arms held against the hips: sliding
    python bench/track.py speed [--resolution 164]    # ~20k vertices (hull 164^3), ours per frame vs nricp_amberg;
                                                      # the fit's factorisation, CHOLMOD vs SuperLU
    python bench/track.py child_rope                  # graphs/track_child_rope.yaml, 200 frames
    python bench/track.py silhouettes [--frames 27:37]   # child_rope: the silhouette term's kernels vs NumPy / scipy
    options: --cache DIR (default ./.volcap-cache), --frames A:B, --no-pictures, --set NODE.PARAM=VALUE (synth, child_rope)

The per-frame reconstructions come from the graphs through the engine and its cache (the first run computes
them: ~5 s per frame), so a second run only re-measures. The correspondence error of the synthetic run: each
tracked vertex is attached at its keyframe to the nearest point of the true surface (a face and barycentric
coordinates); the figure keeps its topology over frames, so that body point's true position is known in every
frame. "tracking error" = |(x_t - x_key) - (g_t - g_key)| (the motion of the point, which leaves out the
visual hull's own offset from the truth); "absolute" = |x_t - g_t|. "Sliding" (nodes.eval.surface.sliding) is
the part along the surface: each tracked vertex's closest true point, in rest-pose coordinates (where a texture is
fixed), against the one it had at the keyframe; told apart where another part of the body touches (eval.surface
contacts: a true point within 3 cm that is 15 cm away at rest), which the `touch` scene holds for half its cycle.
Where two parts touch, a vertex's closest true point may lie on the other part without the vertex having moved: the
tracking error per vertex (against its own body point, split the same way) tells the two apart.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import trimesh

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
os.environ.setdefault("VOLCAP_DATA", str(ROOT.parent / "shared" / "data"))

from nodegraph import Table  # noqa: E402
from nodegraph.cache import Cache  # noqa: E402
from nodegraph.executors import LocalExecutor  # noqa: E402
from nodegraph.graphfile import load_graph  # noqa: E402
from nodegraph.run import run_graph  # noqa: E402
from nodes.common import types as T  # noqa: E402
from nodes.common.closest import SurfaceQuery  # noqa: E402
from nodes.track.tracking import Frames, TrackParams, track_sequence, surface_residuals  # noqa: E402

DOCS = ROOT / "docs"


def header():
    from machine import describe

    print(describe())


def run(graph_file: Path, cache: Path, frames: str | None, upto: str | None = None, overrides=(), keep_all=False):
    """Run a graph (or the part of it ``upto`` depends on) through the engine; returns its run records.
    ``keep_all``: store every output (intermediate ones, e.g. the hull's volume, are not kept by default)."""
    g = load_graph(graph_file, overrides=list(overrides), frames=frames)
    if keep_all:
        g.keep_all()
    if upto:
        keep, todo = set(), [upto]
        while todo:
            n = todo.pop()
            if n not in keep:
                keep.add(n)
                todo.extend(g.upstream[n])
        g.nodes = {k: v for k, v in g.nodes.items() if k in keep}
        g.upstream = {k: v for k, v in g.upstream.items() if k in keep}
    out = cache / "bench_out" / graph_file.stem
    t0 = time.perf_counter()
    res = run_graph(g, Cache(cache), out, LocalExecutor(1), progress=True)
    if not res.ok:
        raise SystemExit(f"{graph_file}: {len(res.failures)} items failed: {res.failures[0].get('error')}")
    print(f"{graph_file.name}: {res.counts()} in {time.perf_counter() - t0:.1f} s")
    return res.records


def outputs(records, node: str, port: str, dtype):
    recs = sorted((r for r in records if r["node"] == node), key=lambda r: (r["frame"] is None, r["frame"] or 0))
    return [dtype.load(Path(r["cache_dir"]) / port) for r in recs], recs


def nricp_chain(meshes, count: int):
    """trimesh nricp_amberg frame to frame (default steps) from meshes[0]: (vertices per frame, seconds each)."""
    from trimesh.registration import nricp_amberg

    current = meshes[0]
    out, secs = [np.asarray(current.vertices)], [0.0]
    for m in meshes[1:count]:
        t0 = time.perf_counter()
        v = nricp_amberg(current, m)
        secs.append(time.perf_counter() - t0)
        current = trimesh.Trimesh(v, current.faces, process=False)
        out.append(v)
    return out, secs


# ---------------------------------------------------------------- synthetic figure
def attach(truth_key: trimesh.Trimesh, points: np.ndarray):
    """Faces and barycentric coordinates of the nearest points of the true surface."""
    closest, _, face = SurfaceQuery(truth_key.vertices, truth_key.faces).closest(points, with_faces=True)
    return face, trimesh.triangles.points_to_barycentric(truth_key.triangles[face], closest)


def carried(truth_t: trimesh.Trimesh, face, bary) -> np.ndarray:
    return np.einsum("vk,vka->va", bary, truth_t.vertices[truth_t.faces[face]])


def correspondence(track_v: dict, key: int, truth: dict, voxel: float) -> dict:
    """Per frame of ``track_v`` (frame -> vertices): tracking and absolute error (voxels) against the truth."""
    face, bary = attach(truth[key], track_v[key])
    g_key = carried(truth[key], face, bary)
    rows = {}
    for f, x in track_v.items():
        g = carried(truth[f], face, bary)
        rows[f] = (np.linalg.norm((x - track_v[key]) - (g - g_key), axis=1).mean() / voxel,
                   np.linalg.norm(x - g, axis=1).mean() / voxel)
    return rows


def slide_report(seq, segs, frames, scene: str):
    """Sliding over the true surface (mm along the body) at contacts and elsewhere, every tracked frame."""
    from nodes.eval.surface import contacts, sliding
    from nodes.synth import scenes

    at, away, moved_at, moved_away = [], [], [], []
    for a, b in segs:
        key = [m.metadata["frame"] for m in seq[a:b]].index(seq[a].metadata["keyframe"])
        sc = [scenes.build(scene, m.metadata["frame"]) for m in seq[a:b]]
        x = np.stack([np.asarray(m.vertices) for m in seq[a:b]])
        s = sliding(x, np.asarray(seq[a].faces), [c.mesh for c in sc], sc[0].texcoords, key)
        face, bary = attach(sc[key].mesh, x[key])          # each vertex's own body point, carried by the true motion
        g_key = carried(sc[key].mesh, face, bary)
        for t, c in enumerate(sc):
            touch = contacts(c.mesh.vertices, c.texcoords, x[t])
            err = np.linalg.norm((x[t] - x[key]) - (carried(c.mesh, face, bary) - g_key), axis=1)
            at.append(s[t][touch])
            away.append(s[t][~touch])
            moved_at.append(err[touch])
            moved_away.append(err[~touch])
    at, away = np.concatenate(at) * 1000, np.concatenate(away) * 1000
    moved_at, moved_away = np.concatenate(moved_at) * 1000, np.concatenate(moved_away) * 1000

    def row(v):
        return (f"{len(v)} vertex-frames, median {np.median(v):.1f}, p95 {np.percentile(v, 95):.1f}, max {v.max():.1f} mm, "
                f"{np.mean(v > 50) * 100:.1f} % beyond 50 mm" if len(v) else "none")

    from machine import describe

    print(describe())
    print(f"  sliding over the true surface: where the body touches itself {row(at)}; elsewhere {row(away)}")
    # where two body parts touch, the closest true point of a vertex between them may lie on the other part (the
    # rest-pose distance then jumps by the parts' distance at rest) without the vertex having moved off its own
    # point: its tracking error (its motion against its own body point's true motion) tells the two apart
    print(f"  tracking error of each vertex (its motion against its own body point's): where the body touches itself "
          f"{row(moved_at)}; elsewhere {row(moved_away)}")
    if len(at):
        cross = at > 50
        print(f"  of the vertex-frames at contacts sliding beyond 50 mm ({int(cross.sum())}): tracking error median "
              f"{np.median(moved_at[cross]) if cross.any() else 0:.1f} mm, max {moved_at[cross].max() if cross.any() else 0:.1f} mm")
    return at, away


def bench_synth(args):
    from nodes.synth import scenes

    scene = next((o.split("=", 1)[1] for o in args.set if o.startswith("stage.scene=")), "figure")
    graph = ROOT / "graphs/track_synth.yaml"
    records = run(graph, args.cache, args.frames, overrides=args.set)
    recon, recs = outputs(records, "relax", "mesh", T.Mesh)
    first = recs[0]["frame"]
    vols, _ = outputs(run(graph, args.cache, f"{first}:{first + 1}", upto="hull", keep_all=True), "hull", "volume", T.Volume)
    voxel = float(vols[0].voxel_size.max())
    seq = outputs(records, "track", "sequence", T.MeshSequence)[0][0]
    table = outputs(records, "track", "residuals", Table)[0][0]
    track_rec = next(r for r in records if r["node"] == "track")
    frames = [m.metadata["frame"] for m in seq]
    truth = {f: scenes.build(scene, f).mesh for f in frames}
    print(f"\nsynthetic figure ({scene}): {len(frames)} frames, hull 128^3 (voxel {voxel * 1000:.2f} mm), "
          f"{len(recon[0].vertices)} vertices per reconstruction")
    segs = T.sequence_segments(seq)
    constant = all(np.array_equal(seq[a].faces, seq[i].faces) for a, b in segs for i in range(a, b))
    # our distances were computed in the track node's voxel; restate them in this hull's voxel
    scale = table["voxel"] / voxel
    acc = np.array(table["timeline"]["accuracy_mean"]) * scale
    comp = np.array(table["timeline"]["completeness_mean"]) * scale
    ours = {}
    for a, b in segs:
        key = frames.index(seq[a].metadata["keyframe"])
        ours.update(correspondence({frames[i]: np.asarray(seq[i].vertices) for i in range(a, b)}, frames[key], truth, voxel))
    err = np.array([ours[f][0] for f in frames])
    absolute = np.array([ours[f][1] for f in frames])
    key0 = seq[0].metadata["keyframe"]
    same_phase = [f for f in frames if (f - frames[-1]) % 24 == 0]
    print(f"ours: {len(segs)} segment(s), keyframe(s) {sorted({m.metadata['keyframe'] for m in seq})}; constant connectivity "
          f"per segment: {constant}; track node {table['seconds']:.1f} s = {table['seconds_per_frame']:.2f} s/frame "
          f"(when it was computed{', a cache hit now' if track_rec.get('cache_hit') else ''})")
    print(f"  surface distance to each frame's reconstruction, voxels: tracked->rec mean {acc.mean():.3f} (max {acc.max():.3f}), "
          f"rec->tracked mean {comp.mean():.3f} (max {comp.max():.3f})")
    print(f"  correspondence error vs truth, voxels: tracking mean {err.mean():.2f} (max {err.max():.2f}); absolute mean "
          f"{absolute.mean():.2f} (max {absolute.max():.2f}; at the keyframe {ours[key0][1]:.2f} = the hull's own offset)")
    print(f"  drift: tracking error first frame {err[0]:.2f}, last {err[-1]:.2f} (ratio {err[-1] / max(err[0], 1e-9):.2f}); "
          f"same gait phase as the last frame (frames {same_phase}): {[round(float(ours[f][0]), 2) for f in same_phase]}")
    slide_report(seq, segs, frames, scene)
    usd_check(records, seq, args.cache / "bench_out" / graph.stem)
    # nricp_amberg frame to frame from frame 0, and ours from the same start, on the first frames
    n = min(args.nricp_frames, len(frames))
    if n > 1:
        print(f"\nnricp_amberg frame to frame (default steps) on frames {frames[0]}..{frames[n - 1]} "
              f"({len(recon[0].vertices)} vertices); ours tracked from frame {frames[0]} too:")
        nv, nsec = nricp_chain(recon[:n], n)
        fr = Frames(recon[:n], voxel=table["voxel"])
        t0 = time.perf_counter()
        res, _ = track_sequence(fr, TrackParams(voxel=table["voxel"]), keyframe=0)
        osec = (time.perf_counter() - t0) / max(1, n - 1)
        e_n = correspondence({frames[i]: v for i, v in enumerate(nv)}, frames[0], truth, voxel)
        e_o = correspondence({frames[i]: r.vertices for i, r in enumerate(res)}, frames[0], truth, voxel)
        print(f"{'frame':>6} {'nricp s':>8} {'nricp surf':>10} {'nricp err':>9} | {'ours s':>7} {'ours surf':>9} {'ours err':>8}")
        for i in range(1, n):
            tq = Frames([recon[i]], voxel=voxel).target(0)
            sn = surface_residuals((nv[i] - tq.origin) / voxel, recon[0].faces, tq)
            so = surface_residuals((res[i].vertices - tq.origin) / voxel, recon[0].faces, tq)
            print(f"{frames[i]:>6} {nsec[i]:>8.1f} {0.5 * (sn['accuracy_mean'] + sn['completeness_mean']):>10.3f} "
                  f"{e_n[frames[i]][0]:>9.2f} | {res[i].seconds:>7.2f} {0.5 * (so['accuracy_mean'] + so['completeness_mean']):>9.3f} "
                  f"{e_o[frames[i]][0]:>8.2f}")
        print(f"mean seconds per frame: nricp_amberg {np.mean(nsec[1:]):.1f}, ours {osec:.2f} "
              f"({np.mean(nsec[1:]) / osec:.0f}x)")
    if not args.no_pictures:
        picture(seq, [0, 24, 49, 74, 99], DOCS / "track_synth.png", "synthetic walk: one tracked mesh, frames")
        plot_residuals(table, DOCS / "track_synth_residuals.png", "synthetic walk", extra=("tracking error vs truth", err))


def usd_check(records, seq, out: Path):
    """The exported USD (in the run's output folder ``out``) opened with usd-core: points at every frame k
    against ours at frame k; storage."""
    from pxr import Usd, UsdGeom

    usd = next(out.glob("*.usdc"))
    stage = Usd.Stage.Open(str(usd))
    meshes = [UsdGeom.Mesh(p) for p in stage.GetPrimAtPath("/DynamicMesh").GetChildren()]
    worst = 0.0
    for m in seq:
        f = m.metadata["frame"]
        vis = [u for u in meshes if u.ComputeVisibility(Usd.TimeCode(f)) != UsdGeom.Tokens.invisible]
        got = np.array(vis[0].GetPointsAttr().Get(Usd.TimeCode(f)), np.float32)
        worst = max(worst, float(np.abs(got - np.asarray(m.vertices, np.float32)).max()))
    sizes = outputs(records, "export", "sizes", Table)[0][0]
    mb = 1 / 1e6
    print(f"  USD ({Path(usd).name}, usd-core {Usd.GetVersion()}): {len(seq)} frames, max |points(k) - ours(k)| = {worst:g} m; "
          f"storage: per-frame PLY {sizes['reconstruction_ply_bytes'] * mb:.1f} MB (Draco {sizes['reconstruction_draco_bytes'] * mb:.1f} MB); "
          "dynamic " + ", ".join(f"{k} {v * mb:.1f} MB" for k, v in sizes["files"].items())
          + f", Draco per frame {sizes.get('dynamic_draco_bytes', 0) * mb:.1f} MB")


# ---------------------------------------------------------------- speed at ~20k vertices
def bench_speed(args):
    from trimesh.registration import nricp_amberg

    res = [f"hull.resolution={args.resolution}"]
    records = run(ROOT / "graphs/track_synth.yaml", args.cache, "0:11", upto="relax", overrides=res)
    recon, _ = outputs(records, "relax", "mesh", T.Mesh)
    vols, _ = outputs(run(ROOT / "graphs/track_synth.yaml", args.cache, "0:1", upto="hull", overrides=res, keep_all=True),
                      "hull", "volume", T.Volume)
    voxel = float(vols[0].voxel_size.max())
    nv = np.mean([len(m.vertices) for m in recon])
    fr = Frames(recon, voxel=voxel)
    t0 = time.perf_counter()
    res, segs = track_sequence(fr, TrackParams(voxel=voxel), keyframe=0)
    total = time.perf_counter() - t0
    per = [r.seconds for r in res[1:]]
    print(f"\nspeed: synthetic figure, hull {args.resolution}^3, {nv:.0f} vertices per frame, {len(recon)} frames, {len(segs)} segment(s)")
    print(f"ours: {np.median(per):.2f} s per frame median (min {min(per):.2f}, max {max(per):.2f}); whole run incl. graph "
          f"build {total:.1f} s = {total / (len(recon) - 1):.2f} s/frame")
    t0 = time.perf_counter()
    nricp_amberg(recon[0], recon[1])
    tn = time.perf_counter() - t0
    print(f"nricp_amberg (default steps), frame 0 -> 1: {tn:.1f} s; ratio {tn / np.median(per):.0f}x")
    factor_speed(fr, voxel)
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


def factor_speed(frames: Frames, voxel: float, reps: int = 20):
    """The fit's normal equations on the keyframe's graph (assembled as an ICP iteration assembles them, random
    normals for the matches): CHOLMOD's numeric factorisation and a solve, as the fit runs
    them (nodes/common/cholesky.py), against scipy's SuperLU in a fill-reducing order found once with diagonal
    pivots (the fit's method before stop 55), the same matrix; medians of ``reps``."""
    from scipy.sparse.linalg import splu

    from nodes.track import deform

    key = frames.meshes[0]
    target = frames.target(0)
    graph = deform.build_graph(target.vertices, np.asarray(key.faces, np.int64), TrackParams().spacing)
    reg = deform.Registration(graph, key.faces, deform.FitParams())
    # assembled as the fit assembles it: point-to-plane blocks n n^T of the sampled vertices (random normals), the
    # ARAP blocks at the fit's final weight, the tiny diagonal
    n = np.random.default_rng(0).normal(size=(len(reg.src), 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    pairs = reg.pair_of_sample @ ((n[:, :, None] * n[:, None, :]).reshape(-1, 9) / len(n))
    pairs += reg.params.arap / max(1, len(graph.directed)) * reg.arap_blocks
    pairs[reg.diag_pair] += 1e-8 * np.eye(3).ravel()
    values = pairs.ravel()[reg.gather]
    b = np.random.default_rng(1).normal(size=reg.n3)
    A = reg.cholesky.full(values).tocsc()
    position = splu(A, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True}).perm_c   # unknown -> position
    order = np.argsort(position)
    P = A[order][:, order].tocsc()

    def timed(f):
        ts = []
        for _ in range(reps):
            t0 = time.perf_counter()
            out = f()
            ts.append(time.perf_counter() - t0)
        return 1e3 * float(np.median(ts)), out

    t_chol, _ = timed(lambda: reg.cholesky.factor(values))
    t_csolve, x = timed(lambda: reg.cholesky.solve(b))
    t_lu, lu = timed(lambda: splu(P, permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True}))
    t_lsolve, y = timed(lambda: lu.solve(b[order])[position])
    assert np.abs(x - y).max() < 1e-9 * np.abs(x).max()
    route = {"cholmod": "CHOLMOD", "superlu": "SuperLU (no cvxopt)"}[reg.cholesky.route]
    print(f"the fit's normal equations ({reg.n3} unknowns, {A.nnz} nonzeros): {route} factorisation {t_chol:.2f} ms, "
          f"solve {t_csolve:.2f} ms; SuperLU (MMD order found once, diagonal pivots) {t_lu:.2f} ms, solve "
          f"{t_lsolve:.2f} ms ({t_lu / t_chol:.1f}x, {t_lsolve / t_csolve:.1f}x); the same solution (1e-9)")


# ---------------------------------------------------------------- the silhouette term's kernels
def bench_silhouettes(args):
    """child_rope frames (10 views, binary masks cropped by track.crop): the distance outline of each frame's masks
    (kernels/edt.cl vs scipy's exact transform) and the silhouette term's rows for 6000 samples of the previous
    frame's surface (kernels/outline.cl vs NumPy), the same results asserted, medians of 5 calls each."""
    from nodes.common.silhouettes import Silhouettes, outline_field, outline_field_reference
    from nodes.track import deform

    graph = ROOT / "graphs/track_child_rope.yaml"
    frames = args.frames or "27:37"
    crop = run(graph, args.cache, frames, upto="crop")
    meshes, _ = outputs(run(graph, args.cache, frames, upto="relax"), "relax", "mesh", T.Mesh)
    masks, _ = outputs(crop, "crop", "masks", T.Masks)
    cams, _ = outputs(crop, "crop", "cameras", T.CameraSet)

    def best(f, *a):
        ts = []
        for _ in range(5):
            t0 = time.perf_counter()
            out = f(*a)
            ts.append(time.perf_counter() - t0)
        return float(np.median(ts)), out

    rng = np.random.default_rng(0)
    rows = []
    for i in range(1, len(meshes)):
        fields = [best(f, m) for m in masks[i].masks for f in (outline_field, outline_field_reference)]
        assert all(np.array_equal(a[1], b[1]) for a, b in zip(fields[::2], fields[1::2]))
        views = Silhouettes.from_inputs(masks[i], cams[i], min_views=9, node="track").distance_outline()
        target = deform.Target(meshes[i].vertices, meshes[i].faces, np.asarray(meshes[0].vertices).min(axis=0), 0.0122, views)
        prev = (np.asarray(meshes[i - 1].vertices) - target.origin) / target.voxel
        x = prev[rng.choice(len(prev), min(6000, len(prev)), replace=False)]
        new, ref = best(deform.silhouette_rows, x, target), best(deform.silhouette_rows_reference, x, target)
        assert all(np.array_equal(a, b) for a, b in zip(new[1], ref[1]))
        rows.append((sum(t for t, _ in fields[::2]), sum(t for t, _ in fields[1::2]), new[0], ref[0], len(new[1][0])))
    r = np.array(rows)
    print(f"\nchild_rope frames {frames}, {len(masks[1].masks)} views, masks {sum(m.size for m in masks[1].masks) / 1e6:.2f} Mpx "
          f"a frame; the same results asserted")
    print(f"distance outline of a frame's masks: device {1e3 * np.median(r[:, 0]):.1f} ms, scipy {1e3 * np.median(r[:, 1]):.1f} ms "
          f"({np.median(r[:, 1] / r[:, 0]):.1f}x)")
    print(f"silhouette rows, 6000 samples x views ({np.median(r[:, 4]):.0f} rows): device {1e3 * np.median(r[:, 2]):.1f} ms, "
          f"NumPy {1e3 * np.median(r[:, 3]):.1f} ms ({np.median(r[:, 3] / r[:, 2]):.1f}x); 15 calls a fit")


# ---------------------------------------------------------------- child_rope
def bench_child_rope(args):
    graph = ROOT / "graphs/track_child_rope.yaml"
    records = run(graph, args.cache, args.frames, overrides=args.set)
    seq = outputs(records, "track", "sequence", T.MeshSequence)[0][0]
    table = outputs(records, "track", "residuals", Table)[0][0]
    before = outputs(records, "classify", "report", Table)[0][0]
    after = outputs(records, "tracked", "report", Table)[0][0]
    sizes = outputs(records, "export", "sizes", Table)[0][0]
    scores, _ = outputs(records, "score", "report", Table)
    track_rec = next(r for r in records if r["node"] == "track")
    lengths = [s["frames"] for s in table["segments"]]
    drop = np.array(table["residual"]["iou_drop"])
    print(f"\nchild_rope: {table['frames']} frames, reconstructions {before['class']} "
          f"({len(before['ranges'])} ranges, genus {min(before['topology']['genus'])}..{max(before['topology']['genus'])}, "
          f"{min(before['topology']['vertices'])}..{max(before['topology']['vertices'])} vertices)")
    print(f"tracked: {len(lengths)} segments, lengths {lengths}; median {np.median(lengths):.0f} (goal >= 60), "
          f"classes after: {after['frames_per_class']}; frames bridged: {table.get('bridged_frames', 0)}")
    print(f"silhouette IoU of the tracked mesh vs the frame's own refined reconstruction: drop mean {drop.mean():.4f}, "
          f"max {drop.max():.4f} (frames above 0.01: {int((drop > 0.01).sum())}); reconstruction IoU mean "
          f"{np.mean([s['mean_iou'] for s in scores]):.4f}")
    print(f"residual (voxels, mean of both ways): mean {table['distance_mean']:.3f}, max {table['distance_max']:.3f}; "
          f"track node {table['seconds']:.0f} s = {table['seconds_per_frame']:.2f} s/frame (when it was computed"
          f"{', a cache hit now' if track_rec.get('cache_hit') else ''})")
    for s in table["segments"]:
        print(f"  segment {s['start']:>3}..{s['stop']:>3} key {s['keyframe']:>3} genus {s['genus']} {s['vertices']} vertices; "
              f"ended after: {s['ended_after']}")
    mb = 1 / 1e6
    print(f"storage: per-frame reconstructions PLY {sizes['reconstruction_ply_bytes'] * mb:.1f} MB, raw "
          f"{sizes['reconstruction_raw_bytes'] * mb:.1f} MB, Draco {sizes['reconstruction_draco_bytes'] * mb:.1f} MB; dynamic "
          f"mesh raw {sizes['dynamic_raw_bytes'] * mb:.1f} MB, " + ", ".join(f"{k} {v * mb:.1f} MB" for k, v in sizes["files"].items())
          + f", Draco per frame {sizes.get('dynamic_draco_bytes', 0) * mb:.1f} MB")
    if not args.no_pictures:
        picks = [int(round(x)) for x in np.linspace(0, len(seq) - 1, 6)]
        # child_rope may not be published with the project (SOURCE.md): its meshes go to out/, not docs/
        (ROOT / "out").mkdir(exist_ok=True)
        picture(seq, picks, ROOT / "out" / "track_child_rope.png", "child_rope: tracked meshes")
        plot_residuals(table, DOCS / "track_child_rope_residuals.png", "child_rope")


# ---------------------------------------------------------------- pictures
def picture(seq, picks, path: Path, title: str):
    """Tracked meshes at a few frames, coloured by their keyframe (rest) position so a surface point keeps its
    colour while it is tracked; the segment and keyframe under each."""
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv

    p = pv.Plotter(off_screen=True, window_size=(240 * len(picks), 440), shape=(1, len(picks)), border=False)
    by_seg = {}
    for m in seq:
        by_seg.setdefault(m.metadata.get("segment"), np.asarray(m.vertices))   # first frame of each segment
    for col, i in enumerate(picks):
        m = seq[i]
        rest = by_seg[m.metadata.get("segment")]
        lo, hi = rest.min(axis=0), rest.max(axis=0)
        u = (rest - lo) / np.maximum(hi - lo, 1e-9)
        stripes = (np.floor(u[:, 2] * 20) % 2) * 0.55 + (np.floor(u[:, 0] * 6) % 2) * 0.3 + (np.floor(u[:, 1] * 6) % 2) * 0.15
        faces = np.hstack([np.full((len(m.faces), 1), 3), m.faces]).ravel()
        mesh = pv.PolyData(np.asarray(m.vertices), faces)
        mesh["pattern"] = stripes
        p.subplot(0, col)
        p.add_mesh(mesh, scalars="pattern", cmap="viridis", show_scalar_bar=False, smooth_shading=True)
        p.add_text(f"frame {m.metadata.get('frame', i)}  seg {m.metadata.get('segment')} (key {m.metadata.get('keyframe')})",
                   font_size=9, color="black")
        p.set_background("white")
        lo_all = np.min([np.asarray(seq[j].vertices).min(axis=0) for j in picks], axis=0)
        hi_all = np.max([np.asarray(seq[j].vertices).max(axis=0) for j in picks], axis=0)
        centre, size = (lo_all + hi_all) / 2, float(np.max(hi_all - lo_all))
        p.camera.focal_point = centre
        p.camera.position = centre + size * np.array([1.6, -2.2, 0.5])
        p.camera.up = (0, 0, 1)
        p.camera.view_angle = 30
    p.screenshot(str(path))
    p.close()
    print(f"wrote {path}")


def plot_residuals(table, path: Path, title: str, extra=None):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    f = table["timeline"]["frame"]
    rows = 3 if "iou_drop" in table["residual"] or extra else 2
    fig, ax = plt.subplots(rows, 1, figsize=(9, 2.2 * rows), sharex=True)
    ax[0].plot(f, table["residual"]["distance"], label="mean surface distance (both ways)")
    ax[0].plot(f, table["residual"]["distance_p95"], label="95th percentile", alpha=0.7)
    ax[0].set_ylabel("voxels")
    ax[0].legend(fontsize=7)
    ax[1].step(f, table["timeline"]["segment"], where="mid", color="k")
    bridged = [x for x, b in zip(f, table["timeline"].get("bridged", [])) if b]
    if bridged:
        seg = dict(zip(f, table["timeline"]["segment"]))
        ax[1].plot(bridged, [seg[x] for x in bridged], "o", color="tab:orange", ms=3, label="bridged frames")
        ax[1].legend(fontsize=7, loc="lower right")
    ax[1].set_ylabel("segment")
    for s in table["segments"]:
        for a in ax:
            a.axvline(s["start"] - 0.5, color="0.8", lw=0.6)
        ax[0].plot([s["keyframe"]], [0], "rv", ms=4)
    if "iou_drop" in table["residual"]:
        ax[2].plot(f, table["residual"]["iou_drop"], color="tab:red")
        ax[2].axhline(0.01, color="tab:red", ls=":", lw=0.8)
        ax[2].set_ylabel("IoU drop")
    elif extra:
        ax[2].plot(f, extra[1], color="tab:green")
        ax[2].set_ylabel(f"{extra[0]}\n(voxels)", fontsize=7)
    ax[-1].set_xlabel("frame")
    fig.suptitle(f"{title}: residual per frame (keyframes: red marks)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    print(f"wrote {path}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=("synth", "speed", "child_rope", "silhouettes"))
    ap.add_argument("--cache", type=Path, default=ROOT / ".volcap-cache")
    ap.add_argument("--frames", default=None)
    ap.add_argument("--nricp-frames", type=int, default=3)
    ap.add_argument("--resolution", type=int, default=164, help="speed: hull resolution (164^3: ~20k vertices after relax)")
    ap.add_argument("--no-pictures", action="store_true")
    ap.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE", help="synth, child_rope: graph overrides")
    args = ap.parse_args()
    header()
    {"synth": bench_synth, "speed": bench_speed, "child_rope": bench_child_rope, "silhouettes": bench_silhouettes}[args.what](args)
    print(f"load average at the end: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
