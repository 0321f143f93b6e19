"""Atlas size against what the cameras hold (texel density): a graph's `texture` items run again at several atlas
sizes on the same meshes, photos and mattes, read from a finished run's cache (`volcap run GRAPH` first, same code);
per size: texels on the surface (mm per texel) next to the mattes' pixels in all views, the in-sample PSNR of the
textured mesh rendered into every camera against its photo (render and matte pixels; and on the sharpest fifth of
those by the photo's gradient, where a coarser atlas would blur first), and the node's seconds per frame on its reused
atlas, with their ratio to the last size's. Starts with the OpenCL device, the CPU and the load average.

    volcap run graphs/datasets/pose2sim_single_volumetric.yaml [--frames 0:23]
    python bench/texture_size.py graphs/datasets/pose2sim_single_volumetric.yaml [--frames 0:23] --sizes 1024,2048

Stop 52 (pose2sim_single, 2-core AMD EPYC): 1024 / 2048 texels per side, 22.955 / 22.962 dB in sample (10 frames),
19.709 / 19.735 on the sharpest fifth; frames 0, 11, 22 through the node 0.261 / 0.565 s (0.46x): the
graph takes 1024.
"""
from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from machine import describe, load_average  # noqa: E402


def item_inputs(graph, cache, node: str, frame: int):
    """The inputs of ``node``'s item at ``frame``: each value from the cache where the run kept it, else its item run
    again (in this process) from what was kept upstream."""
    from nodegraph.records import Join, resolve_type
    from nodegraph.run import plan_graph
    from nodegraph.worker import call_node

    items, _ = plan_graph(graph, cache)
    by_key = {it.key: it for it in items}
    log = logging.getLogger("bench.texture_size")
    memo = {}

    def value(r):
        if (r.key, r.port) not in memo:
            it = by_key[r.key]
            if r.port in (cache.stored(r.key) or set()):
                memo[(r.key, r.port)] = cache.load(r.key, r.port, graph.nodes[it.node].cls.outputs[r.port].type)
            else:
                out = call_node(graph.nodes[it.node].cls, inputs(it), it.params, frame=it.frame, frames=it.frames, log=log)
                memo.update({(r.key, p): v for p, (_, v) in out.items()})
        return memo[(r.key, r.port)]

    def inputs(it):
        return {p: None if r is None else [value(x) for x in r] if isinstance(r, list)
                else resolve_type(r.type).join([value(x) for x in r.refs]) if isinstance(r, Join) else value(r)
                for p, r in it.inputs.items()}

    found = [it for it in items if it.node == node and it.frame == frame]
    if not found:
        raise SystemExit(f"no item of node '{node}' at frame {frame} in {graph.path}")
    return inputs(found[0]), found[0].params


def sharp_pixels(photo: np.ndarray, sel: np.ndarray, share: float = 0.2) -> np.ndarray:
    """The ``share`` of ``sel``'s pixels where the photo's grey gradient is largest."""
    import cv2

    grey = cv2.cvtColor(np.ascontiguousarray(photo), cv2.COLOR_RGB2GRAY).astype(np.float32)
    g = np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1))
    return sel & (g >= np.percentile(g[sel], 100 * (1 - share)))


def main():
    from nodegraph.cache import Cache
    from nodegraph.graphfile import load_graph
    from nodes.common.meshops import face_areas
    from nodes.common.raster import render_texture
    from nodegraph.worker import call_node
    from nodes.common.gltf import texture_image
    from nodes.texture.reuse import BakeLayout
    from nodes.texture.texturing import Settings

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("graph")
    ap.add_argument("--cache", default=os.environ.get("VOLCAP_CACHE", ".volcap-cache"))
    ap.add_argument("--node", default="texture")
    ap.add_argument("--sizes", default="1024,2048")
    ap.add_argument("--frames", help="the run's frame range A:B, when it was not the graph's own")
    ap.add_argument("--every", type=int, default=11, help="every n-th frame of the range")
    args = ap.parse_args()
    print(describe())
    graph = load_graph(Path(args.graph), frames=args.frames)
    cache = Cache(Path(args.cache))
    sizes = [int(s) for s in args.sizes.split(",")]
    cls, log = graph.nodes[args.node].cls, logging.getLogger("bench.texture_size")
    frames = list(graph.frames)[::args.every]
    rows = {s: {"psnr": [], "sharp": [], "seconds": [], "mm": [], "texels": []} for s in sizes}
    pixels = []
    for fr in frames:
        inp, p = item_inputs(graph, cache, args.node, fr)
        mesh, imgs, cams, masks = inp["mesh"], inp["images"], inp["cameras"], inp["masks"]
        area = float(face_areas(mesh.vertices, mesh.faces).sum())
        pixels.append(sum(int((m > 127).sum()) for m in masks.masks))
        line = [f"frame {fr}: {pixels[-1]} matte pixels in {len(cams)} views, surface {area:.2f} m2"]
        for s in sizes:
            # the graph's own node at each size (its params otherwise): once to make the segment's atlas, then timed
            params = {**p, "size": s}
            call_node(cls, inp, params, frame=fr, frames=None, log=log)
            t = time.perf_counter()
            out = call_node(cls, inp, params, frame=fr, frames=None, log=log)
            rows[s]["seconds"].append(time.perf_counter() - t)
            atlas, texture = out["atlas"][1], texture_image(out["mesh"][1])
            texels = int(BakeLayout.of(atlas, max(1, Settings.gutter)).inner.sum())
            rows[s]["texels"].append(texels)
            rows[s]["mm"].append(1000 * np.sqrt(area / texels))
            d_all, d_sharp = [], []
            for v in range(len(cams)):
                rend, hit = render_texture(mesh.vertices, mesh.faces, atlas.uv01(), texture, cams, v)
                sel = hit & (masks.masks[v] > 127)
                photo = np.asarray(imgs.images[v])
                d_all.append(rend[sel].astype(np.float64) - photo[sel])
                sh = sharp_pixels(photo, sel)
                d_sharp.append(rend[sh].astype(np.float64) - photo[sh])
            for key, d in (("psnr", d_all), ("sharp", d_sharp)):
                d = np.concatenate(d)
                rows[s][key].append(10 * np.log10(255.0 ** 2 / max(float(np.mean(d * d)), 1e-12)))
            line.append(f"{s}: {texels} texels ({rows[s]['mm'][-1]:.2f} mm), {rows[s]['psnr'][-1]:.2f} dB, "
                        f"sharp {rows[s]['sharp'][-1]:.2f}, {rows[s]['seconds'][-1]:.3f} s")
        print("; ".join(line), flush=True)
    print(f"\n{len(frames)} frames, matte pixels (all views) median {int(np.median(pixels))}")
    base = sizes[-1]                                  # ratios to the last size listed (the former default: 2048)
    print(f"size  texels (median)  mm/texel  in sample dB (mean)  sharpest fifth dB  s/frame (median)  time / {base}'s")
    for s in sizes:
        r = rows[s]
        print(f"{s:5d}  {int(np.median(r['texels'])):14d}  {np.median(r['mm']):8.2f}  {np.mean(r['psnr']):19.3f}  "
              f"{np.mean(r['sharp']):17.3f}  {np.median(r['seconds']):16.3f}  "
              f"{np.median(r['seconds']) / np.median(rows[base]['seconds']):12.2f}")
    print(f"load average at the end: {load_average()}")


if __name__ == "__main__":
    main()
