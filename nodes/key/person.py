"""A learned person matte where there is neither a green screen nor a clean plate: MediaPipe Pose's body
segmentation and its 33 body landmarks (the "full" pose model and the pose detector ship inside the mediapipe
0.10.14 wheel: nothing is downloaded at run time; later wheels ship no models).

Measured on pose2sim_single (a lab full of clutter and other people): the pose segmentation finds the one subject in
all four views, the selfie-segmentation model (also in the wheel) takes in furniture and misses the cap, so the
pose model is the one used. It finds the most prominent person per image: the multi-view consensus (key.consensus)
removes a view that picked someone else.

mediapipe is installed by ./setup.sh without its declared dependencies (opencv-contrib-python would shadow the
project's opencv-python-headless; jax is not needed by these models): protobuf < 5, absl-py, flatbuffers."""
from __future__ import annotations

import contextlib
import os

import numpy as np

from nodegraph import NodeError

INSTALL = ("pip install --no-deps mediapipe==0.10.14 'protobuf>=4.25.3,<5' absl-py flatbuffers (./setup.sh does it)")
LANDMARKS = ("nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye", "right_eye_outer",
             "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder", "right_shoulder", "left_elbow",
             "right_elbow", "left_wrist", "right_wrist", "left_pinky", "right_pinky", "left_index", "right_index",
             "left_thumb", "right_thumb", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle",
             "right_ankle", "left_heel", "right_heel", "left_foot_index", "right_foot_index")

_POSE = {}


@contextlib.contextmanager
def _quiet():
    """MediaPipe's C++ side (TFLite, absl) writes INFO and W0000 lines straight to file descriptor 2 on every
    graph start: send them to /dev/null for the call (its errors still come back as Python exceptions)."""
    import sys
    import warnings

    sys.stderr.flush()
    saved, null = os.dup(2), os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 2)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")   # protobuf's GetPrototype deprecation, raised per call
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(null)


def _pose(min_confidence: float):
    """One MediaPipe Pose graph per confidence per process (building one costs ~0.1 s; static-image mode keeps
    no state between calls, so every camera and frame shares it)."""
    if min_confidence not in _POSE:
        try:
            with _quiet():
                import mediapipe as mp
        except ImportError as exc:
            raise NodeError(f"key.person needs mediapipe 0.10.14 ({exc}): {INSTALL}") from None
        if getattr(mp, "__version__", "") != "0.10.14":
            raise NodeError(f"key.person needs mediapipe 0.10.14 (found {mp.__version__}: later wheels ship no "
                            f"models and would download them): {INSTALL}")
        with _quiet():
            _POSE[min_confidence] = mp.solutions.pose.Pose(static_image_mode=True, model_complexity=1,
                                                           enable_segmentation=True,
                                                           min_detection_confidence=min_confidence)
    return _POSE[min_confidence]


def person_matte(rgb: np.ndarray, min_confidence: float = 0.5) -> tuple[np.ndarray, np.ndarray | None]:
    """(alpha float32 (H, W) 0..1, landmarks (33, 4) float64 [x px, y px, visibility, depth] or None) of the most
    prominent person in one RGB uint8 image; alpha is all 0 where no person is found."""
    pose = _pose(min_confidence)
    with _quiet():
        out = pose.process(np.ascontiguousarray(rgb[..., :3]))
    h, w = rgb.shape[:2]
    if out.segmentation_mask is None or out.pose_landmarks is None:
        return np.zeros((h, w), np.float32), None
    lm = np.array([[p.x * w, p.y * h, p.visibility, p.z * w] for p in out.pose_landmarks.landmark], np.float64)
    return np.clip(out.segmentation_mask.astype(np.float32), 0, 1), lm
