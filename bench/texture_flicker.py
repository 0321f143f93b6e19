"""Texture flicker on a sequence with known albedo: how much the same texels (one atlas per tracked segment)
change from frame to frame beyond what the lit surface itself does (nodes.texture.quality.flicker).

    python3 bench/texture_flicker.py [--frames 8] [--size 1024] [--samples 40000]

The walking synthetic figure (12 cameras 640x480, green screen) through the product's path: a graph run by the
CLI (key -> hull -> mc -> refine -> relax -> track -> track.frame -> texture on the segment's atlas); the
texture node's own output per frame is scored. Each sampled texel's surface point on the tracked mesh is taken
to the true surface of that frame (closest point) for the truth: the pattern as the renderer lit it. Texels
within 1 cm of a pattern edge in any frame are counted apart ("all" vs "interior"): there a texel's sampling
position moves against a hard edge of the un-antialiased photos, whatever the texturing does.

Same run, in process, on the same tracked meshes and photos (and on the true meshes: no tracking drift), through
the node's own code (texturing.texture_mesh) with two of its steps wrapped (Variant):
  node defaults          what the texture node does (per frame, independently)
  gains fixed            the first frame's per-camera gains kept for every later frame
  selection prior l      the view selection's data cost + l where a face's view is not the one it had in the
                         previous frame (a texel keeps its camera without cause to switch)
Camera switches: the share of faces whose selected view differs from the previous frame.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from nodes.common.types import CameraSet, Images, Masks, Mesh  # noqa: E402
from nodes.synth import scenes  # noqa: E402
from nodes.synth.render import surface_truth  # noqa: E402
from nodes.texture import texturing as T  # noqa: E402
from nodes.texture import views as V  # noqa: E402
from nodes.texture.nodes import AtlasType  # noqa: E402
from nodes.texture.quality import flicker  # noqa: E402
from nodes.texture.reuse import BakeLayout, reference_atlas  # noqa: E402

GRAPH = """\
frames: 0:{frames}
nodes:
  stage:   {{type: synth, params: {{scene: figure, rig: ring, cameras: 12, width: 640, height: 480, background: green, shadow: true}}}}
  key:     {{type: key.chroma, in: {{images: stage.images, cameras: stage.cameras, bounds: stage.bounds}}}}
  clean:   {{type: key.cleanup, in: {{masks: key.masks}}}}
  hull:    {{type: hull, in: {{masks: clean.masks, cameras: stage.cameras, bounds: stage.bounds}}, params: {{resolution: 128}}}}
  mesh:    {{type: mc, in: {{volume: hull.volume}}, params: {{largest: true}}}}
  refine:  {{type: refine, in: {{mesh: mesh.mesh, volume: hull.volume, masks: clean.masks, cameras: stage.cameras}}}}
  relax:   {{type: relax, in: {{mesh: refine.mesh, masks: clean.masks, cameras: stage.cameras}}}}
  track:   {{type: track, in: {{meshes: relax.mesh}}}}
  tracked: {{type: track.frame, in: {{sequence: track.sequence}}}}
  texture: {{type: texture, in: {{mesh: tracked.mesh, reference: tracked.keyframe, images: key.images, cameras: stage.cameras, masks: clean.masks}}, params: {{size: {size}}}}}
"""


def run_graph(folder: Path, frames: int, size: int) -> dict:
    g = folder / "flicker.yaml"
    g.write_text(GRAPH.format(frames=frames, size=size))
    out = folder / "out"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, str(ROOT / "app.py"), "run", str(g), "--out", str(out), "--cache",
                        str(folder / "cache"), "--jobs", "1", "--keep-all", "--quiet"], env=env, capture_output=True,
                       text=True)
    if r.returncode != 0:
        raise RuntimeError(f"the graph failed: {r.stdout[-800:]} {r.stderr[-800:]}")
    recs = {}
    for rec in json.loads((out / "run.json").read_text())["items"]:
        if rec.get("cache_dir"):
            recs[(rec["node"], rec.get("frame"))] = Path(rec["cache_dir"])
    return recs


class Variant:
    """The texture node's own path (texturing.texture_mesh, kernels and all) with the bench's options, applied
    around two of its steps: ``fixed_gains`` keeps the first frame's camera_gains; ``prior`` > 0 adds ``prior``
    to the face_cost kernel's cost of every view but the one a face had in the previous frame (the labels of the
    last result), before the ICM."""

    def __init__(self, prior: float, fixed_gains: bool):
        self.prior, self.fixed, self.gains, self.labels = prior, fixed_gains, None, None

    def __enter__(self):
        self._gains, self._cost = V.camera_gains, V.data_cost_cl

        def gains(*a, **k):
            g = self._gains(*a, **k)
            if self.fixed:
                self.gains = g if self.gains is None else self.gains
                return self.gains
            return g

        def cost(stats, *a, **k):
            import pyopencl as cl

            d_cost, spread, d_best = self._cost(stats, *a, **k)
            nv, nf = stats.quality.shape
            prev = self.labels
            if self.prior > 0 and prev is not None and len(prev) == nf:
                q = V.TextureCL.get().queue
                c = np.empty((nf, nv), np.float32)
                cl.enqueue_copy(q, c, d_cost, is_blocking=True)
                seen = c < V.INVISIBLE
                pen = np.where(prev[:, None] >= 0, np.float32(self.prior), np.float32(0.0)) * seen
                pen[np.flatnonzero(prev >= 0), prev[prev >= 0]] = 0.0
                c += pen
                best = np.where(seen.any(axis=1), np.argmin(c, axis=1), -1).astype(np.int32)
                cl.enqueue_copy(q, d_cost, c)
                cl.enqueue_copy(q, d_best, best, is_blocking=True)
            return d_cost, spread, d_best

        V.camera_gains, V.data_cost_cl = gains, cost
        return self

    def __exit__(self, *exc):
        V.camera_gains, V.data_cost_cl = self._gains, self._cost


def truth_of(points, frames):
    """Per frame the sampled texels' true colours (T, N, 3) and which texels stay 1 cm from pattern edges."""
    truth, dist = [], []
    for t, p in enumerate(points):
        a, d = surface_truth(scenes.build("figure", frames[t]), p)
        truth.append(a)
        dist.append(d)
    return np.stack(truth), np.min(np.stack(dist), axis=0) > 0.01


