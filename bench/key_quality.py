"""Keying quality on the key stage with known truth (nodes/synth/keystage.py: the walking figure in a textured
room, its soft floor shadow, sensor noise sigma 3 every frame, a light band on the walls that is off in every
third frame; the same footage on a green screen with spill; 24 frames of the empty stage), every method in the
same run against the exact silhouettes: mask IoU (mean and worst over frames x cameras), alpha error (mean
|alpha - truth| over the image, in % of full scale), ms per frame (all cameras) of the key itself.

Methods: key.chroma on the green footage; key.difference against one plate frame (the 1-Gaussian key), with and
without the shadow model (shadow 1); key.difference against capture.background's mixture (1 and 3 components, with
and without the shadow model; shift 0: no allowance for a camera that moved between plate and footage,
which this stage's cameras do not); the plate from the footage itself (key.plate's median over the footage frames,
where no plate was shot); OpenCV's MOG2 (detectShadows, learnt on the same plate frames, shadows as background)
as the baseline a user would otherwise pick.

    python bench/key_quality.py [--cameras 6] [--frames 6] [--width 320]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from machine import describe, load_average  # noqa: E402

from nodegraph.testing import run_node  # noqa: E402
from nodes.capture.load import load_capture  # noqa: E402
from nodes.common.types import ImageSet  # noqa: E402
from nodes.synth.keystage import write_key_capture  # noqa: E402

PATTERNS = {"images": "{name}/frames/{frame:04d}.png", "background": "{name}/plate/{frame:04d}.png"}


def scores(masks_per_frame, alpha_per_frame, truth):
    ious, errs = [], []
    for masks, alphas, tr in zip(masks_per_frame, alpha_per_frame, truth):
        for m, a, t in zip(masks, alphas, tr):
            got, want = m > 127, t > 127
            ious.append((got & want).sum() / max((got | want).sum(), 1))
            errs.append(np.abs(a.astype(np.float32) - want).mean())
    return float(np.mean(ious)), float(np.min(ious)), 100 * float(np.mean(errs))


def alphas_of(ms):
    return [a for a in ms.alpha] if ms.alpha is not None else [m / 255.0 for m in ms.masks]


def main():
    import cv2

    ap = argparse.ArgumentParser()
    ap.add_argument("--cameras", type=int, default=6)
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--width", type=int, default=320)
    args = ap.parse_args()
    print(describe())
    with tempfile.TemporaryDirectory() as d:
        folder = Path(d)
        t0 = time.perf_counter()
        truth = write_key_capture(folder, cameras=args.cameras, width=args.width, height=args.width * 3 // 4,
                                  frames=args.frames, plates=24)
        print(f"key stage: {args.cameras} cameras {args.width}x{args.width * 3 // 4}, {args.frames} footage frames "
              f"(light off in {sum(not x for x in truth['light'])}), 24 plate frames; rendered in "
              f"{time.perf_counter() - t0:.1f} s")
        caps = [load_capture(folder, f, **PATTERNS) for f in range(args.frames)]
        greens = [ImageSet([cv2.imread(str(folder / n / "green" / f"{f:04d}.png"))[:, :, ::-1].copy()
                            for n in caps[0]["images"].names], caps[0]["images"].names) for f in range(args.frames)]
        t = time.perf_counter()
        models = {k: run_node("capture.background", {}, {"path": str(folder), **PATTERNS, "components": k})
                  for k in (1, 3)}
        learn = (time.perf_counter() - t) / 2
        still = run_node("capture.background", {}, {"path": str(folder), **PATTERNS, "shift": 0.0})
        foot = run_node("key.plate", {"images": [c["images"] for c in caps]}, {}, frames=list(range(args.frames)))
        print(f"capture.background: {learn:.2f} s per model ({args.cameras} cameras x 24 frames); "
              f"several backgrounds on {100 * np.mean([c['several_backgrounds'] for c in models[3]['report']['cameras'].values()]):.1f} % "
              f"of the pixels; footage plate stable on "
              f"{100 * np.mean([c['stable'] for c in foot['report']['cameras'].values()]):.1f} %")

        def node(inputs_of, params=None):
            def run(f):
                return run_node("key.difference", inputs_of(f), params or {})["masks"]
            return run

        methods = {
            "key.chroma (green screen)": lambda f: run_node("key.chroma", {"images": greens[f]}, {})["masks"],
            "difference, 1 plate": node(lambda f: {"images": caps[f]["images"], "background": caps[f]["background"]}),
            "difference, 1 plate, no shadow model": node(
                lambda f: {"images": caps[f]["images"], "background": caps[f]["background"]}, {"shadow": 1.0}),
            "difference, mixture K=1 (24 plates)": node(lambda f: {"images": caps[f]["images"], "model": models[1]["model"]}),
            "difference, mixture K=3 (24 plates)": node(lambda f: {"images": caps[f]["images"], "model": models[3]["model"]}),
            "difference, mixture K=3, shift 0": node(lambda f: {"images": caps[f]["images"], "model": still["model"]}),
            "difference, mixture K=3, no shadow model": node(
                lambda f: {"images": caps[f]["images"], "model": models[3]["model"]}, {"shadow": 1.0}),
            "difference, plate from the footage": node(lambda f: {"images": caps[f]["images"], "background": foot["background"]}),
        }
        mogs = []
        for v in range(args.cameras):
            mog = cv2.createBackgroundSubtractorMOG2(detectShadows=True)
            for k in range(24):
                mog.apply(cv2.imread(str(folder / caps[0]["images"].names[v] / "plate" / f"{k:04d}.png")), learningRate=-1)
            mogs.append(mog)

        def mog2(f):
            ms = [np.where(m.apply(im[:, :, ::-1].copy(), learningRate=0) == 255, 255, 0).astype(np.uint8)
                  for m, im in zip(mogs, caps[f]["images"].images)]
            return type("M", (), {"masks": ms, "alpha": None})

        methods["OpenCV MOG2 (24 plates, shadows)"] = mog2
        off = [f for f in range(args.frames) if not truth["light"][f]]
        print(f"\n{'method':42s} {'IoU mean':>8s} {'worst':>6s} {'light off':>9s} {'alpha err %':>11s} {'ms/frame':>8s}")
        for name, fn in methods.items():
            fn(0)
            t = time.perf_counter()
            outs = [fn(f) for f in range(args.frames)]
            ms = 1000 * (time.perf_counter() - t) / args.frames
            mean, worst, err = scores([o.masks for o in outs], [alphas_of(o) for o in outs], truth["masks"])
            dark = scores([outs[f].masks for f in off], [alphas_of(outs[f]) for f in off], [truth["masks"][f] for f in off])[0]
            print(f"{name:42s} {mean:8.3f} {worst:6.3f} {dark:9.3f} {err:11.2f} {ms:8.1f}")
        draw_model(models[3]["model"], caps[off[0] if off else 0]["images"], folder)
        print(f"load average at the end: {load_average()}")


def draw_model(model, images, folder):
    """docs/background_keystage.png, camera 0: the most frequent background, the second where there is one
    (grey elsewhere), sigma of the first (x8), and the footage frame keyed against the model."""
    import cv2

    mean, sigma, weight = model.mean[0], model.sigma[0].astype(np.float32), model.weight[0]
    second = np.where((weight[1] > 0)[..., None], mean[1], 96).astype(np.uint8)
    sig = np.repeat(np.clip(sigma[0].max(-1) * 8, 0, 255).astype(np.uint8)[..., None], 3, -1)
    masks = run_node("key.difference", {"images": images, "model": model})["masks"]
    keyed = images.images[0].copy()
    keyed[masks.masks[0] > 127] = (40, 220, 60)
    tiles = [np.ascontiguousarray(mean[0]), second, sig, keyed]
    labels = ["background 1", "background 2 (where one)", "sigma x8", "keyed, light off"]
    for tile, label in zip(tiles, labels):
        cv2.putText(tile, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1)
    out = Path(__file__).resolve().parent.parent / "docs" / "background_keystage.png"
    cv2.imwrite(str(out), np.hstack(tiles)[:, :, ::-1])
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
