"""Silhouette agreement of a mesh with masks, per view (the mesh rasterized into every camera).

Convention: a pixel is covered when its centre (integer coordinates, as cv2.projectPoints) lies inside a
projected triangle, the way the masks themselves sample the scene. An independent evaluator that projects
with cv2.projectPoints and fills pixel centres (skimage.draw.polygon) gets the same IoU (within 0.002: tests/
stages/common/test_pixel_conventions.py); one that fills triangles with cv2.fillPoly (every pixel the outline
touches, about half a pixel fatter) reports less, e.g. inria_dancer's hull mesh 0.911 instead of 0.930."""
from __future__ import annotations

import numpy as np

from nodes.common import raster
from nodes.common.cameras import Cameras
from nodes.common.silhouettes import check_sizes
from nodes.common.types import MaskSet


def silhouette_report(vertices, faces, cameras: Cameras, masks: MaskSet) -> dict:
    """Per view: IoU of the mesh's silhouette with the mask (> 127), mesh pixels outside the mask and mask
    pixels the mesh does not cover; plus mean / min IoU and the error sums over views."""
    check_sizes(masks.masks, cameras, "eval.silhouette")
    views = [{"name": cam.name, **v} for cam, v in zip(cameras, raster.silhouette_iou(vertices, faces, cameras, masks.masks))]
    ious = [v["iou"] for v in views]
    return {
        "views": views,
        "mean_iou": float(np.mean(ious)), "min_iou": float(np.min(ious)),
        "mesh_outside_mask": sum(v["mesh_outside_mask"] for v in views),
        "mask_not_covered": sum(v["mask_not_covered"] for v in views),
        "mean_mesh_outside_mask": float(np.mean([v["mesh_outside_mask"] for v in views])),
        "mean_mask_not_covered": float(np.mean([v["mask_not_covered"] for v in views])),
    }
