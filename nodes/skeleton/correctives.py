"""Corrective shapes: what linear blend skinning leaves of a tracked sequence, kept as K blend shapes (morph
targets) and their weights per frame, so that an exported rig reproduces the sequence it was fitted to.

A glTF player and UsdSkel both add blend shapes to the rest points *before* skinning, so a frame's correction
of vertex v is the residual taken back through that vertex's blended LBS transform: with A_fv = sum_k w_vk R_fj
and b_fv = sum_k w_vk t_fj (j = the vertex's k-th joint), the file skins A_fv (x_v + d_fv) + b_fv, which is the
tracked point y_fv exactly when d_fv = A_fv^-1 (y_fv - b_fv) - x_v (a pose-space corrective, one per frame). The
(F, 3V) matrix of these displacements is compressed by its truncated SVD (no mean: the shapes are added to the
rest, with weight 0 at rest) into K shapes and an (F, K) weight curve: the best rank-K approximation in the rest
space (Eckart-Young); K >= the frame count keeps every frame exactly. Each shape is scaled so its weights span
[-1, 1] (a slider's range in Blender and other tools). The error after correction is measured where it counts,
in the posed (skinned) space, per frame.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Correctives:
    """K shapes (K, V, 3) rest-space displacements, weights (F, K), and the per-frame posed error (rms and max,
    metres) of plain LBS and of LBS with the shapes."""

    shapes: np.ndarray
    weights: np.ndarray
    lbs_rms: np.ndarray
    lbs_max: np.ndarray
    rms: np.ndarray
    max: np.ndarray

    def table(self) -> dict:
        r = lambda a: [round(float(x), 7) for x in a]  # noqa: E731
        return {"shapes": int(len(self.shapes)), "lbs_rms": r(self.lbs_rms), "lbs_max": r(self.lbs_max),
                "corrected_rms": r(self.rms), "corrected_max": r(self.max),
                "lbs_rms_total": float(np.sqrt((self.lbs_rms ** 2).mean())),
                "corrected_rms_total": float(np.sqrt((self.rms ** 2).mean())),
                "corrected_max_total": float(self.max.max()) if len(self.max) else 0.0}


def blended_transforms(indices, weights, rotations, translations) -> tuple[np.ndarray, np.ndarray]:
    """(A (F, V, 3, 3), b (F, V, 3)): each vertex's blended LBS transform per frame from sparse influences
    (``formats.sparse_influences``) and (F, J, 3, 3) rotations, (F, J, 3) translations."""
    r = np.asarray(rotations, np.float64)[:, indices]             # (F, V, k, 3, 3)
    t = np.asarray(translations, np.float64)[:, indices]          # (F, V, k, 3)
    return np.einsum("vk,fvkab->fvab", weights, r), np.einsum("vk,fvka->fva", weights, t)


def rest_residuals(vertices, indices, weights, rotations, translations, targets) -> np.ndarray:
    """(F, V, 3) per-frame rest-space displacements d with A (x + d) + b = target (the module docstring); a
    vertex whose blended transform is singular (opposed rotations cancelling) gets the least-squares one."""
    a, b = blended_transforms(indices, weights, rotations, translations)
    rhs = np.asarray(targets, np.float64) - b
    try:
        local = np.linalg.solve(a, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:
        local = np.einsum("fvab,fvb->fva", np.linalg.pinv(a), rhs)
    return local - np.asarray(vertices, np.float64)[None]


def fit_correctives(vertices, indices, weights, rotations, translations, targets, k: int) -> Correctives:
    """``k`` corrective shapes (truncated SVD of ``rest_residuals``) and their weights per frame, with the
    posed error per frame before and after (``Correctives``); k is capped at the frame count."""
    x = np.asarray(vertices, np.float64)
    y = np.asarray(targets, np.float64)
    a, b = blended_transforms(indices, weights, rotations, translations)
    lbs = np.einsum("fvab,vb->fva", a, x) + b
    err0 = np.linalg.norm(lbs - y, axis=2)
    d = rest_residuals(x, indices, weights, rotations, translations, y)
    f, v = d.shape[:2]
    k = int(min(k, f))
    u, s, vt = np.linalg.svd(d.reshape(f, -1), full_matrices=False)
    w = u[:, :k] * s[:k]                                           # (F, K)
    shapes = vt[:k].reshape(k, v, 3)
    span = np.abs(w).max(0) if k else np.zeros(0)
    span = np.where(span > 0, span, 1.0)
    w, shapes = w / span, shapes * span[:, None, None]
    approx = np.einsum("fk,kva->fva", w, shapes)
    posed = np.einsum("fvab,fvb->fva", a, x[None] + approx) + b
    err = np.linalg.norm(posed - y, axis=2)
    return Correctives(shapes, w, np.sqrt((err0 ** 2).mean(1)), err0.max(1), np.sqrt((err ** 2).mean(1)), err.max(1))
