"""On-disk forms for full-resolution images in the cache: write and read seconds per frame of 24 x 1920x1080 RGB
images (a synthetic green-screen frame rendered by the synth node), and the bytes, for PNG (OpenCV, level 1),
raw .npy (read by memory map: np.load's, and the cache's own reader ``nodes.common.types._load_array``, which maps
the file without np.memmap), .npy compressed with LZ4 and with zstd (level 1), and .npz (zip deflate). Then
a tracked take's ``MeshSequence`` as every per-frame reader of it (``track.frame``) loads it: its stored arrays,
against the segments' PLYs for the faces (how it was read before stop 51, still the route for older entries).
Prints the machine (CPU, load average, OpenCL device unused here) and the tables.

    python bench/formats.py [--cameras 24] [--repeats 3] [--segments 13]
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from machine import describe, load_average  # noqa: E402


def formats():
    import cv2

    def png_w(p, im):
        cv2.imwrite(str(p) + ".png", im, [cv2.IMWRITE_PNG_COMPRESSION, 1])

    def png_r(p):
        return cv2.imread(str(p) + ".png", cv2.IMREAD_COLOR)

    def npy_w(p, im):
        np.save(str(p) + ".npy", im)

    def npy_r(p):
        return np.load(str(p) + ".npy", mmap_mode="r")

    def npy_cache(p):                     # the product's reader: the same read-only array
        from nodes.common.types import _load_array

        return _load_array(Path(str(p) + ".npy"))

    def npy_read_all(p):
        return np.array(np.load(str(p) + ".npy", mmap_mode="r"))   # a copy: every page read (ascontiguousarray of
                                                                   # a contiguous map is the map itself)

    out = {}
    try:
        import lz4.frame

        def lz4_w(p, im):
            Path(str(p) + ".lz4").write_bytes(lz4.frame.compress(im.tobytes(), compression_level=0))

        def lz4_r(p):
            return np.frombuffer(lz4.frame.decompress(Path(str(p) + ".lz4").read_bytes()), np.uint8)

        out["npy + lz4"] = (lz4_w, lz4_r, ".lz4")
    except ImportError:
        print("(lz4 not installed: its row left out)")
    try:
        import zstandard

        zc, zd = zstandard.ZstdCompressor(level=1, threads=0), zstandard.ZstdDecompressor()

        def zst_w(p, im):
            Path(str(p) + ".zst").write_bytes(zc.compress(im.tobytes()))

        def zst_r(p):
            return np.frombuffer(zd.decompress(Path(str(p) + ".zst").read_bytes()), np.uint8)

        out["npy + zstd 1"] = (zst_w, zst_r, ".zst")
    except ImportError:
        print("(zstandard not installed: its row left out)")

    def npz_w(p, im):
        np.savez_compressed(str(p) + ".npz", im=im)

    def npz_r(p):
        with np.load(str(p) + ".npz") as z:
            return z["im"]

    return {"png level 1": (png_w, png_r, ".png"), "npy (memory map)": (npy_w, npy_r, ".npy"),
            "npy (cache reader)": (npy_w, npy_cache, ".npy"),
            "npy (read all)": (npy_w, npy_read_all, ".npy"), **out, "npz (deflate)": (npz_w, npz_r, ".npz")}


def sequence_read(segments: int, repeats: int):
    """Load seconds of a take of ``segments`` segments x 8 frames of 10k and 41k vertices, both routes."""
    import trimesh

    from nodes.common.types import MeshSequence

    print(f"\nMeshSequence, {segments} segments x 8 frames: load ms, best of {repeats}")
    print(f"{'vertices':>9} {'arrays':>14} {'PLYs':>9} {'ratio':>6}")
    for sub in (5, 6):
        base = trimesh.creation.icosphere(sub)
        seq = [trimesh.Trimesh(base.vertices * (1 + 0.01 * k) + s, base.faces, process=False,
                               metadata={"segment": s, "keyframe": 8 * s, "frame": 8 * s + k})
               for s in range(segments) for k in range(8)]
        times = []
        with tempfile.TemporaryDirectory(dir=os.environ.get("VOLCAP_BENCH_TMP")) as d:
            MeshSequence.save(seq, Path(d))
            for route in ("arrays", "ply"):
                if route == "ply":
                    for f in Path(d).glob("*.faces.npy"):
                        f.unlink()
                best = float("inf")
                for _ in range(repeats + 1):
                    t = time.perf_counter()
                    back = MeshSequence.load(Path(d))
                    float(back[-1].vertices[-1, -1])                                   # touch the data
                    best = min(best, time.perf_counter() - t)
                times.append(best)
        print(f"{len(base.vertices):>9} {times[0] * 1e3:14.1f} {times[1] * 1e3:9.1f} {times[1] / times[0]:6.1f}", flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cameras", type=int, default=24)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--segments", type=int, default=13)
    a = ap.parse_args()
    from nodegraph.testing import run_node

    images = run_node("synth", params={"scene": "figure", "cameras": a.cameras, "width": 1920, "height": 1080})["images"].images
    print(describe())
    print(f"{a.cameras} images of 1920x1080 RGB ({sum(im.nbytes for im in images) / 1e6:.0f} MB raw)")
    print(f"{'format':>18} {'write ms':>9} {'read ms':>9} {'MB':>7}")
    with tempfile.TemporaryDirectory(dir=os.environ.get("VOLCAP_BENCH_TMP")) as d:
        for name, (w, r, ext) in formats().items():
            tw = tr = float("inf")
            for rep in range(a.repeats):
                t = time.perf_counter()
                for i, im in enumerate(images):
                    w(Path(d) / f"{name[:3]}{i}", im)
                tw = min(tw, time.perf_counter() - t)
                t = time.perf_counter()
                total = 0
                for i in range(len(images)):
                    arr = r(Path(d) / f"{name[:3]}{i}")
                    total += int(arr[-1, -1, -1] if arr.ndim == 3 else arr[-1])  # touch the data
                tr = min(tr, time.perf_counter() - t)
            size = sum(f.stat().st_size for f in Path(d).glob(f"{name[:3]}*{ext}"))
            print(f"{name:>18} {tw * 1e3:9.0f} {tr * 1e3:9.1f} {size / 1e6:7.1f}", flush=True)
    sequence_read(a.segments, a.repeats)
    print(f"load average now {load_average()}")


if __name__ == "__main__":
    main()
