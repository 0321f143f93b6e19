"""The photo-consistency test's colour arithmetic, in NumPy (mirrors kernels/carve.cl), and per-camera gains.

A voxel is tested on the mean colour of its footprint pixels in each view that sees it (r g b, 0..255,
times the view's gain), converted to the test's colour space:
    rgb   sRGB values as they are (0..255 per channel)
    lab   CIE L*a*b* (D65 white; L* 0..100), where a distance of 1 is about one just-noticeable difference
Its colour deviation is the RMS distance of those per-view colours from their mean,
    deviation^2 = mean_v |q_v|^2 - |mean_v q_v|^2,
and it is photo-consistent when
    deviation <= threshold + adaptive * sqrt(mean_v spread_v^2),
spread_v being the RMS spread of the view's pixels around their mean, in the same colour space (the
adaptive threshold of Slabaugh, Culbertson, Malzbender & Schafer 2004: a voxel over texture, whose
footprint mixes colours, needs a wider tolerance than one over a plain surface). Using per-view means
rather than pooled pixels (as Seitz & Dyer do) keeps texture inside one footprint from counting as
disagreement between views.
"""
from __future__ import annotations

import numpy as np

SPACES = ("rgb", "lab")

_RGB_TO_XYZ = np.array([[0.4124564, 0.3575761, 0.1804375],
                        [0.2126729, 0.7151522, 0.0721750],
                        [0.0193339, 0.1191920, 0.9503041]], np.float32)


def _srgb_linear(c: np.ndarray) -> np.ndarray:
    f = np.float32
    c = c / f(255)
    with np.errstate(invalid="ignore"):
        return np.where(c <= f(0.04045), c / f(12.92), np.power((c + f(0.055)) / f(1.055), f(2.4))).astype(f)


def _lab_f(t: np.ndarray) -> np.ndarray:
    f = np.float32
    return np.where(t > f(0.008856452), np.cbrt(t), t / f(0.12841855) + f(0.13793103)).astype(f)


def colour_space(rgb: np.ndarray, space: str) -> np.ndarray:
    """(N, 3) float32 mean colours (r g b, 0..255) in the test's colour space (float32, kernel order)."""
    rgb = np.asarray(rgb, np.float32)
    if space == "rgb":
        return rgb
    f = np.float32
    r, g, b = (_srgb_linear(rgb[:, a]) for a in range(3))
    M = _RGB_TO_XYZ
    X = ((M[0, 0] * r + M[0, 1] * g) + M[0, 2] * b) / f(0.95047)
    Y = (M[1, 0] * r + M[1, 1] * g) + M[1, 2] * b
    Z = ((M[2, 0] * r + M[2, 1] * g) + M[2, 2] * b) / f(1.08883)
    fx, fy, fz = _lab_f(X), _lab_f(Y), _lab_f(Z)
    return np.stack([f(116) * fy - f(16), f(500) * (fx - fy), f(200) * (fy - fz)], axis=1).astype(f)


def dot3(q: np.ndarray) -> np.ndarray:
    """Squared length per row, summed left to right (the kernel's order)."""
    return (q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1]) + q[:, 2] * q[:, 2]


def spread(m: np.ndarray, sd: np.ndarray, q: np.ndarray, space: str) -> np.ndarray:
    """Squared spread in the colour space of pixels with mean ``m`` and per-channel standard deviation ``sd``
    (N, 3 each; ``q`` = colour_space(m)): sum over channels of |f(m + sd_a e_a) - f(m)|^2 (kernel order)."""
    if space == "rgb":
        return dot3(sd)
    out = []
    for a in range(3):
        x = m.copy()
        x[:, a] = x[:, a] + sd[:, a]
        out.append(dot3(colour_space(x, space) - q))
    return (out[0] + out[1]) + out[2]


def camera_gains(images: list[np.ndarray], masks: list[np.ndarray]) -> np.ndarray:
    """(V, 3) float32 per-camera, per-channel gains that bring each view's mean colour inside its silhouette
    to the mean over all views (exposure and white-balance differences between cameras). A view with an
    empty silhouette or a zero channel mean gets gain 1 for it."""
    means = np.ones((len(images), 3))
    for v, (im, m) in enumerate(zip(images, masks)):
        sel = m > 127
        if sel.any():
            means[v] = im[sel].reshape(-1, 3).mean(axis=0)
    target = means.mean(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        gains = np.where(means > 0, target / means, 1.0)
    return gains.astype(np.float32)
