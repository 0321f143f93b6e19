"""End-to-end speed of the per-frame core, key.chroma -> hull -> mc, on 24 cameras of 1920x1080.

    python bench/e2e.py [--frames 20] [--cameras 24] [--resolution 128]

One frame of the synthetic stage (walking figure, green screen, ring rig) is rendered once with the synth
node, outside the timed loop; then the same frame is processed again and again, calling the stages'
functions directly (not the YAML engine, whose PNG caching of every output is not the point here):
  key    nodes.key.chroma_key_cl per view, the path key.chroma takes with key_color given and spill 0
         (matte only, no despill), garbage matte from the capture box's projection (computed per frame, as
         the node does); the alpha goes to the hull as it is: the hull's inside test (value > 127) is the
         node's mask (alpha >= 128), checked below
  hull   nodes.hull.visual_hull, sparse coarse-to-fine, a cube around the synth bounds (RESOLUTION^3)
  mc     nodes.mc.marching_cubes (OpenCL)
Prints ms per stage (median and min over the frames) and frames/s, next to the industrial reference of
25 frames/s (REFERENCES.md: Ladikos et al. 2008 reach 30 frames/s for 16 cameras on a GPU).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from nodegraph import clrt  # noqa: E402
from nodegraph.testing import run_node  # noqa: E402
from nodegraph.types import MaskSet  # noqa: E402
from nodes import key as K  # noqa: E402
from nodes.hull import visual_hull  # noqa: E402
from nodes.mc import marching_cubes  # noqa: E402
from nodes.synth import GREEN  # noqa: E402

REFERENCE_FPS = 25.0


def cube_around(bounds: np.ndarray) -> np.ndarray:
    """The smallest cube with the same centre that holds ``bounds`` (2, 3): RESOLUTION^3 voxels."""
    centre, half = bounds.mean(0), (bounds[1] - bounds[0]).max() / 2
    return np.array([centre - half, centre + half])


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=20, help="timed repetitions of the frame")
    ap.add_argument("--cameras", type=int, default=24)
    ap.add_argument("--resolution", type=int, default=128)
    args = ap.parse_args()

    t = time.perf_counter()
    stage = run_node("synth", {}, {"scene": "figure", "rig": "ring", "cameras": args.cameras, "width": 1920,
                                   "height": 1080, "background": "green", "shadow": True})
    render_s = time.perf_counter() - t
    images, cams, bounds = stage["images"].images, stage["cameras"], stage["bounds"]
    box = cube_around(bounds)
    key = K.key_direction_from_rgb([round(255 * c) for c in GREEN])

    def key_stage():
        alphas = []
        for v, im in enumerate(images):
            edges = K.matte_edges(cams, v, bounds)
            alpha, _ = K.chroma_key_cl(im, key, edges=edges, despill=False)
            alphas.append(alpha)
        return MaskSet(alphas, names=cams.names)

    def hull_stage(masks):
        return visual_hull(masks, cams, box, args.resolution, method="sparse")

    def mc_stage(volume):
        return marching_cubes(volume)

    # warm-up (kernel builds, buffers) and the checks, outside the timed loop
    masks = key_stage()
    volume = hull_stage(masks)
    verts, faces = mc_stage(volume)
    node_masks = run_node("key.chroma", {"images": stage["images"], "cameras": cams, "bounds": bounds},
                          {"key_color": [round(255 * c) for c in GREEN], "spill": 0.0})["masks"]
    same_hull = np.array_equal(hull_stage(node_masks).occupancy, volume.occupancy)
    truth = stage["masks"].masks
    iou = [np.logical_and(a >= 128, t > 127).sum() / np.logical_or(a >= 128, t > 127).sum()
           for a, t in zip(masks.masks, truth)]

    times = {"key": [], "hull": [], "mc": [], "frame": []}
    for _ in range(args.frames):
        t0 = time.perf_counter()
        masks = key_stage()
        t1 = time.perf_counter()
        volume = hull_stage(masks)
        t2 = time.perf_counter()
        mc_stage(volume)
        t3 = time.perf_counter()
        for name, dt in (("key", t1 - t0), ("hull", t2 - t1), ("mc", t3 - t2), ("frame", t3 - t0)):
            times[name].append(1e3 * dt)

    print(f"OpenCL device: {clrt.device_name()}")
    print(f"synth render (once, not timed below): {args.cameras} x 1920x1080 in {render_s:.1f} s")
    print(f"functions called directly, not through the YAML engine (no PNG cache); {args.frames} frames")
    print(f"key: mean IoU vs the true silhouettes {np.mean(iou):.4f} (min {np.min(iou):.4f}); "
          f"hull from the alpha == hull from the node's masks: {same_hull}")
    print(f"hull: {'x'.join(map(str, volume.occupancy.shape))} voxels, {int(volume.occupancy.sum())} inside; "
          f"mc: {len(verts)} vertices, {len(faces)} faces")
    print(f"{'stage':>8} {'median ms':>10} {'min ms':>8}")
    for name in ("key", "hull", "mc", "frame"):
        print(f"{name:>8} {np.median(times[name]):10.1f} {np.min(times[name]):8.1f}")
    fps = 1e3 / np.median(times["frame"])
    print(f"frames/s: {fps:.1f} (median; best frame {1e3 / np.min(times['frame']):.1f}); industrial reference "
          f"{REFERENCE_FPS:.0f} frames/s: {'met' if fps >= REFERENCE_FPS else 'not met'}")


if __name__ == "__main__":
    main()
