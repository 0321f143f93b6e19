"""Where the humanoid rig's LBS error on child_rope lies, and what a 19-bone LBS can reach on the same motion.

    python bench/humanoid_ceiling.py [--cache DIR] [--segments 0,1,2] [--skip-dembones]

Runs graphs/skeleton/child_rope_humanoid.yaml through the engine (cache hits after bench/humanoid.py child_rope)
and per segment:
  - the rig's LBS residual (skin_K) split by named bone region (each vertex in the region of its strongest bone):
    share of the squared error, rms, 95th percentile; and per frame (rms, max);
  - the same template parts (fit_K) skinned again four ways, same run: rotation-only joints with the joints kept
    (the graph's skin, captured rest), with the joints as unknowns shared over frames (``pivots``), free rigid bones
    (lengths: free, as Dem Bones moves them), and py-dem-bones with 19 bones from its own clustering (30 iterations,
    4 influences): the ceiling of a 19-bone LBS on this motion; and py-dem-bones at the graph rig's bone count when
    its skin adds helper bones (the template and its helpers against as many free bones);
  - correctives: the residual of the graph's rig in rest space (each vertex's offset undone by its blended
    rotation), its principal components: how many per-frame corrective shapes take the rms to 1 % of the height.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from machine import describe  # noqa: E402


def region_of(name: str) -> str:
    if name.startswith("helper_"):            # a helper bone (helper_<host>_<k>) counts in its host's region
        name = name.removeprefix("helper_").rsplit("_", 1)[0]
    for key in ("clavicle", "shoulder", "elbow", "wrist", "hip", "knee", "ankle"):
        if name.startswith(key):
            return {"clavicle": "clavicle", "shoulder": "upper arm", "elbow": "forearm", "wrist": "hand",
                    "hip": "thigh", "knee": "shin", "ankle": "foot"}[key]
    return {"pelvis": "pelvis", "spine": "spine", "chest": "chest", "neck": "neck", "head": "head"}.get(name, name)


def rms(x, axis=None):
    return float(np.sqrt(np.mean(x ** 2))) if axis is None else np.sqrt(np.mean(x ** 2, axis=axis))


def report_fit(label, pred, frames, secs, height, extra=""):
    d = np.linalg.norm(pred - frames, axis=2)
    per = 1000 * rms(d, axis=1)
    mx = 1000 * d.max(1)
    ok = int(((per <= 10 * height) & (mx <= 50 * height)).sum())
    print(f"  {label:34s} {secs:6.1f} s  rms {1000 * rms(d):6.1f} mm  per frame median {np.median(per):5.1f} worst "
          f"{per.max():5.1f}  max per frame median {np.median(mx):6.1f} worst {mx.max():6.1f}  frames within goals "
          f"{ok}/{len(per)} {extra}")
    return d


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cache", type=Path, default=ROOT / ".volcap-cache")
    ap.add_argument("--segments", default="0,1,2")
    ap.add_argument("--skip-dembones", action="store_true")
    ap.add_argument("--skip-refits", action="store_true", help="not the template parts skinned again (the residual "
                    "split and Dem Bones still run)")
    a = ap.parse_args()
    print(describe())
    from nodegraph import Table
    from nodes.common import types as T
    from nodes.skeleton.motion import Rig, Trajectories
    from nodes.skeleton.skinning import fit_skin, lbs
    from nodes.common.types import sequence_segments
    from track import outputs, run

    os.environ.setdefault("VOLCAP_DATA", str(ROOT.parent / "shared" / "data"))
    records = run(ROOT / "graphs" / "skeleton" / "child_rope_humanoid.yaml", a.cache, None)
    seq = list(outputs(records, "track", "sequence", T.MeshSequence)[0][0])
    heights = [float(np.ptp(np.asarray(m.vertices)[:, 2])) for m in seq]
    height = float(np.percentile(heights, 95))
    print(f"child_rope: subject height {height:.3f} m: goals rms <= {10 * height:.1f} mm, max <= {50 * height:.1f} mm per frame")
    runs = sequence_segments(seq)
    for k in map(int, a.segments.split(",")):
        start, stop = runs[k]
        frames = np.stack([np.asarray(m.vertices, np.float64) for m in seq[start:stop]])
        faces = np.asarray(seq[start].faces, np.int64)
        [sk], _ = outputs(records, f"skin_{k}", "skeleton", T.Skeleton)
        [rest], _ = outputs(records, f"skin_{k}", "rest", T.Mesh)
        [err], _ = outputs(records, f"skin_{k}", "error", Table)
        [fit], _ = outputs(records, f"fit_{k}", "skeleton", T.Skeleton)
        rest = np.asarray(rest.vertices, np.float64)
        w = np.asarray(sk.weights)
        rot, tr = np.asarray(sk.rotations), np.asarray(sk.translations)
        pred = lbs(rest, w, rot, tr)
        res = pred - frames                                           # (F, V, 3)
        d = np.linalg.norm(res, axis=2)
        print(f"\nsegment {k}: frames {start}..{stop - 1} ({len(frames)}), {frames.shape[1]} vertices, {len(sk.names)} "
              f"bones; the graph's rig (T pose): rms {1000 * rms(d):.1f} mm (node's table: {1000 * err['rmse']:.1f})")
        report_fit(f"the graph's rig ({len(sk.names)} bones)", pred, frames, err["seconds"], height)
        strongest = np.argmax(w, axis=1)
        region = np.array([region_of(sk.names[b]) for b in strongest])
        total = float((d ** 2).sum())
        rows = []
        for r in dict.fromkeys(region_of(n) for n in sk.names):
            m = region == r
            if not m.any():
                continue
            dr = d[:, m]
            rows.append((float((dr ** 2).sum()) / total, r, int(m.sum()), 1000 * rms(dr), 1000 * np.percentile(dr, 95),
                         1000 * dr.max()))
        print("  by region (vertices by their strongest bone; both sides together): share of the squared error, "
              "vertices, rms / p95 / max mm")
        for share, r, n, a_rms, p95, mx in sorted(rows, reverse=True):
            print(f"    {r:10s} {100 * share:5.1f} %  {n:6d}  {a_rms:6.1f} {p95:6.1f} {mx:6.1f}")
        per = 1000 * rms(d, axis=1)
        order = np.argsort(per)
        print("  per frame rms mm (best 3, median, worst 3): " + ", ".join(
            f"{sk.frames[i]}: {per[i]:.1f}" for i in list(order[:3]) + [order[len(order) // 2]] + list(order[-3:])))
        top = np.argsort(-d.max(0))[:200]
        print("  where the 200 worst vertices (by max over frames) are: " + ", ".join(
            f"{r} {c}" for r, c in zip(*np.unique(region[top], return_counts=True))))
        # correctives: the residual in rest space, its principal components
        blend = np.einsum("vj,fjab->fvab", w, rot)                    # (F, V, 3, 3)
        back = -np.einsum("fvba,fvb->fva", blend, res)                # approx. R^-1 (frames - pred)
        x = back.reshape(len(frames), -1)
        mean = x.mean(0)
        u, s, vt = np.linalg.svd(x - mean, full_matrices=False)
        line = []
        for c in (0, 1, 2, 4, 8, 16, 32):
            if c > len(s):
                break
            approx = mean + (u[:, :c] * s[:c]) @ vt[:c] if c else np.broadcast_to(mean, x.shape)
            fixed = res + np.einsum("fvab,fvb->fva", blend, approx.reshape(back.shape))
            dd = np.linalg.norm(fixed, axis=2)
            line.append(f"{c}: {1000 * rms(dd):.1f} / {1000 * np.median(dd.max(1)):.0f}")
        print("  correctives (mean + c principal shapes of the rest-space residual, per-frame coefficients): "
              "c: rms / median max per frame mm: " + "; ".join(line))
        if not a.skip_refits:
            print("  the same motion, skinned again (captured rest, 4 influences):")
            traj = Trajectories(frames[0], frames)
            labels = np.argmax(np.asarray(fit.weights), axis=1)
            rig = Rig(np.asarray(fit.joints, np.float64), list(fit.parents), list(fit.names), np.asarray(fit.rotations),
                      np.asarray(fit.translations), labels, np.zeros(len(fit.parents)), np.zeros(len(fit.parents)))
            one = np.zeros((len(labels), len(fit.parents)))
            one[np.arange(len(labels)), labels] = 1
            report_fit("template parts, rigid (fit's motion)", lbs(frames[0], one, rig.rotations, rig.translations), frames,
                       0.0, height)
            for label, kw in (("joints kept (the graph's skin)", dict(pivots=False, merge=False)),
                              ("joints as unknowns (pivots)", dict(pivots=True, merge=False)),
                              ("free rigid bones (Dem Bones' step)", dict(fixed_lengths=False, merge=False))):
                t0 = time.perf_counter()
                f = fit_skin(traj, faces, rig, **kw)
                dd = report_fit(label, lbs(f.rest, f.weights, f.rotations, f.translations), frames,
                                time.perf_counter() - t0, height, f"({len(f.history)} its)")
                if kw.get("pivots"):
                    moved = np.linalg.norm(f.joints - rig.joints, axis=1)
                    print("    joints moved cm: " + ", ".join(f"{n} {100 * m:.1f}" for n, m in zip(fit.names, moved)))
        if not a.skip_dembones:
            import py_dem_bones as pdb

            # the template's bone count, and the graph's rig's (the template and its helper bones) where that differs
            for bones in dict.fromkeys((len(fit.parents), len(sk.names))):
                t0 = time.perf_counter()
                r = pdb.solve_skinning(frames[0], frames, bones, faces=faces, max_influences=4, iterations=30)
                wd, m = r.weights.T, r.transforms
                pred = (np.einsum("vb,fbij,vj->fvi", wd, m[:, :, :3, :3], frames[0], optimize=True)
                        + np.einsum("vb,fbi->fvi", wd, m[:, :, :3, 3]))
                report_fit(f"py-dem-bones, {bones} bones, 30 its", pred, frames, time.perf_counter() - t0, height,
                           f"({wd.shape[1]} bones returned)")
    print("at the end: " + describe())


if __name__ == "__main__":
    main()
