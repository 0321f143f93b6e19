"""The `capture` source nodes: one frame of a calibrated multi-camera capture (see load.py), and the background
mixture learnt from the empty stage's frames."""
from __future__ import annotations

import numpy as np

from nodegraph import InPath, Node, NodeError, Output, Param, Table
from nodes.common.background import background_mixture
from nodes.common.types import CameraSet, Images, Masks, PlateMixture, PlateModel

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


class Background(Node):
    """A per-pixel Gaussian mixture of the background learnt from several frames of the empty stage (the plate
    video or frames of ``background``; the seed's "learning techniques" for shadows and a background that is not
    still): every pixel gets up to ``components`` Gaussians with their own per-channel sigma, a component being
    background when it holds ``min_weight`` of the frames (a flickering light, a monitor, sensor noise that
    differs across the image). Give its model to key.difference. Reads the capture folder as `capture` does."""

    type_name = "capture.background"
    version = 1
    inputs = {}
    outputs = {"model": Output(PlateModel, "per camera the background mixture"),
               "report": Output(Table, "per camera the frames used, the share of pixels with several backgrounds, "
                                       "the median sigma")}
    params = {
        "path": Param(InPath, doc="dataset folder (as capture's)"),
        "images": Param(str, "", doc="image pattern, as capture's ('' = auto): names the cameras"),
        "background": Param(str, "", doc="the empty stage: a video, '*' or {frame} pattern per camera ('' = the layout's)"),
        "calibration": Param(str, "", doc="calibration file or folder, as capture's ('' = auto)"),
        "frames": Param(int, 25, range=(2, 100000), doc="at most this many plate frames, spread over all there are"),
        "components": Param(int, 3, range=(1, 5), doc="Gaussians per pixel (1: one, with its own sigma)"),
        "noise": Param(float, 4.0, range=(0.5, None), doc="lowest sigma, grey levels"),
        "match": Param(float, 4.0, range=(1.0, None), doc="colour distance (sigmas) within which a frame joins a component"),
        "min_weight": Param(float, 0.1, range=(0.0, 1.0), doc="share of the frames a component needs to be background"),
        "shift": Param(float, 0.5, range=(0.0, 10.0), doc="pixels the footage may sit off the plate frames: sigma grows "
                       "by this times the background's gradient (edges)"),
    }

    def run(self, *, path, images, background, calibration, frames, components, noise, match, min_weight, shift):
        cap = load_capture(path, 0, images=images, background=background, calibration=calibration, log=self.log,
                           plates=frames)
        sets, used = cap["plates"], cap["plate_frames"]
        if len(sets) < 2:
            raise NodeError(f"capture.background: the background pattern holds {len(sets)} frame: a mixture needs "
                            "several frames of the empty stage (give a plate video or a '*' pattern)")
        names = sets[0].names
        means, sigmas, weights, report = [], [], [], {"frames_used": used, "cameras": {}}
        for v, name in enumerate(names):
            self.progress(v, len(names), "cameras")
            mean, sigma, weight = background_mixture((s.images[v] for s in sets), components, noise, match, min_weight, shift)
            means.append(mean)
            sigmas.append(sigma)
            weights.append(weight)
            count = (weight > 0).sum(0)
            report["cameras"][name] = {
                "frames": len(sets),
                "several_backgrounds": round(float((count > 1).mean()), 4),
                "stable": round(float((weight[0] >= 0.5).mean()), 4),
                "median_sigma": round(float(np.median(sigma[0].astype(np.float32))), 2)}
        return {"model": PlateMixture(means, sigmas, weights, names), "report": report}
