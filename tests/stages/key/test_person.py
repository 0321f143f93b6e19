"""key.person: the learned person matte (MediaPipe Pose segmentation, its model inside the mediapipe 0.10.14
wheel) on the synthetic figure with exact silhouettes, a view with nobody in it, the refusal without mediapipe, a
golden; and (realdata) pose2sim_single, where neither a plate nor a green screen exists."""
from __future__ import annotations

import sys

import numpy as np
import pytest

from nodegraph.errors import NodeError
from nodegraph.testing import run_node
from nodes.common.types import ImageSet, Masks, MaskSet


def iou(a, b) -> float:
    a, b = np.asarray(a) > 127, np.asarray(b) > 127
    return float((a & b).sum() / max((a | b).sum(), 1))


@pytest.fixture(scope="module")
def figure():
    return run_node("synth", params={"scene": "figure", "cameras": 6, "width": 320, "height": 240,
                                     "background": "plate"}, frame=0)


def test_person_matte_finds_the_figure(figure):
    out = run_node("key.person", {"images": figure["images"]}, roundtrip=True)
    scores = [iou(m, t) for m, t in zip(out["masks"].masks, figure["masks"].masks)]
    assert min(scores) > 0.94 and np.mean(scores) > 0.96, np.round(scores, 3)   # measured 0.970-0.988
    assert all(0 <= a.min() and a.max() <= 1 for a in out["masks"].alpha)
    kp = out["keypoints"]
    assert kp["landmarks"][0] == "nose" and len(kp["landmarks"]) == 33
    for v, (name, cam) in enumerate(kp["cameras"].items()):
        assert cam["found"]
        pts = np.array(cam["points"])
        mask = figure["masks"].masks[v] > 0
        hips = pts[[23, 24]]                                         # inside the silhouette, where they are seen
        inside = [mask[int(round(y)), int(round(x))] for x, y, vis in hips if vis > 0.5]
        assert inside and all(inside), (name, hips)


def test_view_with_nobody_is_empty_and_says_so(figure, caplog):
    plate = figure["background"]
    images = ImageSet([figure["images"].images[0], plate.images[1]], ["a", "b"])
    out = run_node("key.person", {"images": images})
    assert out["masks"].masks[0].any() and not out["masks"].masks[1].any()
    assert out["keypoints"]["cameras"]["b"] == {"found": False, "points": None}
    assert "camera 'b': no person found" in caplog.text


def test_refused_without_mediapipe(figure, monkeypatch):
    from nodes.key import person

    monkeypatch.setattr(person, "_POSE", {})
    monkeypatch.setitem(sys.modules, "mediapipe", None)              # import mediapipe -> ImportError
    with pytest.raises(NodeError, match=r"key.person needs mediapipe 0.10.14 .*--no-deps"):
        run_node("key.person", {"images": figure["images"]})


def test_person_golden(figure, golden):
    small = ImageSet([im[::2, ::2].copy() for im in figure["images"].images[:2]], figure["images"].names[:2])
    out = run_node("key.person", {"images": small})
    masks = MaskSet(out["masks"].masks, None, small.names)           # the binary mattes (the soft alpha: 96 kB of EXR)
    golden.check("key_person_figure", masks, Masks, iou=0.97)


@pytest.mark.realdata
def test_pose2sim_person_mattes_agree_through_the_four_view_hull(data_dir):
    """pose2sim_single frame 0 (clutter, other people in two views, no plate): the person matte of every view
    agrees with the 4-view hull the four carve (IoU of matte and hull silhouette >= 0.82 each, 0.85 mean; measured
    0.845-0.94), and every view finds the subject's 33 landmarks."""
    cap = run_node("capture", params={"path": str(data_dir / "pose2sim_single")}, frame=0)
    out = run_node("key.person", {"images": cap["images"]})
    assert all(c["found"] for c in out["keypoints"]["cameras"].values())
    masks = run_node("key.cleanup", {"masks": out["masks"]})["masks"]
    bounds = run_node("bounds", {"masks": masks, "cameras": cap["cameras"]})["bounds"]
    vol = run_node("hull", {"masks": masks, "cameras": cap["cameras"], "bounds": bounds},
                   {"resolution": 128, "floor": True})["volume"]
    mesh = run_node("mc", {"volume": vol}, {"largest": True})["mesh"]
    lo, hi = mesh.bounds
    assert -0.02 < lo[2] < 0.1 and 1.6 < hi[2] < 2.1, mesh.bounds    # a standing adult on the treadmill (z 0)
    score = run_node("eval.silhouette", {"mesh": mesh, "cameras": cap["cameras"], "masks": masks})["report"]
    assert score["mean_iou"] >= 0.85 and score["min_iou"] >= 0.82, score
