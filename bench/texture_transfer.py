"""The stream's lower rung painted two ways, same frames, same run: `texture` from the photos (what the demo did
before) and `texture.transfer` from the full rung's textured mesh. Seconds per frame (the atlas reused: a
segment's frames after its first), and how each looks: rendered into every camera, PSNR against the photo inside
the key's mask and the render, and against the full rung's own render (how far the rung's colours are from the
full stream's).

    python3 bench/texture_transfer.py [--frames 0:4] [--cache DIR] [--cameras 12 --width 640 --height 480]

Runs graphs/demo.yaml through the CLI into the cache (every output kept), then both nodes in this process on the
cached values (nodegraph.testing.run_node). Prints the OpenCL device, the CPU and the load average.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "bench")]

from machine import describe, load_average  # noqa: E402


def psnr(a, b, sel):
    if not np.any(sel):
        return float("nan")
    d = a[sel].astype(np.float64) - b[sel].astype(np.float64)
    return 10 * np.log10(255.0 ** 2 / max(float(np.mean(d * d)), 1e-12))


def render(mesh, cameras, view):
    from nodes.common.raster import render_texture

    uv = np.asarray(mesh.visual.uv)[np.asarray(mesh.faces)]
    tex = np.asarray(mesh.visual.material.baseColorTexture.convert("RGB"))
    return render_texture(np.asarray(mesh.vertices), np.asarray(mesh.faces), uv, tex, cameras, view)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", default="0:4")
    ap.add_argument("--cache", default=str(ROOT / ".volcap-cache" / "bench_transfer"))
    ap.add_argument("--cameras", type=int, default=12)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    print(describe())
    out = Path(args.cache) / "out"
    sets = [f"stage.cameras={args.cameras}", f"stage.width={args.width}", f"stage.height={args.height}"]
    cmd = [sys.executable, str(ROOT / "app.py"), "--cache", args.cache, "run", str(ROOT / "graphs/demo.yaml"), "--keep-all",
           "--frames", args.frames, "--out", str(out), "-q", "-j", "1"] + [x for s in sets for x in ("--set", s)]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)

    from nodegraph.cache import Cache
    from nodegraph.node import node_class
    from nodegraph.testing import run_node

    cache = Cache(args.cache)
    records = json.loads((out / "run.json").read_text())["items"]

    def value(node, port, frame):
        [r] = [r for r in records if r["node"] == node and r["frame"] in (frame, None)]
        return cache.load(r["key"], port, node_class(r["type"]).outputs[port].type)

    frames = sorted({r["frame"] for r in records if r["node"] == "texture_low"})
    from nodegraph.graphfile import load_graph

    tsize = int(load_graph(ROOT / "graphs/demo.yaml").nodes["texture_low"].params["size"])
    rows = {"texture (photos)": [], "texture.transfer": []}
    times = {k: [] for k in rows}
    for f in frames:
        low, key = value("tracked_low", "mesh", f), value("tracked_low", "keyframe", f)
        full = value("texture", "mesh", f)
        images, cameras, masks = value("key", "images", f), value("stage", "cameras", f), value("clean", "masks", f)
        runs = {
            "texture (photos)": lambda: run_node("texture", {"mesh": low, "reference": key, "images": images,
                                                             "cameras": cameras, "masks": masks}, {"size": tsize}),
            "texture.transfer": lambda: run_node("texture.transfer", {"mesh": low, "reference": key, "source": full},
                                                 {"size": tsize}),
        }
        for name, fn in runs.items():
            fn()                                            # the segment's atlas and layout made once, as per frame
            ts = []
            for _ in range(args.repeat):
                t = time.perf_counter()
                got = fn()["mesh"]
                ts.append(time.perf_counter() - t)
            times[name].append(min(ts))
            for v in range(len(cameras)):
                rgb, hit = render(got, cameras, v)
                ref, ref_hit = render(full, cameras, v)
                sel = hit & (masks.masks[v] > 127)
                rows[name].append((psnr(rgb, images.images[v], sel), psnr(rgb, ref, sel & ref_hit)))
        print(f"  frame {f}: " + ", ".join(f"{k} {times[k][-1]:.3f} s" for k in rows) + f"; load {load_average()}", flush=True)
    print(f"\nquarter rung ({len(low.faces)} faces, {tsize}² atlas), {len(frames)} frames x {len(cameras)} cameras "
          f"{args.width}x{args.height}, atlas reused (best of {args.repeat} per frame)")
    print(f"{'method':22s} {'s/frame':>8s} {'PSNR vs photo':>14s} {'worst view':>11s} {'PSNR vs full rung':>18s}")
    for name, r in rows.items():
        a = np.array(r)
        print(f"{name:22s} {np.median(times[name]):8.3f} {np.median(a[:, 0]):14.2f} {a[:, 0].min():11.2f} {np.median(a[:, 1]):18.2f}")
    full_psnr = []
    for f in frames:
        full = value("texture", "mesh", f)
        images, cameras, masks = value("key", "images", f), value("stage", "cameras", f), value("clean", "masks", f)
        for v in range(len(cameras)):
            rgb, hit = render(full, cameras, v)
            full_psnr.append(psnr(rgb, images.images[v], hit & (masks.masks[v] > 127)))
    print(f"{'full rung (reference)':22s} {'':8s} {np.median(full_psnr):14.2f} {min(full_psnr):11.2f}")
    print(f"load average at the end: {load_average()}")


if __name__ == "__main__":
    main()
