"""The `capture` source node: one frame of a calibrated multi-camera capture (see load.py)."""
from __future__ import annotations

from nodegraph import InPath, Node, Output, Param
from nodes.common.types import CameraSet, Images, Masks

from .load import load_capture


class Capture(Node):
    """One frame of a calibrated multi-camera capture (images, optional masks and clean plates, cameras)
    from a dataset folder; known dataset layouts are detected, patterns override them."""

    type_name = "capture"
    version = 1
    uses_frame = True
    outputs = {
        "images": Output(Images, "RGB image per camera"),
        "masks": Output(Masks, "silhouettes shipped with the dataset (None when it has none)", optional=True),
        "cameras": Output(CameraSet, "calibration"),
        "background": Output(Images, "clean plates, one per camera (None when the dataset has none)", optional=True),
    }
    params = {
        "path": Param(InPath, doc="dataset folder"),
        "images": Param(str, "", doc="image pattern ({cam} {cam1} {name} {frame}, '*' = frames, or a video); '' = auto"),
        "masks": Param(str, "", doc="mask pattern, 'alpha' for the images' alpha channel; '' = auto"),
        "background": Param(str, "", doc="clean plate pattern (image or video, frame 0); '' = auto"),
        "calibration": Param(str, "", doc="calibration file or folder (relative to path); '' = auto"),
        "mask_threshold": Param(int, 127, range=(0, 254), doc="mask pixels above this grey value are foreground"),
    }

    def run(self, *, path, images, masks, background, calibration, mask_threshold, frame):
        return load_capture(path, frame, images, masks, background, calibration, mask_threshold, log=self.log)
