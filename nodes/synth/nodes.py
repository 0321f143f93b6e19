"""The `synth` source node: a procedural scene rendered from a camera rig, with its ground truth."""
from __future__ import annotations

import numpy as np

from nodegraph import Node, Output, Param
from nodes.common import raster
from nodes.common.types import Bounds, CameraSet, Images, ImageSet, Masks, MaskSet, Mesh, Skeleton

from . import scenes
from .render import render_scene, ring_rig


class Synth(Node):
    """Renders a procedural scene with known ground truth from a camera ring or dome: images, exact
    silhouettes, cameras, the true mesh (and skeleton for the animated figure), a clean plate and a box.
    Shading is Lambert on procedural checker/stripe patterns; no anti-aliasing."""

    type_name = "synth"
    version = 1
    uses_frame = True
    checkpoint = True  # rendering costs seconds per frame: keep what it made for every later run
    inputs = {}
    outputs = {
        "images": Images, "masks": Masks, "cameras": CameraSet,
        "mesh": Output(Mesh, "ground-truth surface of this frame"),
        "skeleton": Output(Skeleton, "joints and LBS weights (figure only)", optional=True),
        "background": Output(Images, "clean plate (background=plate only)", optional=True),
        "bounds": Output(Bounds, "a box around the object"),
    }
    params = {
        "scene": Param(str, "figure", choices=scenes.SCENES, doc="what to render"),
        "rig": Param(str, "ring", choices=("ring", "dome"), doc="camera layout"),
        "cameras": Param(int, 8, range=(1, 256), doc="number of cameras"),
        "width": Param(int, 640, range=(8, 8192), doc="image width, pixels"),
        "height": Param(int, 480, range=(8, 8192), doc="image height, pixels"),
        "fov": Param(float, 50.0, range=(5.0, 150.0), doc="horizontal field of view, degrees"),
        "distortion": Param(float, 0.0, range=(-0.5, 0.5), doc="radial k1 of every camera"),
        "background": Param(str, "green", choices=("green", "plate"), doc="chroma green or a textured room"),
        "shadow": Param(bool, True, doc="soft darker blob on the floor under the object"),
        "seed": Param(int, 0, range=(0, None), doc="0: regular rig; otherwise jittered camera placement"),
    }
    kernels = [raster.KERNELS]

    def run(self, *, scene, rig, cameras, width, height, fov, distortion, background, shadow, seed, frame):
        sc = scenes.build(scene, frame)
        cams = ring_rig(cameras, sc.center, sc.radius, fov, width, height, distortion, seed, dome=rig == "dome")
        images, masks = render_scene(sc, cams, background, shadow)
        plate = None
        if background == "plate":
            plate_images, _ = render_scene(sc, cams, background, False, with_object=False)
            plate = ImageSet(plate_images, cams.names)
        lo, hi = sc.mesh.bounds
        pad = 0.05 * np.linalg.norm(hi - lo)
        return {
            "images": ImageSet(images, cams.names), "masks": MaskSet(masks, names=cams.names), "cameras": cams,
            "mesh": sc.mesh, "skeleton": sc.skeleton, "background": plate,
            "bounds": np.array([lo - pad, hi + pad], dtype=np.float64),
        }
