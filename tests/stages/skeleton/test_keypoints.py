"""skeleton.keypoints: body landmarks from several views triangulated into 3D points: exact projections through
distorted cameras come back, a view that saw something else is dropped, two views that disagree give no point,
refusals; a golden; and (realdata) pose2sim_single, where a real person's bone lengths stay constant."""
from __future__ import annotations

import numpy as np
import pytest

import rig
from nodegraph import Table
from nodegraph.errors import NodeError
from nodegraph.testing import run_node
from nodes.common.cameras import Camera, Cameras


def distorted_rig(n=5):
    cams = rig.ring_rig(n, 640, 480, radius=4.0, z=1.0, fov=50)
    return Cameras([Camera(c.name, c.width, c.height, c.K, c.Rt, np.array([-0.12, 0.03, 0.001, -0.001, 0.0]))
                    for c in cams])


def table_of(cams, X, vis=1.0, edit=None):
    cams_pts = {}
    for v, c in enumerate(cams):
        uv = cams.project(X, v)[0]
        pts = np.hstack([uv, np.full((len(X), 1), vis)])
        if edit:
            pts = edit(v, pts)
        cams_pts[c.name] = {"found": True, "points": pts.tolist()}
    return {"landmarks": [f"p{i}" for i in range(len(X))], "cameras": cams_pts}


def test_exact_projections_come_back_and_an_outlier_view_is_dropped():
    cams = distorted_rig()
    X = np.random.default_rng(0).normal([0, 0, 1.0], 0.3, (12, 3))
    out = run_node("skeleton.keypoints", {"keypoints": table_of(cams, X), "cameras": cams})["points"]
    got = np.array(out["points"])
    assert np.abs(got - X).max() < 1e-5 and out["views"] == [5] * 12 and max(out["rms_px"]) < 1e-3

    def wrong(v, pts):                  # view 2 saw another person: its landmarks 80 px off
        return pts + ([80.0, -60.0, 0] if v == 2 else 0)
    out = run_node("skeleton.keypoints", {"keypoints": table_of(cams, X, edit=wrong), "cameras": cams})["points"]
    assert np.abs(np.array(out["points"]) - X).max() < 1e-5 and out["views"] == [4] * 12

    def unseen(v, pts):                 # landmark 0 seen by one view only; 1 by two that disagree; 2 hidden (vis)
        pts = pts.copy()
        pts[0, 2] = 0.9 if v == 0 else 0.1
        pts[1, 2] = 0.9 if v < 2 else 0.1
        pts[1, :2] += 200 if v == 1 else 0
        return pts
    out = run_node("skeleton.keypoints", {"keypoints": table_of(cams, X, edit=unseen), "cameras": cams})["points"]
    assert out["points"][0] is None and out["points"][1] is None and out["views"][:2] == [0, 0]
    assert out["points"][2] is not None and out["views"][2] == 5


def test_refusals():
    cams = distorted_rig(3)
    X = np.zeros((2, 3)) + [0, 0, 1.0]
    with pytest.raises(NodeError, match="not key.person's table"):
        run_node("skeleton.keypoints", {"keypoints": {"rows": []}, "cameras": cams})
    t = table_of(cams, X)
    t["cameras"]["elsewhere"] = t["cameras"].pop(cams.names[0])
    with pytest.raises(NodeError, match=r"cameras \['elsewhere'\] of the keypoints are not in the rig"):
        run_node("skeleton.keypoints", {"keypoints": t, "cameras": cams})


def test_keypoints_golden(golden):
    """Noisy projections (1 px) of 6 points into 4 distorted cameras (NumPy only: the same on any CPU, to 1e-6)."""
    cams = distorted_rig(4)
    rng = np.random.default_rng(3)
    X = rng.normal([0, 0, 1.0], 0.4, (6, 3))
    t = table_of(cams, X, edit=lambda v, p: p + np.hstack([rng.normal(0, 1.0, (len(p), 2)), np.zeros((len(p), 1))]))
    out = run_node("skeleton.keypoints", {"keypoints": t, "cameras": cams})["points"]
    assert all(0.3 < r < 2.0 for r in out["rms_px"]), out["rms_px"]             # 1 px of noise per view
    golden.check("skeleton_keypoints_noisy", {k: out[k] for k in ("landmarks", "points", "views")}, Table,
                 atol=2e-5)                                                        # points kept to 10 um


@pytest.mark.realdata
def test_pose2sim_bone_lengths_stay_constant(data_dir):
    """A real adult walking (pose2sim_single, every 10th frame of 100, 4 views): thigh, shin, upper arm and forearm
    lengths from the triangulated landmarks stay constant (median absolute deviation under 2 cm; measured 0.5-1.5;
    at most one frame in ten off by more than 5 cm: frame 80's right wrist, a 9 cm forearm), left and right agree
    within 3 cm, and the landmarks reproject within 25 px (median; measured 14 px on 1080x1920)."""
    lengths, rms = {}, []
    for f in range(0, 100, 10):
        cap = run_node("capture", params={"path": str(data_dir / "pose2sim_single")}, frame=f)
        kp = run_node("key.person", {"images": cap["images"]})["keypoints"]
        out = run_node("skeleton.keypoints", {"keypoints": kp, "cameras": cap["cameras"]})["points"]
        P = dict(zip(out["landmarks"], out["points"]))
        rms += [r for r in out["rms_px"] if r is not None]
        for a, b in (("hip", "knee"), ("knee", "ankle"), ("shoulder", "elbow"), ("elbow", "wrist")):
            for side in ("left", "right"):
                pa, pb = P[f"{side}_{a}"], P[f"{side}_{b}"]
                assert pa is not None and pb is not None, (f, side, a, b)
                lengths.setdefault((a, b), {}).setdefault(side, []).append(np.linalg.norm(np.subtract(pa, pb)))
    assert np.median(rms) < 25, np.median(rms)
    for bone, sides in lengths.items():
        for side, v in sides.items():
            dev = np.abs(np.array(v) - np.median(v))
            assert np.median(dev) < 0.02 and (dev > 0.05).sum() <= 1, (bone, side, np.round(v, 3))
        assert abs(np.median(sides["left"]) - np.median(sides["right"])) < 0.03, bone
        assert 0.2 < np.median(sides["left"]) < 0.5, bone
