"""On-disk forms for full-resolution images in the cache: write and read seconds per frame of 24 x 1920x1080 RGB
images (a synthetic green-screen frame rendered by the synth node), and the bytes, for PNG (OpenCV, level 1),
raw .npy (read by memory map), .npy compressed with LZ4 and with zstd (level 1), and .npz (zip deflate).
Prints the machine (CPU, load average, OpenCL device unused here) and the table.

    python bench/formats.py [--cameras 24] [--repeats 3]
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


def machine() -> str:
    cpu = next((ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name")), "?")
    return f"CPU {cpu} x{os.cpu_count()}, load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}"


def formats():
    import cv2
    import lz4.frame
    import zstandard

    def png_w(p, im):
        cv2.imwrite(str(p) + ".png", im, [cv2.IMWRITE_PNG_COMPRESSION, 1])

    def png_r(p):
        return cv2.imread(str(p) + ".png", cv2.IMREAD_COLOR)

    def npy_w(p, im):
        np.save(str(p) + ".npy", im)

    def npy_r(p):
        return np.load(str(p) + ".npy", mmap_mode="r")

    def npy_read_all(p):
        return np.ascontiguousarray(np.load(str(p) + ".npy", mmap_mode="r"))

    def lz4_w(p, im):
        Path(str(p) + ".lz4").write_bytes(lz4.frame.compress(im.tobytes(), compression_level=0))

    def lz4_r(p):
        return np.frombuffer(lz4.frame.decompress(Path(str(p) + ".lz4").read_bytes()), np.uint8)

    zc, zd = zstandard.ZstdCompressor(level=1, threads=0), zstandard.ZstdDecompressor()

    def zst_w(p, im):
        Path(str(p) + ".zst").write_bytes(zc.compress(im.tobytes()))

    def zst_r(p):
        return np.frombuffer(zd.decompress(Path(str(p) + ".zst").read_bytes()), np.uint8)

    def npz_w(p, im):
        np.savez_compressed(str(p) + ".npz", im=im)

    def npz_r(p):
        with np.load(str(p) + ".npz") as z:
            return z["im"]

    return {"png level 1": (png_w, png_r, ".png"), "npy (memory map)": (npy_w, npy_r, ".npy"),
            "npy (read all)": (npy_w, npy_read_all, ".npy"), "npy + lz4": (lz4_w, lz4_r, ".lz4"),
            "npy + zstd 1": (zst_w, zst_r, ".zst"), "npz (deflate)": (npz_w, npz_r, ".npz")}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cameras", type=int, default=24)
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    from nodegraph.testing import run_node

    images = run_node("synth", params={"scene": "figure", "cameras": a.cameras, "width": 1920, "height": 1080})["images"].images
    print(machine())
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


if __name__ == "__main__":
    main()
