"""A keying stage with known truth, written as a capture folder: the animated figure in the textured room (its
soft shadow on the floor), sensor noise that differs every frame, and a flickering light band on the walls, plus
frames of the empty stage (the plate video a studio shoots) and the same footage on a green screen (spill on the
figure). Tests and bench/key.py key it and compare with the exact silhouettes.

Folder: ``Calib.toml``; per camera ``<name>/frames/NNNN.png`` (the footage), ``<name>/plate/NNNN.png`` (the empty
stage), ``<name>/green/NNNN.png`` (the green screen version), ``<name>/truth/NNNN.png`` (the silhouettes)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from nodes.common.calibration import save_toml

from . import scenes
from .render import render_scene, ring_rig

FLICKER = (0.15, 0.32)  # the light band's rows, as shares of the image height
FLICKER_GAIN = (0.55, 1.0)  # the band's brightness in its two states (a light that blinks)


def light(image: np.ndarray, on: bool, truth: np.ndarray | None = None) -> np.ndarray:
    """``image`` with the light band in state ``on`` (bright) or off (dimmer and bluer) on the background pixels
    (``truth``: the subject's silhouette, which the light does not reach)."""
    h = image.shape[0]
    r0, r1 = int(FLICKER[0] * h), int(FLICKER[1] * h)
    out = image.astype(np.float32)
    if not on:
        band = out[r0:r1] * np.float32(FLICKER_GAIN[0]) + np.array([0, 10, 40], np.float32)
        keep = np.zeros(band.shape[:2], bool) if truth is None else truth[r0:r1] > 0
        out[r0:r1] = np.where(keep[..., None], out[r0:r1], band)
    return out


def noisy(image: np.ndarray, sigma: float, rng) -> np.ndarray:
    return np.clip(np.rint(image + rng.normal(0, sigma, image.shape)), 0, 255).astype(np.uint8)


def write_key_capture(folder, *, cameras: int = 6, width: int = 320, height: int = 240, frames: int = 6,
                      plates: int = 24, noise: float = 3.0, start: int = 0, step: int = 4, seed: int = 0) -> dict:
    """Render and write the stage (see the module docstring); footage frame k is the figure's frame
    ``start + step * k`` (it walks, so every background pixel is seen in most frames), the light is off in
    every third footage frame and in a third of the plate frames. Returns the truth: {"cameras", "masks" (per
    frame, per camera, uint8), "light" (per footage frame, on?)}."""
    import cv2

    folder = Path(folder)
    rng = np.random.default_rng(seed)
    first = scenes.build("figure", start)
    cams = ring_rig(cameras, first.center, first.radius, 55.0, width, height)
    folder.mkdir(parents=True, exist_ok=True)
    save_toml(cams, folder / "Calib.toml")
    empty, _ = render_scene(first, cams, "plate", False, with_object=False)
    for v, c in enumerate(cams):
        for d in ("frames", "plate", "green", "truth"):
            (folder / c.name / d).mkdir(parents=True, exist_ok=True)
    for k in range(plates):
        on = k % 3 != 1
        for v, c in enumerate(cams):
            cv2.imwrite(str(folder / c.name / "plate" / f"{k:04d}.png"), noisy(light(empty[v], on), noise, rng)[:, :, ::-1])
    truth, lights = [], []
    for k in range(frames):
        sc = scenes.build("figure", start + step * k)
        on = k % 3 != 2
        images, masks = render_scene(sc, cams, "plate", True)
        green, _ = render_scene(sc, cams, "green", True)
        for v, c in enumerate(cams):
            cv2.imwrite(str(folder / c.name / "frames" / f"{k:04d}.png"),
                        noisy(light(images[v], on, masks[v]), noise, rng)[:, :, ::-1])
            cv2.imwrite(str(folder / c.name / "green" / f"{k:04d}.png"), noisy(green[v], noise, rng)[:, :, ::-1])
            cv2.imwrite(str(folder / c.name / "truth" / f"{k:04d}.png"), masks[v])
        truth.append(masks)
        lights.append(on)
    return {"cameras": cams, "masks": truth, "light": lights}
