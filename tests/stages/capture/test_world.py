"""The capture's world frame (nodes/capture/world.py): +Z up, metres, origin on the floor under the subject."""
import numpy as np
import pytest

from nodegraph.testing import run_node
from nodes.capture.world import WorldFrame, find_world
from nodes.common.cameras import Camera, Cameras


@pytest.fixture(scope="module")
def stage():
    """The synth figure (1.7 m, feet on z = 0) and 8 ring cameras: Z-up metres, the truth."""
    return run_node("synth", params={"scene": "figure", "rig": "dome", "cameras": 8, "width": 160, "height": 120})


def to_dataset(rot, scale, shift) -> WorldFrame:
    """The frame X_d = rot @ X / scale + shift of a dataset (another up, unit of ``scale`` metres, origin)."""
    rot = np.asarray(rot, float)
    return WorldFrame(rot, 1.0 / scale, -scale * rot.T @ np.asarray(shift, float))


ROT_Y_DOWN = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])   # world z -> dataset -y (camera-0-like frames)


def test_camera_transform_keeps_every_pixel(stage):
    cams = stage["cameras"]
    frame = WorldFrame(ROT_Y_DOWN, 10.0, np.array([1.0, -2.0, 3.0]))
    X = np.random.default_rng(0).normal([0, 0, 1], 0.4, (40, 3))
    for bare in (False, True):
        src = Cameras([Camera.from_P(c.name, c.P, c.width, c.height) if bare else c for c in cams])
        moved = frame.cameras(src)
        for v in range(len(cams)):
            uv0, z0 = src.project(X, v)
            uv1, z1 = moved.project(frame.points(X), v)
            np.testing.assert_allclose(uv1, uv0, atol=1e-6)
            assert np.all(np.sign(z1) == np.sign(z0))
        if not bare:
            for c in moved:
                np.testing.assert_allclose(c.Rt[:, :3] @ c.Rt[:, :3].T, np.eye(3), atol=1e-12)  # still a rotation


def test_a_camera_zero_frame_in_tenths_comes_back_upright_in_metres(stage):
    """A dataset in camera-0-like axes (up = -y), 0.1 m units, origin 3 m away: up from the cameras, units from
    the layout, floor from a coarse hull of the masks: the figure stands 1.7 m tall on z = 0 again."""
    ds = to_dataset(ROT_Y_DOWN, 0.1, [2.0, 5.0, 30.0])
    truth = np.asarray(stage["mesh"].vertices)
    np.testing.assert_allclose(ds.points(truth), truth @ ROT_Y_DOWN.T / 0.1 + [2.0, 5.0, 30.0], atol=1e-9)
    frame, rep = find_world(ds.cameras(stage["cameras"]), stage["masks"].masks, {"units": 0.1})
    assert rep["up_from"] == "cameras" and rep["units_from"] == "layout" and rep["warnings"] == []
    assert rep["up_vs_cameras_deg"] == 0 and np.degrees(np.arccos(-rep["up_dataset"][1])) < 0.5   # the dome's pitch
    back = frame.points(ds.points(truth))
    assert abs(np.ptp(back[:, 2]) - np.ptp(truth[:, 2])) < 1e-3                     # height kept, in metres
    assert abs(back[:, 2].min()) < 0.03                                               # feet on the floor
    assert abs(rep["subject_height_m"] - np.ptp(truth[:, 2])) < 0.06                  # the coarse hull's estimate
    assert np.abs(back.mean(0)[:2]).max() < 0.1                                       # origin under the subject


def test_graph_overrides_and_warnings(stage):
    cams = to_dataset(ROT_Y_DOWN, 0.1, [0.0, 0.0, 0.0]).cameras(stage["cameras"])
    _, rep = find_world(cams, stage["masks"].masks, {})                   # units unknown: 1 assumed -> 0.17 m tall
    assert rep["units_from"] == "assumed metres" and any("tall" in w for w in rep["warnings"])
    _, rep = find_world(cams, stage["masks"].masks, {}, up=[0, 1, 0], units=0.1)    # upside down
    assert rep["up_from"] == "graph" and any("180 degrees" in w for w in rep["warnings"])
    assert any("below the floor" in w for w in rep["warnings"])
    frame, rep = find_world(cams, None, {"up": "-y", "units": 0.1, "floor": 0.0}, origin=[0, 0, 0])
    assert rep["origin_from"] == "graph" and rep["warnings"] == []
    np.testing.assert_allclose(frame.points([[0, -10.0, 0]]), [[0, 0, 1.0]], atol=1e-12)      # 10 units up = 1 m


def test_capture_node_world_report_maps_the_dataset(tmp_path):
    from tests.stages.capture.test_capture import CENTRE, sphere_rig, write_dataset

    cams = sphere_rig()
    patterns = write_dataset(tmp_path, cams)
    out = run_node("capture", params={"path": str(tmp_path), **patterns}, roundtrip=True)
    rep = out["world"]
    assert rep["frame"] == "world" and rep["up_from"] == "cameras" and rep["origin_from"] == "subject"
    frame = WorldFrame.from_report(rep)
    X = np.random.default_rng(1).normal(CENTRE, 0.3, (30, 3))
    for v in range(len(cams)):
        np.testing.assert_allclose(out["cameras"].project(frame.points(X), v)[0], cams.project(X, v)[0], atol=1e-4)
    ball = frame.points(CENTRE[None])[0]
    assert abs(ball[0]) < 0.05 and abs(ball[1]) < 0.05 and abs(ball[2] - 0.6) < 0.1    # a 0.6 m ball (its hull 7 cm deeper)
    with pytest.raises(Exception, match="three numbers"):
        run_node("capture", params={"path": str(tmp_path), **patterns, "up": [0, 1]})


@pytest.mark.realdata
@pytest.mark.parametrize("name, height", [("thu_wd_human", (1.5, 1.9)), ("inria_dancer", (1.45, 1.9)),
                                          ("child_rope", (1.0, 1.4)), ("nerf_lego", None),
                                          ("middlebury_templeSR", None), ("uu_infomcv_seated", None)])
def test_real_captures_come_in_upright_in_metres(data_dir, name, height):
    """Each dataset's frame: the subject's coarse hull stands on z = 0 with a person's height; cameras above the
    floor, and no warning."""
    rep = run_node("capture", params={"path": str(data_dir / name)})["world"]
    assert rep["warnings"] == [], rep
    assert rep["camera_height_m"][0] > 0, rep
    if height:
        assert height[0] < rep["subject_height_m"] < height[1] and abs(rep["subject_box_m"][0][2]) < 0.1, rep
