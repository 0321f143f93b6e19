"""End-to-end speed of the per-frame core, key.chroma -> hull -> mc, on 24 cameras of 1920x1080.

    python bench/e2e.py [--frames 20] [--cameras 24] [--resolution 128]

One frame of the synthetic stage (walking figure, green screen, ring rig) is rendered once with the synth
node, outside the timed loop; then the same frame is processed again and again, calling the stages'
functions directly (not the YAML engine, whose PNG caching of every output is not the point here).
Two paths, each timed per stage:
  fused    (device-resident, the fast path)
    matte  nodes.key.matte_edges per view: the garbage matte from the capture box's projection, computed per
           frame as the key.chroma node does (a fixed rig could compute it once)
    key    nodes.key.chroma_key_bits: chroma key (key_color given, no despill) straight into the hull's
           device silhouettes (bits + 8x8 block tables); no alpha, no read-back, no re-packing
    hull   nodes.hull.visual_hull on those SilhouetteBits: sparse coarse-to-fine, a cube around the synth
           bounds (RESOLUTION^3), occupancy read back
    mc     nodes.mc.marching_cubes (OpenCL)
  alpha    (the path the key.chroma and hull nodes take, for comparison): chroma_key_cl per view -> 8-bit
           alpha read back -> the hull packs it and builds the tables -> mc
Checks printed first: the fused silhouettes equal the key.chroma node's masks and give the same hull.
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
from nodes.common.types import MaskSet  # noqa: E402
from nodes.key import keying as K  # noqa: E402
from nodes.hull.hull import visual_hull  # noqa: E402
from nodes.mesh.mc import marching_cubes  # noqa: E402
from nodes.synth.render import GREEN  # noqa: E402

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

    def matte_stage():
        return [K.matte_edges(cams, v, bounds) for v in range(len(images))]

    def key_stage(edges, out=None):  # fused: device silhouettes
        return K.chroma_key_bits(images, key, edges=edges, out=out)

    def key_alpha_stage(edges):  # the nodes' path: 8-bit alpha on the host
        alphas = [K.chroma_key_cl(im, key, edges=e, despill=False)[0] for im, e in zip(images, edges)]
        return MaskSet(alphas, names=cams.names)

    def hull_stage(masks):
        return visual_hull(masks, cams, box, args.resolution, method="sparse")

    def mc_stage(volume):
        return marching_cubes(volume)

    # warm-up (kernel builds, buffers) and the checks, outside the timed loop
    edges = matte_stage()
    sil = key_stage(edges)
    volume = hull_stage(sil)
    verts, faces = mc_stage(volume)
    node_masks = run_node("key.chroma", {"images": stage["images"], "cameras": cams, "bounds": bounds},
                          {"key_color": [round(255 * c) for c in GREEN], "spill": 0.0})["masks"]
    same_masks = all(np.array_equal(a, b) for a, b in zip(sil.masks(), node_masks.masks))
    same_hull = np.array_equal(hull_stage(node_masks).occupancy, volume.occupancy)
    alpha_masks = key_alpha_stage(edges)
    same_alpha_hull = np.array_equal(hull_stage(alpha_masks).occupancy, volume.occupancy)
    truth = stage["masks"].masks
    iou = [np.logical_and(a > 0, t > 127).sum() / np.logical_or(a > 0, t > 127).sum()
           for a, t in zip(sil.masks(), truth)]

    stages = ("matte", "key", "hull", "mc", "frame")
    def timed_frames(key) -> dict:
        """ms per stage over args.frames frames, with ``key(edges)`` producing what the hull consumes."""
        times = {name: [] for name in stages}
        for _ in range(args.frames):
            t0 = time.perf_counter()
            edges = matte_stage()
            t1 = time.perf_counter()
            silhouettes = key(edges)
            t2 = time.perf_counter()
            volume = hull_stage(silhouettes)
            t3 = time.perf_counter()
            mc_stage(volume)
            t4 = time.perf_counter()
            for name, dt in zip(stages, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t4 - t0)):
                times[name].append(1e3 * dt)
        return times

    fused = timed_frames(lambda edges: key_stage(edges, out=sil))
    alpha = timed_frames(key_alpha_stage)

    print(f"OpenCL device: {clrt.device_name()}")
    print(f"synth render (once, not timed below): {args.cameras} x 1920x1080 in {render_s:.1f} s")
    print(f"functions called directly, not through the YAML engine (no PNG cache); {args.frames} frames per path")
    print(f"key: mean IoU vs the true silhouettes {np.mean(iou):.4f} (min {np.min(iou):.4f}); fused silhouettes == "
          f"key.chroma node masks: {same_masks}; hull from them == hull from the node's masks: {same_hull}, "
          f"== hull from the alpha path: {same_alpha_hull}")
    print(f"hull: {'x'.join(map(str, volume.occupancy.shape))} voxels, {int(volume.occupancy.sum())} inside; "
          f"mc: {len(verts)} vertices, {len(faces)} faces")
    print(f"{'':>8} {'fused (device bits)':>20} {'alpha (node path)':>20}")
    print(f"{'stage':>8} {'median ms':>10} {'min ms':>9} {'median ms':>10} {'min ms':>9}")
    for name in stages:
        print(f"{name:>8} {np.median(fused[name]):10.1f} {np.min(fused[name]):9.1f} "
              f"{np.median(alpha[name]):10.1f} {np.min(alpha[name]):9.1f}")
    budget = 1e3 / REFERENCE_FPS
    for label, times in (("fused", fused), ("alpha", alpha)):
        median = np.median(times["frame"])
        verdict = "met" if median <= budget else f"not met: {median / budget:.1f}x the {budget:.0f} ms budget"
        print(f"{label}: {1e3 / median:.1f} frames/s (median; best frame {1e3 / np.min(times['frame']):.1f}); "
              f"industrial reference {REFERENCE_FPS:.0f} frames/s (<= {budget:.0f} ms per frame): {verdict}")

if __name__ == "__main__":
    main()
