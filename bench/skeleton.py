"""Skeletons and skinning (issue 17), next to the libraries a user would otherwise pick, in the same run.

    python bench/skeleton.py [--frames 100] [--bones 10] [--noise 0] [--meshes a.ply,b.ply] [--skip-dembones]
                             [--extract-only | --skin-only]

Extraction (one frame's solid): the synth walking figure at frame 6 (13k vertices), and any --meshes (e.g.
thu_wd_human / inria_dancer reconstructions), voxelized at 128^3 along the longest side.
  ours        nodes.skeleton.curve: parity voxelization + TEASAR + joint tree (the skeletonize node's work)
  kimimaro    kimimaro.skeletonize (TEASAR, C++) on the same voxel grid (our voxelization time not included)
  skeletor    skeletor.skeletonize.by_wavefront on the mesh (its fastest method; contract is minutes)
  For the figure: distance of the true curve-skeleton key points (extremities, branch points, bends of
  more than 15 degrees) to the nearest joint (ours) or skeleton vertex (baselines: they return dense
  polylines, which is easier), in voxels.
Skinning (a dynamic mesh): the figure's true meshes over --frames frames (optionally with Gaussian noise),
frame 0 as rest, the same bone count for everyone:
  ours fixed  skeletonize.sequence + skin (rotation-only joints, bone lengths constant, rest refined)
  ours free   the same with rigid bones moving freely (the SSDR bone update)
  dem bones   py_dem_bones.solve_skinning(max_influences=4, iterations=30)
  ours fixed, k iterations: the first k iterations of ours fixed, k the first whose rms is within Dem Bones' (the
              issue's "<= 1/2 of Dem Bones' time at its accuracy"; the full run above is what the node does by default)
  Columns: seconds, LBS rmse (mm and % of the bbox diagonal), max error, bone-length spread over frames (max
  over bones of (max - min) / mean of the distance between a bone's pivot and its parent's), and for ours the
  joint error against the true joints (the true joint owning most of each part's vertices), in voxels of a
  128^3 grid over the figure.
Prints the OpenCL device, the CPU model and the load average before and after.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import machine  # noqa: E402

from nodes.skeleton import curve, motion, skinning  # noqa: E402
from nodes.synth import scenes  # noqa: E402
from nodes.synth.scenes import figure_keypoints  # noqa: E402


def _timed(fn, *a, reps: int = 1, **k):
    """(result, median seconds over reps runs after one untimed warm-up run when reps > 1)."""
    if reps > 1:
        fn(*a, **k)
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        out = fn(*a, **k)
        times.append(time.perf_counter() - t)
    return out, float(np.median(times))


REPS = 5


def extraction(name, mesh, keys=None):
    try:
        import kimimaro
        import skeletor
    except ImportError as exc:      # the peers are the bench extra's (pyproject.toml), not setup.sh's
        raise SystemExit(f"bench/skeleton.py: the extraction's peers are missing ({exc.name}): "
                         "pip install 'kimimaro>=4.0' 'skeletor>=1.3' (pyproject's bench extra), or --skin-only") from None
    import trimesh
    from scipy.spatial import cKDTree

    (occ, origin, voxel), t_vox = _timed(curve.voxelize, mesh.vertices, mesh.faces, 128, reps=REPS)
    sk, t_ours = _timed(curve.curve_skeleton, occ, origin, voxel, reps=REPS)
    rows = [("ours (voxelize + TEASAR + tree)", t_vox + t_ours, sk.joints, f"{len(sk.joints)} joints, "
             f"{len(sk.leaves)} extremities {[sk.names[j] for j in sk.leaves]}")]
    labels = occ.astype(np.uint32)
    kk, t_k = _timed(kimimaro.skeletonize, labels, teasar_params={"scale": 1.5, "const": 2 * voxel},
                     anisotropy=(voxel,) * 3, dust_threshold=0, fix_branching=True, progress=False, parallel=1,
                     reps=REPS)
    ks = kk[1]
    kv = ks.vertices + origin
    rows.append(("kimimaro (TEASAR, C++; same grid)", t_k, kv, f"{len(ks.vertices)} vertices, {len(ks.edges)} edges"))
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    sw, t_s = _timed(skeletor.skeletonize.by_wavefront, tm, waves=1, step_size=1, progress=False, reps=REPS)
    rows.append(("skeletor by_wavefront (mesh)", t_s, np.asarray(sw.vertices), f"{len(sw.vertices)} vertices"))
    print(f"\n== extraction: {name} ({len(mesh.vertices)} vertices, voxel {voxel * 1000:.1f} mm, "
          f"{int(occ.sum())} voxels inside; voxelization {t_vox * 1000:.0f} ms)")
    print(f"(median of {REPS} runs after a warm-up)")
    print(f"{'method':38s} {'ms':>8s} {'x ours':>7s}  key points: median / max voxels   output")
    for label, secs, pts, what in rows:
        err = ""
        if keys is not None:
            d, _ = cKDTree(pts).query(np.array(list(keys.values())))
            err = f"{np.median(d) / voxel:5.2f} / {d.max() / voxel:5.2f}"
        print(f"{label:38s} {secs * 1000:8.0f} {secs / (t_vox + t_ours):7.2f}  {err:>22s}   {what}")
    if keys is not None:
        d, i = cKDTree(sk.joints).query(np.array(list(keys.values())))
        print("  ours per key point (voxels): " + ", ".join(f"{k} {x / voxel:.1f}" for k, x in zip(keys, d)))


def figure_sequence(frames: int, noise: float):
    rest, weights, _ = scenes.figure_rest()
    pts = np.array([scenes.skin(rest.vertices, weights, *scenes.figure_pose(f)) for f in range(frames)])
    if noise:
        pts = pts + np.random.default_rng(0).normal(0, noise, pts.shape)
    return pts, np.asarray(rest.faces), weights


def bone_spread(joints, parents, rot, tr):
    piv = np.einsum("fjab,jb->fja", rot, joints) + tr
    out = 0.0
    for j, p in enumerate(parents):
        if p >= 0:
            length = np.linalg.norm(piv[:, j] - piv[:, p], axis=1)
            out = max(out, float((length.max() - length.min()) / length.mean()))
    return out


def joint_errors(joints, parents, labels, true_weights, voxel):
    """Per non-root bone: distance between our rest pivot and the true joint between the true bones that
    own most of its part and of its parent part (whichever is the other's parent in the truth)."""
    owner = [int(np.argmax(true_weights[labels == j].sum(0))) for j in range(len(parents))]
    true = scenes.figure_pose(0)[1]
    out = []
    for j, p in enumerate(parents):
        if p >= 0:
            a, b = owner[j], owner[p]
            if scenes.PARENTS[a] == b or scenes.PARENTS[b] == a:
                k = a if scenes.PARENTS[a] == b else b
                out.append((scenes.NAMES[k], float(np.linalg.norm(joints[j] - true[k]) / voxel)))
            else:
                out.append((f"{scenes.NAMES[a]}|{scenes.NAMES[b]} (not adjacent)", float("nan")))
    return out


def skinning_bench(frames, bones, noise, dembones):
    pts, faces, true_w = figure_sequence(frames, noise)
    diag = float(np.linalg.norm(np.ptp(pts[0], axis=0)))
    voxel = float(np.ptp(pts[0], axis=0).max()) / 128
    print(f"\n== skinning: synth figure, {frames} frames, {pts.shape[1]} vertices, noise {noise * 1000:.1f} mm, "
          f"{bones} bones, diagonal {diag:.3f} m (128^3 voxel {voxel * 1000:.1f} mm)")
    print(f"{'method':28s} {'s':>7s} {'rmse mm':>8s} {'% diag':>8s} {'max mm':>7s} {'length spread':>14s}  joints (voxels)")
    traj = motion.Trajectories(pts[0], pts)
    t0 = time.perf_counter()
    parts = motion.rigid_parts(pts[0], pts, faces, bones=bones)
    rig = motion.build_rig(pts[0], faces, parts)
    t_rig = time.perf_counter() - t0
    results = {}
    if dembones:   # first: its rms is the bar ours is stopped at below
        import py_dem_bones as pdb

        res, t_db = _timed(pdb.solve_skinning, pts[0], pts, bones, faces=faces, max_influences=4, iterations=30)
        w, m = res.weights.T, res.transforms
        pred = np.einsum("vb,fbij,vj->fvi", w, m[:, :, :3, :3], pts[0], optimize=True) + np.einsum("vb,fbi->fvi", w, m[:, :, :3, 3])
        d = np.linalg.norm(pred - pts, axis=2)
        db_rmse = float(np.sqrt((d ** 2).mean()))
        print(f"{'dem bones (30 its)':28s} {t_db:7.1f} {db_rmse * 1000:8.3f} {100 * db_rmse / diag:8.4f} {d.max() * 1000:7.2f} "
              f"{'no joints':>14s}  ({w.shape[1]} bones returned)")
        results["dem bones"] = db_rmse
    first_history = []
    for label, fixed in (("ours fixed lengths", True), ("ours free bones", False)):
        fit, t_fit = _timed(skinning.fit_skin, traj, faces, rig, fixed_lengths=fixed)
        rmse = float(np.sqrt((fit.rmse ** 2).mean()))
        errs = joint_errors(fit.joints, fit.parents, rig.labels, true_w, voxel)
        jtxt = f"median {np.nanmedian([e for _, e in errs]):.2f} max {np.nanmax([e for _, e in errs]):.2f}" if fixed else ""
        print(f"{label:28s} {t_rig + t_fit:7.1f} {rmse * 1000:8.3f} {100 * rmse / diag:8.4f} {fit.max_error.max() * 1000:7.2f} "
              f"{bone_spread(fit.joints, fit.parents, fit.rotations, fit.translations):14.2e}  {jtxt}")
        if fixed:
            print("  ours joints (voxels): " + ", ".join(f"{n} {e:.1f}" for n, e in errs))
            print(f"  (skeleton from motion {t_rig:.1f} s, skin {t_fit:.1f} s, {len(fit.history)} iterations)")
            first_history = list(fit.history)
        results[label] = rmse
    if dembones:
        ours = results["ours fixed lengths"]
        print(f"  ours fixed / dem bones rmse: {ours / db_rmse:.2f} ({'not above' if ours <= db_rmse else 'ABOVE'} Dem Bones)")
        # the issue's "<= 1/2 of Dem Bones' time at its accuracy": ours stopped at the first iteration whose rms is
        # within Dem Bones' (the same iterations as the full run: each is deterministic), the rig included
        k = next((i + 1 for i, h in enumerate(first_history) if h <= db_rmse), None)
        if k is None:
            print("  ours fixed never reaches Dem Bones' rms")
        else:
            fit, t_k = _timed(skinning.fit_skin, traj, faces, rig, fixed_lengths=True, iterations=k)
            rmse = float(np.sqrt((fit.rmse ** 2).mean()))
            if abs(rmse - first_history[k - 1]) > 1e-9 * max(rmse, 1e-12):
                print(f"  (note: {k} iterations alone give rms {rmse:.6g}, the full run had {first_history[k - 1]:.6g} there)")
            print(f"{'ours fixed, ' + str(k) + ' iteration' + ('s' if k > 1 else ''):28s} {t_rig + t_k:7.1f} {rmse * 1000:8.3f} "
                  f"{100 * rmse / diag:8.4f} {fit.max_error.max() * 1000:7.2f}  (stopped at Dem Bones' rms: "
                  f"{(t_rig + t_k) / t_db:.2f} x its time, {rmse / db_rmse:.2f} x its rms)")
    return results


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--bones", type=int, default=10)
    ap.add_argument("--noise", type=float, default=0.0, help="Gaussian noise sigma on the sequence, metres")
    ap.add_argument("--meshes", default="", help="comma-separated mesh files for the extraction table")
    ap.add_argument("--skip-dembones", action="store_true")
    ap.add_argument("--extract-only", action="store_true")
    ap.add_argument("--skin-only", action="store_true")
    args = ap.parse_args()
    print(machine.describe())
    if not args.skin_only:
        import trimesh

        sc = scenes.build("figure", 6)
        extraction("synth figure, frame 6", sc.mesh, figure_keypoints(6))
        for path in filter(None, args.meshes.split(",")):
            extraction(Path(path).name, trimesh.load(path, process=False, force="mesh"))
    if not args.extract_only:
        skinning_bench(args.frames, args.bones, args.noise, not args.skip_dembones)
    print("\n" + machine.describe().splitlines()[-1])


if __name__ == "__main__":
    main()
