"""The named humanoid template (skeleton.humanoid) on the synthetic walking figure, against the free curve
skeleton (skeletonize: TEASAR joint tree, five named extremities) the user would otherwise start from, same
voxel resolution, same run: seconds per frame, and the template's joint errors against the figure's true joints
(median, 90th percentile, max; sides checked by name), over a walk cycle.

    python bench/humanoid.py [--frames 24] [--resolution 96]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from machine import describe, load_average  # noqa: E402
from nodegraph.testing import run_node  # noqa: E402
from nodes.synth import scenes  # noqa: E402

TRUTH = {"pelvis": "pelvis", "chest": "chest", "neck": "neck", "head": "head", "shoulder_{s}": "{s}_shoulder",
         "elbow_{s}": "{s}_elbow", "wrist_{s}": "{s}_wrist", "hip_{s}": "{s}_hip", "knee_{s}": "{s}_knee",
         "ankle_{s}": "{s}_ankle"}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--resolution", type=int, default=96)
    a = ap.parse_args()
    print(describe())
    t_h, t_s, err, per_joint = [], [], [], {}
    for f in range(a.frames):
        scene = scenes.build("figure", f)
        t0 = time.perf_counter()
        sk = run_node("skeleton.humanoid", {"mesh": scene.mesh}, {"resolution": a.resolution})["skeleton"]
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
    print(f"load average at the end: {load_average()}")


if __name__ == "__main__":
    main()
