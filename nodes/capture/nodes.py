"""The `capture` source node: one frame of a calibrated multi-camera capture (see load.py)."""
from __future__ import annotations

from nodegraph import InPath, Node, NodeError, Output, Param, Table
from nodes.common.types import CameraSet, Images, Masks

from .load import layout_world, load_capture, world_of


class Capture(Node):
    """One frame of a calibrated multi-camera capture (images, optional masks and clean plates, cameras)
    from a dataset folder; known dataset layouts are detected, patterns override them. The cameras come in
    the world frame (+Z up, metres, origin on the floor under the subject: world.py), one for every frame."""

    type_name = "capture"
    version = 1
    uses_frame = True
    outputs = {
        "images": Output(Images, "RGB image per camera"),
        "masks": Output(Masks, "silhouettes shipped with the dataset (None when it has none)", optional=True),
        "cameras": Output(CameraSet, "calibration"),
        "background": Output(Images, "clean plates, one per camera (None when the dataset has none)", optional=True),
        "world": Output(Table, "the world frame: up, metres per unit and origin in the dataset's frame, where each "
                        "came from, the subject's box and height, warnings; and the videos' frame rate (fps, None "
                        "for image files: give the exports' fps)"),
    }
    params = {
        "path": Param(InPath, doc="dataset folder"),
        "images": Param(str, "", doc="image pattern ({cam} {cam1} {name} {frame}, '*' = frames, or a video); '' = auto"),
        "masks": Param(str, "", doc="mask pattern, 'alpha' for the images' alpha channel; '' = auto"),
        "background": Param(str, "", doc="clean plate pattern (image or video, frame 0); '' = auto"),
        "calibration": Param(str, "", doc="calibration file or folder (relative to path); '' = auto"),
        "mask_threshold": Param(int, 127, range=(0, 254), doc="mask pixels above this grey value are foreground"),
        "world": Param(str, "auto", choices=("auto", "dataset"), doc="auto: cameras in the world frame (+Z up, "
                       "metres, origin on the floor under the subject); dataset: as the calibration files say"),
        "up": Param(list, [], item=float, doc="world up as a vector in the dataset's frame; [] = the layout's, else the "
                    "cameras' mean up"),
        "units": Param(float, 0.0, range=(0.0, 1e6), doc="metres per dataset unit; 0 = the layout's, else 1"),
        "origin": Param(list, [], item=float, doc="the world origin (a point on the floor) in the dataset's frame; "
                        "[] = on the floor under the subject's centre"),
        "origin_frame": Param(int, 0, range=(0, 10**7), doc="the frame whose masks place the origin (the same "
                              "frame for every frame loaded)"),
    }

    def run(self, *, path, images, masks, background, calibration, mask_threshold, world, up, units, origin,
            origin_frame, frame):
        for name, v in (("up", up), ("origin", origin)):
            if len(v) not in (0, 3):
                raise NodeError(f"{self.type_name}: {name} must be [] or three numbers, got {v}")
        out = load_capture(path, frame, images, masks, background, calibration, mask_threshold, log=self.log)
        fps = out.pop("fps", None)
        if world == "dataset":
            out["world"] = {"frame": "dataset", "fps": fps, "warnings": []}
            return out
        ref = out if frame == origin_frame else None
        frame_, report = world_of(path, images, masks, background, calibration, mask_threshold, tuple(up), units,
                                  tuple(origin), origin_frame, ref, self.log)
        out["cameras"] = frame_.cameras(out["cameras"])
        out["world"] = {"frame": "world", "fps": fps, **report}
        return out
