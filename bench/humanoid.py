"""The named humanoid template (skeleton.humanoid) on the synthetic walking figure, against the free curve
skeleton (skeletonize: TEASAR joint tree, five named extremities) the user would otherwise start from, same
voxel resolution, same run: seconds per frame, and the template's joint errors against the figure's true joints
(median, 90th percentile, max; sides checked by name), over a walk cycle.

    python bench/humanoid.py [--frames 24] [--resolution 96]
    python bench/humanoid.py figure [--frames 24] [--cache DIR]
    python bench/humanoid.py child_rope [--cache DIR]

figure: the demo's character on its reconstruction (graphs/bench/figure_character.yaml through the engine: 12
cameras 640x480 -> hull 128^3 -> relax -> track -> skeletonize.humanoid -> skin in a T pose, as graphs/demo.yaml's
demo_character): the posed joints of every frame against the figure's true ones, in voxels of 128^3 (the issue's bar:
every named joint within 2 voxels), per joint.

child_rope: graphs/skeleton/child_rope_humanoid.yaml through the engine (the tracked sequence from its cache:
the first run tracks, ~30 min): every tracked segment rigged with the template (skeletonize.humanoid -> skin,
joints kept) -> per segment the frame it was fitted on, bones kept, LBS rms and max per frame against the goals
(rms <= 1 % of the subject's height, max <= 5 %), posed joints outside the tracked body, the posed ankles' height
above the sole where a foot stands on the floor (an ankle joint: ~4.5 % of the height up), bone lengths per segment,
seconds per frame; the named joints
over the silhouettes of 3 views at 4 frames (out/skeleton_humanoid_child_rope.jpg, and docs/ with --docs).
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
from nodes.skeleton.skinning import is_helper  # noqa: E402
from nodegraph.testing import run_node  # noqa: E402
from nodes.synth import scenes  # noqa: E402

TRUTH = {"pelvis": "pelvis", "chest": "chest", "neck": "neck", "head": "head", "shoulder_{s}": "{s}_shoulder",
         "elbow_{s}": "{s}_elbow", "wrist_{s}": "{s}_wrist", "hip_{s}": "{s}_hip", "knee_{s}": "{s}_knee",
         "ankle_{s}": "{s}_ankle"}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", nargs="?", default="synth", choices=("synth", "figure", "child_rope"))
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--resolution", type=int, default=96)
    ap.add_argument("--cache", type=Path, default=ROOT / ".volcap-cache")
    ap.add_argument("--docs", action="store_true", help="child_rope: also write the picture to docs/")
    a = ap.parse_args()
    print(describe())
    if a.scene == "child_rope":
        return child_rope(a)
    if a.scene == "figure":
        return figure(a)
    t_h, t_s, err, per_joint = [], [], [], {}
    for f in range(a.frames):
        scene = scenes.build("figure", f)
        t0 = time.perf_counter()
        sk = run_node("skeleton.humanoid", {"mesh": scene.mesh}, {"resolution": a.resolution, "hand": 0, "foot": 0.08})["skeleton"]   # no hands, short feet
        t_h.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        run_node("skeletonize", {"mesh": scene.mesh}, {"resolution": a.resolution})
        t_s.append(time.perf_counter() - t0)
        for ours, theirs in TRUTH.items():
            for s in ("l", "r") if "{s}" in ours else (None,):
                n = ours.format(s=s) if s else ours
                e = float(np.linalg.norm(sk.joints[sk.names.index(n)]
                                         - scene.skeleton.joints[scene.skeleton.names.index(theirs.format(s=s) if s else theirs)]))
                err.append(e)
                per_joint.setdefault(ours.replace("_{s}", ""), []).append(e)
    e = 100 * np.array(err)
    print(f"\nsynth figure, {a.frames} frames of the walk, {a.resolution}^3")
    print(f"skeleton.humanoid  {1000 * np.median(t_h):7.1f} ms/frame (median)   joint error cm: median {np.median(e):.1f}, "
          f"p90 {np.percentile(e, 90):.1f}, max {e.max():.1f}")
    print(f"skeletonize        {1000 * np.median(t_s):7.1f} ms/frame (median)   (no named joints: 5 extremities)")
    print(f"ratio humanoid / skeletonize: {np.median(t_h) / np.median(t_s):.2f}")
    print("per joint, median / max cm: " + ", ".join(f"{k} {100 * np.median(v):.1f}/{100 * max(v):.1f}"
                                                     for k, v in per_joint.items()))
    print("at the end: " + describe())


def figure(a):
    """The demo's character (graphs/bench/figure_character.yaml) against the figure's true joints, per frame."""
    from nodes.common import types as T
    from nodes.skeleton import formats
    from track import outputs, run

    graph = ROOT / "graphs" / "bench" / "figure_character.yaml"
    t0 = time.perf_counter()
    records = run(graph, a.cache, f"0:{a.frames}")
    wall = time.perf_counter() - t0
    [sk], _ = outputs(records, "humanoid_skin", "skeleton", T.Skeleton)
    world = formats.world_transforms(np.asarray(sk.joints), np.asarray(sk.rotations), np.asarray(sk.translations))
    per_joint = {}
    for k, f in enumerate(sk.frames):
        scene = scenes.build("figure", f)
        voxel = float(np.ptp(np.asarray(scene.mesh.vertices), axis=0).max()) / 128
        for ours, theirs in TRUTH.items():
            for s in ("l", "r") if "{s}" in ours else (None,):
                n, t = (ours.format(s=s), theirs.format(s=s)) if s else (ours, theirs)
                e = np.linalg.norm(world[k, sk.names.index(n), :3, 3] - scene.skeleton.joints[scene.skeleton.names.index(t)])
                per_joint.setdefault(n, []).append(e / voxel)
    e = np.concatenate(list(per_joint.values()))
    print(f"\nthe demo's character on its reconstruction, {len(sk.frames)} frames, 128^3: posed joints against the "
          f"truth, voxels: median {np.median(e):.2f}, max {e.max():.2f}; (frame, joint) pairs beyond 2 voxels: "
          f"{int((e > 2).sum())} of {e.size}")
    print("per joint, median / max voxels (pairs beyond 2): " + ", ".join(
        f"{n} {np.median(v):.2f}/{max(v):.2f} ({sum(x > 2 for x in v)})" for n, v in per_joint.items()))
    print(f"graph run {wall:.0f} s (cached items are not recomputed); at the end:")
    print(describe())


SEGMENTS = 3          # the graph rigs segments 0, 1, 2 (fit_K, skin_K)
MARK = {"head", "neck", "pelvis", "shoulder", "elbow", "wrist", "hip", "knee", "ankle"}


def child_rope(a):
    from nodegraph import Table
    from nodes.common import types as T
    from track import outputs, run

    os.environ.setdefault("VOLCAP_DATA", str(ROOT.parent / "shared" / "data"))
    graph = ROOT / "graphs" / "skeleton" / "child_rope_humanoid.yaml"
    t0 = time.perf_counter()
    records = run(graph, a.cache, None)
    wall = time.perf_counter() - t0
    seq = outputs(records, "track", "sequence", T.MeshSequence)[0][0]
    heights = [float(np.ptp(np.asarray(m.vertices)[:, 2])) for m in seq]
    height = float(np.percentile(heights, 95))
    print(f"\nchild_rope: {len(seq)} tracked frames, subject height {height:.3f} m (95th percentile over frames of the "
          f"mesh's z extent; median {np.median(heights):.3f}: the child bends and jumps): goals LBS rms <= {10 * height:.1f} mm (1 %), max <= {50 * height:.1f} mm (5 %)")
    rigs, lengths = [], {}
    for k in range(SEGMENTS):
        [fit], [fit_rec] = outputs(records, f"fit_{k}", "report", Table)
        [err], [skin_rec] = outputs(records, f"skin_{k}", "error", Table)
        [sk], _ = outputs(records, f"skin_{k}", "skeleton", T.Skeleton)
        t = err["timeline"]
        rms, mx = 1000 * np.array(t["rmse"]), 1000 * np.array(t["max"])
        secs = fit_rec["seconds"] + err["seconds"]      # skin's own time survives a cache hit; the fit's does not
        seg = fit["segment"]
        print(f"segment {k}: frames {seg['first_frame']}..{seg['last_frame']} ({len(t['frame'])}), template fitted "
              f"on frame {fit['fitted_on_frame']} (legs {fit.get('legs')}; {len(fit.get('frames_refused', []))} frames "
              f"refused; parts' rigid rms by tried frame index, mm: {fit.get('rigid_rms_mm_by_index')}), "
              f"{err['bones']} bones kept{', removed ' + ', '.join(err['removed']) if err['removed'] else ''}")
        print(f"  LBS rms per frame mm: median {np.median(rms):.1f}, worst {rms.max():.1f} (frame "
              f"{t['frame'][int(rms.argmax())]}) = {rms.max() / (10 * height):.2f} % of the height; max per frame: "
              f"median {np.median(mx):.1f}, worst {mx.max():.1f} mm = {mx.max() / (10 * height):.2f} %; frames within "
              f"both goals {int(((rms <= 10 * height) & (mx <= 50 * height)).sum())}/{len(rms)}; bone-length spread "
              f"{err['bone_length_spread']:.1e}; {err['iterations']} iterations")
        out = err.get("joints_outside")
        if out:
            worst = sorted(out["worst_by_joint"].items(), key=lambda kv: -kv[1])[:3]
            print(f"  posed joints outside the tracked body: {out['beyond_2cm']} of {out['pairs']} (frame, joint) "
                  f"pairs ({100 * out['beyond_2cm'] / out['pairs']:.1f} %) beyond 2 cm, {out['beyond_limit']} beyond "
                  f"their bones' thickness; worst {1000 * out['worst']:.0f} mm ({out['worst_joint']}, frame "
                  f"{out['worst_frame']}); "
                  f"worst joints {', '.join(f'{n} {1000 * x:.0f}' for n, x in worst)} mm")
            if out.get("helpers"):
                hp = out["helpers"]
                print(f"  helper bones' pivots (the centre of the surface each skins) outside the tracked body beyond "
                      f"2 cm: {hp['beyond_2cm']} of {hp['pairs']} (frame, helper) pairs, worst {1000 * hp['worst']:.0f} mm")
        print(f"  seconds: fit {fit_rec['seconds']:.1f}{' (a cache hit)' if fit_rec['cache_hit'] else ''} + skin "
              f"{err['seconds']:.1f} = {secs / len(rms):.2f} s per frame")
        rise = planted_ankles(sk, seq)
        if len(rise):
            print(f"  posed ankles above the sole where the foot stands on the floor (the tracked surface's lowest point "
                  f"within 10 cm across and nearer it than the other ankle, under 3 cm up): median {100 * np.median(rise):.1f} cm, p10 "
                  f"{100 * np.percentile(rise, 10):.1f}, p90 {100 * np.percentile(rise, 90):.1f} over {len(rise)} "
                  f"(frame, ankle) pairs (an ankle joint stands ~4.5 % of the height up: {4.5 * height:.1f} cm)")
        if err.get("helpers"):
            h = err["helpers"]
            print(f"  helper bones: {h['bones']} (free rigid bones under the template's; the template alone: LBS rms "
                  f"{1000 * h['rig_rmse']:.1f} mm over the segment, with them {1000 * h['rmse']:.1f})")
        rigs.append((sk, err))
        piv = np.einsum("jab,jb->ja", sk.rotations[0], sk.joints) + sk.translations[0]
        for j, p in enumerate(sk.parents):
            if p >= 0 and not is_helper(sk.names[j]):
                lengths.setdefault(sk.names[j], []).append(float(np.linalg.norm(piv[j] - piv[p])))
    print("bone lengths per segment, cm (the bone ending at the joint): " + ", ".join(
        f"{n} {'/'.join(f'{100 * x:.0f}' for x in v)}" for n, v in lengths.items() if len(v) > 1))
    print(f"graph run {wall:.0f} s (cached items are not recomputed); at the end:")
    print(describe())
    picture(rigs, a)


def planted_ankles(sk, seq) -> np.ndarray:
    """Heights (m) of the rig's posed ankles above the tracked surface's lowest point within 10 cm of them across and
    nearer them than the other ankle (the sole), over the (frame, ankle) pairs where that point lies under 3 cm above
    the floor (z = 0): a foot standing on the floor, whose ankle joint is a few centimetres up whatever the clothes."""
    J = {n: i for i, n in enumerate(sk.names)}
    by_frame = {int(m.metadata.get("frame", k)): m for k, m in enumerate(seq)}
    out = []
    for i, f in enumerate(sk.frames):
        piv = np.einsum("jab,jb->ja", sk.rotations[i], sk.joints) + sk.translations[i]
        V = np.asarray(by_frame[int(f)].vertices)
        for s, o in (("l", "r"), ("r", "l")):
            a, b = piv[J[f"ankle_{s}"]], piv[J[f"ankle_{o}"]]
            across = np.linalg.norm(V[:, :2] - a[:2], axis=1)
            near = (across < 0.10) & (across < np.linalg.norm(V[:, :2] - b[:2], axis=1))   # this foot, not the other
            if near.any() and V[near, 2].min() < 0.03:
                out.append(a[2] - V[near, 2].min())
    return np.asarray(out)


def picture(rigs, a):
    """The named joints (posed by skin's bone motions) over the silhouettes of 3 views at 4 frames."""
    import cv2

    from nodegraph.testing import run_node
    from render_skeletons import draw_sides

    frames = sorted({f for sk, _ in rigs for f in sk.frames})
    picks = [frames[int(round(x))] for x in np.linspace(0, len(frames) - 1, 4)]
    cams = None
    rows = []
    for f in picks:
        cap = run_node("capture", {}, {"path": str(Path(os.environ["VOLCAP_DATA"]) / "child_rope")}, frame=f)
        cams, masks = cap["cameras"], cap["masks"]
        sk, err = next((sk, e) for sk, e in rigs if f in sk.frames)
        i = list(sk.frames).index(f)
        piv = np.einsum("jab,jb->ja", sk.rotations[i], sk.joints) + sk.translations[i]
        own = [j for j, n in enumerate(sk.names) if not is_helper(n)]      # the template's joints (helpers are leaves)
        piv, parents, names = piv[own], [own.index(sk.parents[j]) if sk.parents[j] >= 0 else -1 for j in own], \
            [sk.names[j] for j in own]
        views = [0, len(cams.cameras) // 3, 2 * len(cams.cameras) // 3]
        tiles = []
        for v in views:
            m = np.asarray(masks.masks[v])
            img = np.dstack([(m > 0) * 90 + 40] * 3).astype(np.uint8)
            uv, _ = cams.project(piv, v)
            draw_sides(img, uv, parents, names, labelled=MARK)
            ys, xs = np.nonzero(m)
            lo = np.maximum([xs.min() - 60, ys.min() - 40], 0)
            hi = np.minimum([xs.max() + 60, ys.max() + 40], [m.shape[1], m.shape[0]])
            tile = img[lo[1]:hi[1], lo[0]:hi[0]]
            tile = cv2.resize(tile, (int(tile.shape[1] * 420 / tile.shape[0]), 420), interpolation=cv2.INTER_AREA)
            cv2.putText(tile, f"frame {f}, {cams.names[v]}: rms {1000 * err['timeline']['rmse'][i]:.1f} mm",
                        (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
            tiles.append(tile)
        rows.append(np.hstack(tiles))
    width = max(r.shape[1] for r in rows)
    sheet = np.vstack([np.pad(r, ((0, 4), (0, width - r.shape[1]), (0, 0))) for r in rows])
    for path in [ROOT / "out" / "skeleton_humanoid_child_rope.jpg"] + ([ROOT / "docs" / "skeleton_humanoid_child_rope.jpg"]
                                                                     if a.docs else []):
        path.parent.mkdir(exist_ok=True)
        cv2.imwrite(str(path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 80])
        print(path)


if __name__ == "__main__":
    main()
