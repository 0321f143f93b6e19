"""Corrective blend shapes (skeleton.export ``correctives``): how much of what linear blend skinning leaves of a
tracked sequence K shapes take back, and what they cost in file size and export time.

    python bench/correctives.py [--frames 24]                 # the synthetic walk: the demo's two rigs
    python bench/correctives.py child_rope [--cache DIR] [--range 0:200] [--k 0,8,16,32]

synth: the walking figure's meshes (one connectivity), rigged as the demo rigs them: the character
(skeletonize.humanoid -> skin, joints kept, bound in a T pose) and the free rig (skeletonize.sequence -> skin).
child_rope: graphs/skeleton/child_rope_humanoid.yaml through the engine up to its skins (every tracked segment of
the frames given, as the graph rigs them; the first run reconstructs and tracks them). For K = ``--k`` and the frame
count:
the LBS error per frame of the glTF (rms and max, mm: median and worst frame) as the export reports it, the frames
within the goal (1 % / 5 % of the height; for 0 < K < frames fitted towards it, skeleton.export's default, and by
least squares alone, its ``goal: [0, 0]``), the
worst per-frame max measured again by skinning the written GLB (formats.read_gltf: morph targets, then joints),
the GLB and USD sizes and the export's seconds.
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

from machine import describe, load_average  # noqa: E402
from nodegraph.testing import run_node  # noqa: E402
from nodes.skeleton.humanoid import body_stature  # noqa: E402


def table(label, sk, rest, meshes, frames, ks=(0, 4, 8, 16)):
    from nodes.skeleton import formats

    tracked = np.stack([np.asarray(m.vertices) for m in meshes])
    print(f"\n{label}: {len(frames)} frames, {len(rest.vertices)} vertices, {len(sk.parents)} joints")
    height = body_stature(tracked)                              # as skeleton.export measures it
    print(f"goal (skeleton.export's default): rms <= {10 * height:.1f} mm, max <= {50 * height:.1f} mm per frame (1 % / 5 % "
          f"of the height, {height:.3f} m); fit 'goal' = towards it, 'lsq' = least squares alone (goal: [0, 0])")
    print(f"{'K':>4} {'fit':>4} {'rms med':>8} {'rms worst':>9} {'max med':>8} {'max worst':>9} {'within':>7} {'GLB max':>8} "
          f"{'GLB KB':>8} {'USD KB':>8} {'export s':>8}")
    for k in sorted({*ks, len(frames)}):
        if k > len(frames):
            continue
        for fit, goal in (("goal", [0.01, 0.05]), ("lsq", [0.0, 0.0])) if 0 < k < len(frames) else (("", [0.01, 0.05]),):
            t0 = time.perf_counter()
            out = run_node("skeleton.export", {"skeleton": sk, "rest": rest, "meshes": meshes},
                           {"name": "rig", "correctives": k, "goal": goal}, frames=frames)
            secs = time.perf_counter() - t0
            t = out["report"]["files"]["rig.glb"]
            rms, mx = 1000 * np.array(t["corrected_rms"]), 1000 * np.array(t["corrected_max"])
            inside = int(np.sum((rms <= 10 * height) & (mx <= 50 * height)))
            back = formats.read_gltf(out["files"]["rig.glb"])["skinned"][:len(frames)]
            glb_max = 1000 * np.linalg.norm(back - tracked, axis=2).max()
            print(f"{k:>4} {fit:>4} {np.median(rms):8.3f} {rms.max():9.3f} {np.median(mx):8.3f} {mx.max():9.3f} "
                  f"{inside:>3}/{len(rms):<3} {glb_max:8.3f} {len(out['files']['rig.glb']) / 1024:8.0f} "
                  f"{len(out['files']['rig.usd']) / 1024:8.0f} {secs:8.2f}")


def synth(a):
    from nodes.synth import scenes

    frames = list(range(a.frames))
    meshes = [scenes.build("figure", f).mesh for f in frames]
    h = run_node("skeletonize.humanoid", {"meshes": meshes}, {"resolution": 96, "hand": 0, "foot": 0.08}, frames=frames)
    c = run_node("skin", {"meshes": meshes, "skeleton": h["skeleton"]}, {"pivots": False, "rest_pose": "T"},
                 frames=frames)
    table("synth walk, the character (humanoid, T pose)", c["skeleton"], c["rest"], meshes, frames)
    s = run_node("skeletonize.sequence", {"meshes": meshes}, {}, frames=frames)
    f = run_node("skin", {"meshes": meshes, "skeleton": s["skeleton"]}, {}, frames=frames)
    table("synth walk, the free rig (skeletonize.sequence)", f["skeleton"], f["rest"], meshes, frames)


def child_rope(a):
    from nodes.common import types as T
    from track import outputs, run

    os.environ.setdefault("VOLCAP_DATA", str(ROOT.parent / "shared" / "data"))
    graph = ROOT / "graphs" / "skeleton" / "child_rope_humanoid.yaml"
    ks = [int(k) for k in a.k.split(",")]
    for s in range(3):
        try:
            records = run(graph, a.cache, a.range, upto=f"skin_{s}")
        except SystemExit as e:          # fewer segments in this tracking
            print(f"segment {s}: {e}")
            break
        seq = outputs(records, "track", "sequence", T.MeshSequence)[0][0]
        [sk], _ = outputs(records, f"skin_{s}", "skeleton", T.Skeleton)
        [rest], _ = outputs(records, f"skin_{s}", "rest", T.Mesh)
        by_frame = {int(m.metadata.get("frame", i)): m for i, m in enumerate(seq)}
        frames = list(sk.frames)
        table(f"child_rope segment {s}, frames {frames[0]}..{frames[-1]} (character, T pose)", sk, rest,
              [by_frame[f] for f in frames], frames, ks)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", nargs="?", default="synth", choices=("synth", "child_rope"))
    ap.add_argument("--frames", type=int, default=24, help="synth: frames of the walk")
    ap.add_argument("--range", default="0:200", help="child_rope: the frames to reconstruct and track")
    ap.add_argument("--k", default="0,8,16,32", help="child_rope: corrective shape counts (and the frame count)")
    ap.add_argument("--cache", type=Path, default=ROOT / ".volcap-cache")
    a = ap.parse_args()
    print(describe())
    synth(a) if a.scene == "synth" else child_rope(a)
    print(f"load average at the end: {load_average()}")


if __name__ == "__main__":
    main()
