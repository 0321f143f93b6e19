"""Keying speed: 24 x 1920x1080 frames, our OpenCL keys vs the baselines of REFERENCES.md (cv2.inRange,
MOG2 with shadow detection), in the same run. Prints a table of the minimum over repeats (shared machine),
then key.chroma's upload (a zero-copy buffer over the frame), kernel and download (alpha, despilled RGB).
"learn" rows: the background mixture learnt from the n frames as plates (per camera, once per capture).
"hull bits" is the fused real-time path (chroma_key_bits: silhouettes packed for the hull on the device, no
download), here without a garbage matte, so every pixel is keyed.

    python bench/key.py [--frames 24] [--repeats 5]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from nodes.key import keying as K  # noqa: E402


def frames(n: int, h=1080, w=1920) -> tuple[list[np.ndarray], np.ndarray]:
    """n green-screen frames with a moving red ball, and a textured clean plate."""
    rng = np.random.default_rng(0)
    ys, xs = np.mgrid[:h, :w]
    plate = np.stack([40 + 10 * np.sin(xs / 50), 160 + 20 * np.cos(ys / 40), 60 + 0 * xs], -1)
    out = []
    for i in range(n):
        ball = (ys - h / 2) ** 2 + (xs - 300 - 50 * i) ** 2 < 200**2
        img = np.where(ball[..., None], np.array([200.0, 60, 50]), plate)
        out.append(np.clip(img + rng.normal(0, 2, (1, w, 3)), 0, 255).astype(np.uint8))
    return out, np.clip(plate, 0, 255).astype(np.uint8)


def best(fn, repeats: int) -> float:
    fn()  # warm-up (kernel build, buffer allocation)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main():
    import cv2

    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    imgs, plate = frames(args.frames)
    key = K.estimate_key_direction(imgs[0])
    mean, inv_var = K.plate_model(plate, 4.0)
    bgr = [im[:, :, ::-1].copy() for im in imgs]

    def inrange():
        for im in bgr:
            hsv = cv2.cvtColor(im, cv2.COLOR_BGR2HSV)
            cv2.inRange(hsv, (40, 80, 40), (85, 255, 255))

    def inrange_only():
        for im in bgr:
            cv2.inRange(im, (0, 100, 0), (120, 255, 120))

    def mog2():
        mog = cv2.createBackgroundSubtractorMOG2(detectShadows=True)
        for im in bgr:
            mog.apply(im)

    def chroma_alpha():  # the matte alone (key.chroma with spill 0)
        for im in imgs:
            K.chroma_key_cl(im, key, despill=False)

    def chroma_full():
        for im in imgs:
            K.chroma_key_cl(im, key)

    bits = [None]

    def chroma_bits():  # the fused path: silhouette bits + block tables for the hull, left on the device
        bits[0] = K.chroma_key_bits(imgs, key, out=bits[0])

    def difference():
        for im in imgs:
            K.difference_key_cl(im, mean, inv_var)

    from nodes.common.background import background_mixture
    from nodes.common.types import PlateMixture

    plates = [np.clip(plate.astype(np.int16) + np.random.default_rng(k).integers(-4, 5, plate.shape), 0, 255)
              .astype(np.uint8) for k in range(args.frames)]
    model = PlateMixture(*[[x] for x in background_mixture(plates)], ["a"])

    def mixture():
        for im in imgs:
            K.difference_key_mixture_cl(im, model, 0)

    def learn_cl():
        background_mixture(plates, method="opencl")

    def learn_np():
        background_mixture(plates, method="numpy")

    def learn_mog2():
        mog = cv2.createBackgroundSubtractorMOG2(detectShadows=True)
        for im in plates:
            mog.apply(im, learningRate=-1)

    rows = [
        ("cv2.cvtColor HSV + inRange", inrange),
        ("cv2.inRange (RGB box only)", inrange_only),
        ("cv2 MOG2 detectShadows", mog2),
        ("key.chroma OpenCL (alpha only)", chroma_alpha),
        ("key.chroma OpenCL (alpha+despill)", chroma_full),
        ("key.chroma OpenCL -> hull bits", chroma_bits),
        ("key.difference OpenCL", difference),
        ("key.difference OpenCL, mixture model", mixture),
        ("learn: capture.background OpenCL", learn_cl),
        ("learn: its NumPy reference", learn_np),
        ("learn: cv2 MOG2 apply (same frames)", learn_mog2),
    ]
    n = args.frames
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from machine import describe

    print(describe())
    print(f"{n} frames of 1920x1080, min of {args.repeats} repeats")
    print(f"{'method':36s} {'total ms':>9s} {'ms/frame':>9s}")
    for name, fn in rows:
        t = best(fn, args.repeats)
        print(f"{name:36s} {1000 * t:9.1f} {1000 * t / n:9.2f}")
    print("\nkey.chroma steps (queue finished after each; min of repeats), ms for all frames:")
    print(f"{'path':16s} {'upload':>7s} {'kernel':>7s} {'download':>9s}")
    for despill in (False, True):
        steps = {}
        for _ in range(args.repeats):
            t: dict = {}
            for im in imgs:
                K.chroma_key_cl(im, key, despill=despill, timings=t)
            steps = {k: min(v, steps.get(k, v)) for k, v in t.items()}
        name = "alpha+despill" if despill else "alpha only"
        print(f"{name:16s} {1000 * steps['upload']:7.1f} {1000 * steps['kernel']:7.1f} {1000 * steps['download']:9.1f}")


if __name__ == "__main__":
    main()