def score(textures, truth, interior, layout, sel):
    """flicker over all sampled texels and over pattern-interior ones; textures (T, S, S, 3)."""
    cols = np.stack([tex.reshape(-1, 3)[layout.texel[sel]].astype(np.float64) for tex in textures])
    return flicker(cols, truth), flicker(cols, truth, interior), float(interior.mean())


def switches(labels):
    return float(np.mean([np.mean(a != b) for a, b in zip(labels, labels[1:])]))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--samples", type=int, default=40000)
    args = ap.parse_args()
    from machine import describe, load_average

    print(describe())
    frames = list(range(args.frames))
    with tempfile.TemporaryDirectory() as d:
        recs = run_graph(Path(d), args.frames, args.size)
        meshes = [Mesh.load(recs[("tracked", f)] / "mesh") for f in frames]
        images = [Images.load(recs[("key", f)] / "images").images for f in frames]
        masks = [Masks.load(recs[("clean", f)] / "masks").masks for f in frames]
        cams = [CameraSet.load(recs[("stage", f)] / "cameras") for f in frames]
        atlas = AtlasType.load(recs[("texture", frames[0])] / "atlas")
        node_tex = []
        for f in frames:
            with np.load(recs[("texture", f)] / "mesh" / "mesh.npz") as z:
                node_tex.append(z["texture"])
        def sampled(atl):
            lay = BakeLayout.of(atl, 2)
            texels = np.flatnonzero(lay.inner)
            return lay, np.random.default_rng(0).choice(texels, min(args.samples, len(texels)), replace=False)

        def points(ms, lay, sel):
            return [np.einsum("nk,nkc->nc", lay.bary[sel], np.asarray(m.vertices)[np.asarray(m.faces)[lay.face[sel]]])
                    for m in ms]

        rows = []
        layout, sel = sampled(atlas)
        truth, interior = truth_of(points(meshes, layout, sel), frames)
        a, i, share = score(node_tex, truth, interior, layout, sel)
        rows.append(("tracked meshes", "texture node (CLI output)", a, i, share, None))
        true_meshes = [scenes.build("figure", f).mesh for f in frames]
        true_atlas = reference_atlas(true_meshes[0].vertices, true_meshes[0].faces, args.size, 6)
        for geometry, ms, atl in (("tracked meshes", meshes, atlas), ("true meshes", true_meshes, true_atlas)):
            layout, sel = sampled(atl)
            truth, interior = truth_of(points(ms, layout, sel), frames)
            for label, prior, fixed in (("node defaults", 0.0, False), ("gains fixed", 0.0, True),
                                        ("selection prior 0.3", 0.3, False), ("selection prior 1.0", 1.0, False),
                                        ("prior 0.3 + gains fixed", 0.3, True)):
                texs, labels = [], []
                with Variant(prior, fixed) as var:
                    for k, m in enumerate(ms):
                        r = T.texture_mesh(m.vertices, m.faces, images[k], masks[k], cams[k],
                                           T.Settings(size=args.size, margin=2, edge_px=2), atlas=atl)
                        texs.append(r.texture)
                        labels.append(r.labels)
                        var.labels = r.labels
                a, i, share = score(texs, truth, interior, layout, sel)
                rows.append((geometry, label, a, i, share, switches(labels)))
                print(f"  {geometry}, {label}: flicker {a['flicker']:.3f} (interior {i['flicker']:.3f})", flush=True)
    print("\n" + describe())
    print(f"texture flicker, synthetic figure walking, frames 0:{args.frames}, {args.size}² atlas, {args.samples} texels "
          f"sampled; 0..255 mean over RGB; load {load_average()}")
    print("| geometry | texturing | flicker, all | interior (share) | texel change (truth's) | camera switches |")
    print("|---|---|---|---|---|---|")
    for geometry, label, a, i, share, sw in rows:
        print(f"| {geometry} | {label} | {a['flicker']:.3f} | {i['flicker']:.3f} ({share * 100:.0f} %) | "
              f"{a['change']:.2f} ({a['truth_change']:.2f}) | {'-' if sw is None else f'{sw * 100:.1f} %'} |")


if __name__ == "__main__":
    main()
