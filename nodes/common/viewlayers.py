"""View-dependent texture layers as data (made by nodes/texture/viewdep.py, written by export.views) and the
blend a renderer applies to them (``layer_weights``: the reference of a player's fragment shader)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NONE = 255                    # texel_view value of a layer no camera painted
SIGMA = np.radians(20.0)      # blend width: measured best of 5/10/20/40 deg on oxford_dino and thu_wd_human


@dataclass
class ViewLayers:
    """K atlas layers of one frame and the cameras that painted them."""

    layers: np.ndarray        # (K, S, S, 3) uint8 colours (the blended texture where the layer has no view)
    texel_view: np.ndarray    # (S, S, K) uint8 camera index per texel and layer, NONE = not painted
    centres: np.ndarray       # (V, 3) float64 camera centres, world frame
    names: list               # (V,) camera names
    sigma: float = SIGMA      # the blend width a renderer should use (radians)

    def problem(self) -> str | None:
        if self.layers.ndim != 4 or self.layers.shape[-1] != 3 or self.layers.dtype != np.uint8:
            return f"layers must be (K, S, S, 3) uint8, got {self.layers.shape} {self.layers.dtype}"
        k, s = self.layers.shape[0], self.layers.shape[1]
        if self.texel_view.shape != (s, s, k) or self.texel_view.dtype != np.uint8:
            return f"texel_view must be ({s}, {s}, {k}) uint8, got {self.texel_view.shape} {self.texel_view.dtype}"
        if self.centres.shape != (len(self.names), 3):
            return f"{len(self.names)} camera names for {len(self.centres)} centres"
        used = self.texel_view[self.texel_view != NONE]
        if used.size and int(used.max()) >= len(self.names):
            return f"texel_view names camera {int(used.max())} of {len(self.names)}"
        return None


def layer_weights(points, eye, centres, ids, sigma=SIGMA) -> tuple[np.ndarray, np.ndarray]:
    """Blend weights at surface points (N, 3) seen from ``eye`` (3,): (N, K) for the layers and (N,) for the
    blended (static) texture. With a_k the angle between the ray to the eye and the ray to layer k's camera,
    w_k = exp(-(a_k / sigma)^2) / a_k and the static texture counts as a layer at angle ``sigma``: a camera at
    the eye takes all (the photo comes back), cameras nearer than sigma dominate, and where every camera is
    far from the eye the static blend (the least-squares guess) takes over. Normalised to sum 1."""
    p = np.asarray(points, np.float64)
    ids = np.asarray(ids)
    valid = ids != NONE
    c = np.asarray(centres, np.float64)[np.where(valid, ids, 0)]           # (N, K, 3)
    to_eye = np.asarray(eye, np.float64)[None] - p
    to_eye /= np.maximum(np.linalg.norm(to_eye, axis=1, keepdims=True), 1e-12)
    to_cam = c - p[:, None]
    to_cam /= np.maximum(np.linalg.norm(to_cam, axis=2, keepdims=True), 1e-12)
    ang = np.arccos(np.clip(np.einsum("nkd,nd->nk", to_cam, to_eye), -1, 1))
    sigma = float(sigma)
    w = np.where(valid, np.exp(-(ang / sigma) ** 2) / np.maximum(ang, 1e-4), 0.0)
    wb = np.full(len(p), np.exp(-1.0) / sigma)
    s = w.sum(axis=1) + wb
    return (w / s[:, None]).astype(np.float32), (wb / s).astype(np.float32)
