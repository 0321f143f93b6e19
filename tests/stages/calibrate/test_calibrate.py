"""calibrate: the NumPy camera model against OpenCV, the board's canonical corner order on rendered boards, a
synthetic rig of known truth (8 cameras with distortion, boards held close and shared shots in the middle), the
written files read back, the CLI, the refusals, and the Qualisys intrinsics of pose2sim_single."""
from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from nodegraph.errors import NodeError
from nodegraph.testing import run_node
from nodes.calibrate.board import Board, detect
from nodes.calibrate.bundle import CAM_PARAMS, project, rodrigues
from nodes.common import calibration
from nodes.synth.boards import background_for, board_rig, render_board, write_board_capture

BOARD = Board(9, 6, 0.08)
SHARED = "extrinsics/{name}/{shot}.png"


def test_rodrigues_and_projection_are_opencvs():
    rng = np.random.default_rng(0)
    r = rng.normal(size=(20, 3))
    r[0] = 0
    r[1] = 1e-14
    for v, R in zip(r, rodrigues(r)):
        assert np.abs(R - cv2.Rodrigues(v)[0]).max() < 1e-12
    cam = np.array([800, 810, 320, 240, -0.2, 0.05, 1e-3, -2e-3, 0.01, 0.1, -0.2, 0.05, 0.1, -0.05, 2.0])
    shot = np.array([0.3, 0.1, -0.2, -0.2, -0.1, 0.3])
    obj = BOARD.object_points()
    ours = project(np.repeat(cam[None], len(obj), 0), np.repeat(shot[None], len(obj), 0), obj)
    R = cv2.Rodrigues(cam[9:12])[0] @ cv2.Rodrigues(shot[:3])[0]
    t = cv2.Rodrigues(cam[9:12])[0] @ shot[3:] + cam[12:]
    K = np.array([[cam[0], 0, cam[2]], [0, cam[1], cam[3]], [0, 0, 1]])
    ref = cv2.projectPoints(obj, cv2.Rodrigues(R)[0], t, K, cam[4:9])[0].reshape(-1, 2)
    assert np.abs(ours - ref).max() < 1e-9
    assert CAM_PARAMS[:4] == ("fx", "fy", "cx", "cy")


@pytest.mark.parametrize("roll", [0, 90, 180, 270])
def test_detect_gives_the_board_order_at_any_roll(roll):
    """The corners come in the board's order however the board is turned in its plane (OpenCV's own order turns
    with it): every detected corner lies on the true projection of the same corner."""
    cam = board_rig(1, 640, 480)[0]
    R = cam.Rt[:, :3]
    a = math.radians(roll + 10)
    Rb = R.T @ np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    centre = cam.center + 1.6 * (R.T @ [0, 0, 1.0])
    tb = centre - Rb @ np.array([4 * BOARD.square, 2.5 * BOARD.square, 0])
    img = render_board(cam, Rb, tb, BOARD, background_for(cam, 0), rng=np.random.default_rng(1))
    uv = detect(img, BOARD)
    assert uv is not None
    Rc, tc = R @ Rb, R @ tb + cam.Rt[:, 3]
    ref = cv2.projectPoints(BOARD.object_points(), cv2.Rodrigues(Rc)[0], tc, cam.K, cam.dist)[0].reshape(-1, 2)
    assert np.abs(uv - ref).max() < 0.3


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """8 cameras 640x360 round a 3 m ring, 5 close boards each and 12 shared shots: folder, truth, node output."""
    folder = tmp_path_factory.mktemp("boards")
    cams = board_rig(8, 640, 360)
    truth = write_board_capture(folder, cams, BOARD, intrinsic=5, shared=12)
    out = run_node("calibrate", params={"path": str(folder), "board": [9, 6], "square": 0.08, "extrinsics": SHARED})
    return folder, truth, out


def errors(truth, out):
    """Per camera: focal error (%), principal point error (px), rotation error (deg), centre error (mm), in the
    frame of the reference shot's board (the calibration's world)."""
    ref = int(out["report"]["reference_shot"].split(":")[1])
    Rb, tb = truth["shots"][ref]
    rows = []
    for c, e in zip(truth["cameras"], out["cameras"]):
        R, t = c.Rt[:, :3] @ Rb, c.Rt[:, :3] @ tb + c.Rt[:, 3]
        rot = math.degrees(math.acos(np.clip((np.trace(R.T @ e.Rt[:, :3]) - 1) / 2, -1, 1)))
        rows.append((100 * abs(e.K[0, 0] / c.K[0, 0] - 1), np.abs(e.K[:2, 2] - c.K[:2, 2]).max(), rot,
                     1000 * np.linalg.norm(-R.T @ t - e.center)))
    return np.array(rows)


@pytest.mark.slow
def test_synthetic_rig_is_found(rig):
    """Known truth (noise 2 grey levels, blur 0.7 px): focal within 0.5 %, principal point within 2.5 px, rotation
    within 0.25 deg, centre within 15 mm at 3 m; sub-0.15 px RMS, under half the OpenCV start's (per-camera
    calibrations, shot poses chained from single views)."""
    _, truth, out = rig
    err = errors(truth, out)
    assert err[:, 0].max() < 0.5 and err[:, 1].max() < 2.5, err
    assert err[:, 2].max() < 0.25 and err[:, 3].max() < 15, err
    r = out["report"]
    assert r["rms_px"] < 0.15 and r["shared_shots"] >= 10 and not r["dropped_views"]
    assert np.mean([c["start_rms_px"] for c in r["cameras"]]) > 2 * r["rms_px"]
    for c, e in zip(truth["cameras"], out["cameras"]):
        assert abs(e.dist[0] - c.dist[0]) < 0.01 and (e.width, e.height) == (640, 360)
    # the reported standard deviations are honest: the true errors of fx fy cx cy in units of them (measured:
    # median 0.92, 94 % under 3)
    z = np.abs([(row[k] - c.K[i, j]) / row["sigma"][k] for c, row in zip(truth["cameras"], r["cameras"])
                for k, (i, j) in (("fx", (0, 0)), ("fy", (1, 1)), ("cx", (0, 2)), ("cy", (1, 2)))])
    assert np.median(z) < 1.5 and np.mean(z < 3) > 0.8 and z.max() < 6, z


@pytest.mark.slow
def test_golden_synthetic_rig(rig, golden):
    """Intrinsics and centres of the synthetic rig (0.05 px / 0.5 mm: detection is exact arithmetic on the same
    images, the solver stops at a relative cost change of 1e-5)."""
    _, _, out = rig
    table = {c.name: {"fx": c.K[0, 0], "fy": c.K[1, 1], "cx": c.K[0, 2], "cy": c.K[1, 2], "k1": c.dist[0],
                      "centre_mm": (1000 * c.center).tolist()} for c in out["cameras"]}
    golden.check("calibrate_rig_8", table, __import__("nodegraph").Table, atol=0.05, rtol=0)


@pytest.mark.slow
def test_written_files_read_back_as_the_same_rig(rig, tmp_path):
    """OpenCV YAML (one per camera), COLMAP text and the Pose2Sim TOML project as the node's cameras (1e-6 px)."""
    _, _, out = rig
    for rel, data in out["files"].items():
        p = tmp_path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)
    cal = tmp_path / "calibration"
    cams = out["cameras"]
    loaded = {"toml": calibration.load_cameras(cal / "Calib.toml"),
              "colmap": calibration.load_cameras(cal / "colmap"),
              "opencv": [calibration.read_opencv(cal / "opencv" / f"{c.name}.yml")[0] for c in cams]}
    X = np.random.default_rng(0).uniform(-0.5, 0.5, (100, 3)) + [0.3, 0.2, -1.0]
    for fmt, got in loaded.items():
        for v, c in enumerate(cams):
            g = got[v]
            assert g.name == c.name and (g.width, g.height) == (c.width, c.height), fmt
            a = cv2.projectPoints(X, cv2.Rodrigues(c.Rt[:, :3])[0], c.Rt[:, 3], c.K, c.dist)[0]
            b = cv2.projectPoints(X, cv2.Rodrigues(g.Rt[:, :3])[0], g.Rt[:, 3], g.K, g.dist)[0]
            assert np.abs(a - b).max() < 1e-6, fmt
    report = json.loads((cal / "report.json").read_text())
    assert report["rms_px"] == out["report"]["rms_px"]


@pytest.mark.slow
def test_cli_calibrates_a_folder(rig, tmp_path, capsys):
    from nodegraph.cli import main

    folder, _, out = rig
    rc = main(["--cache", str(tmp_path / "cache"), "calibrate", str(folder), "--board", "9x6", "--square", "0.08",
               "--extrinsics", SHARED, "--out", str(tmp_path / "out")])
    text = capsys.readouterr().out
    assert rc == 0
    assert "cam08" in text and "all: RMS" in text
    assert (tmp_path / "out/calibrate.yaml").is_file()
    got = calibration.load_cameras(tmp_path / "out/calibration/Calib.toml")
    assert np.allclose([c.K for c in got], [c.K for c in out["cameras"]], atol=1e-9)


def small_folder(tmp_path, cams=3, shared=6):
    rig = board_rig(cams, 480, 360, radius=2.0)
    write_board_capture(tmp_path, rig, BOARD, intrinsic=5, shared=shared, ss=2)
    return rig


def node(path, **params):
    return run_node("calibrate", params={"path": str(path), "board": [9, 6], "square": 0.08, **params})


def test_intrinsics_only_gives_no_rig(tmp_path):
    small_folder(tmp_path, cams=2, shared=0)
    out = node(tmp_path)
    assert out["cameras"] is None
    assert out["report"]["world"].startswith("none")
    assert sorted(out["files"]) == ["calibration/opencv/cam01.yml", "calibration/opencv/cam02.yml",
                                    "calibration/report.json"]
    assert out["report"]["rms_px"] < 0.3


def test_refusals_name_the_problem(tmp_path):
    small_folder(tmp_path, cams=2, shared=2)
    cases = [
        (dict(board=[9, 7], extrinsics=SHARED), "half round"),                # symmetric board with shared shots
        (dict(board=[12, 9]), "found in none of the"),                        # wrong corner count
        (dict(intrinsics="intrinsics/cam01/*", cameras=["cam01", "cam02"]), "no {name} field"),
        (dict(intrinsics="", extrinsics="extrinsics/{name}/*.png"), "needs {shot}"),
        (dict(intrinsics="nothing/{name}/*.png"), "no file under"),
        (dict(cameras=["cam01", "cam09"]), "cam09"),
        (dict(intrinsics="", extrinsics=""), "give an intrinsics or an extrinsics"),

    ]
    for params, words in cases:
        with pytest.raises(NodeError, match=words.replace("{", r"\{").replace("}", r"\}")):
            node(tmp_path, **params)


def test_too_few_views_and_unlinked_cameras_are_refused(tmp_path):
    small_folder(tmp_path, cams=2, shared=0)
    for f in sorted((tmp_path / "intrinsics/cam02").glob("*.png"))[2:]:
        f.unlink()
    with pytest.raises(NodeError, match="camera 'cam02': the board was found in 2 image"):
        node(tmp_path)
    # two cameras opposite each other: no shared shot sees both
    other = tmp_path / "pair"
    rig = board_rig(4, 480, 360, radius=2.0)
    write_board_capture(other, rig, BOARD, intrinsic=5, shared=4, ss=2)
    for name in ("cam02", "cam04"):
        for f in (other / "intrinsics" / name).glob("*.png"):
            f.unlink()
        (other / "extrinsics" / name).rename(other / f"unused_{name}")
    with pytest.raises(NodeError, match="share no shot"):
        run_node("calibrate", params={"path": str(other), "board": [9, 6], "square": 0.08, "extrinsics": SHARED,
                                      "cameras": ["cam01", "cam03"]})


def test_shared_shots_without_a_board_are_refused_not_dropped(tmp_path):
    """Extrinsics asked for but the board found in none of them: an error, not a quiet intrinsics-only result."""
    small_folder(tmp_path, cams=2, shared=2)
    for f in (tmp_path / "extrinsics").rglob("*.png"):
        cv2.imwrite(str(f), np.full((360, 480), 128, np.uint8))
    with pytest.raises(NodeError, match="found in none of the 4 shared images"):
        node(tmp_path, extrinsics=SHARED)


def test_images_of_one_camera_must_share_a_size(tmp_path):
    small_folder(tmp_path, cams=1, shared=0)
    f = sorted((tmp_path / "intrinsics/cam01").glob("*.png"))[0]
    cv2.imwrite(str(f), cv2.resize(cv2.imread(str(f)), (240, 135)))
    with pytest.raises(NodeError, match="240x135"):
        node(tmp_path)


@pytest.mark.slow
@pytest.mark.realdata
def test_pose2sim_intrinsics_match_qualisys(dataset_run, data_dir):
    """The graph graphs/calibrate_pose2sim.yaml on the demo's checkerboard images (4x7, 60 mm): focal lengths
    within 1 % of the Qualisys calibration, principal points within 50 px (measured: 20-43 px; 6 views of a
    hand-held board pin the focal length, not the centre), RMS under 0.5 px."""
    from pathlib import Path

    from conftest import output

    graph = Path(__file__).resolve().parents[3] / "graphs" / "calibrate_pose2sim.yaml"
    res = dataset_run(graph)
    report = output(res, "calibrate", "report")
    qualisys = calibration.load_cameras(data_dir / "pose2sim_single/calibration/Calib.qca.txt", image_sizes=(1088, 1920))
    assert [c["camera"] for c in report["cameras"]] == qualisys.names
    for row, q in zip(report["cameras"], qualisys):
        assert abs(row["fx"] / q.K[0, 0] - 1) < 0.01 and abs(row["fy"] / q.K[1, 1] - 1) < 0.01, (row, q.K)
        assert abs(row["cx"] - q.K[0, 2]) < 50 and abs(row["cy"] - q.K[1, 2]) < 50, (row, q.K)
        assert row["rms_px"] < 0.5 and row["views"] >= 6
        assert 0 < row["sigma"]["cx"] < 10
    assert output(res, "calibrate", "cameras") is None


def test_videos_are_read_frame_by_frame(tmp_path):
    """The same boards as videos (MJPG .avi): every frame a view, the frame number the shot of the shared ones;
    the rig agrees with the one from the still images (the views found within one per camera, focal lengths within
    0.5 %)."""
    small_folder(tmp_path, cams=4, shared=16)
    names = ["cam01", "cam02", "cam03", "cam04"]
    for kind, video in (("intrinsics", "intr"), ("extrinsics", "ext")):
        (tmp_path / video).mkdir()
        for n in names:
            frames = [cv2.imread(str(f)) for f in sorted((tmp_path / kind / n).glob("*.png"))]
            h, w = frames[0].shape[:2]
            vw = cv2.VideoWriter(str(tmp_path / video / f"{n}.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10, (w, h))
            for f in frames:
                vw.write(f)
            vw.release()
    stills = node(tmp_path, extrinsics=SHARED, cameras=names)
    videos = node(tmp_path, intrinsics="intr/{name}.avi", extrinsics="ext/{name}.avi", cameras=names, every=1)
    assert abs(videos["report"]["shared_shots"] - stills["report"]["shared_shots"]) <= 1
    assert videos["report"]["shared_shots"] >= 8
    for a, b in zip(stills["report"]["cameras"], videos["report"]["cameras"]):
        assert abs(a["views"] - b["views"]) <= 1  # JPEG frames: a marginal board may be found in one, not the other
        assert abs(a["fx"] / b["fx"] - 1) < 0.005
    assert videos["cameras"] is not None and videos["report"]["rms_px"] < 0.3


def test_charuco_partial_views_calibrate_the_rig(tmp_path):
    """A ChArUco board (9x6 inner corners, 120 mm squares, 90 mm markers, OpenCV's board image rendered into 4
    cameras of 640x480 at 2 m): partial views count, so
    more corners are used than whole boards give; the rig's truth is found (focal within 1 %, rotation 0.3 deg,
    centre 20 mm at 2 m)."""
    board = Board(9, 6, 0.12, marker=0.09)
    rig = board_rig(4, 640, 480, radius=2.0)
    truth = write_board_capture(tmp_path, rig, board, intrinsic=5, shared=16, ss=2)
    out = run_node("calibrate", params={"path": str(tmp_path), "board": [9, 6], "square": 0.12, "marker": 0.09,
                                        "extrinsics": SHARED})
    r = out["report"]
    assert r["charuco"] == {"marker_m": 0.09, "dictionary": "DICT_4X4_50"}
    assert any(c["corners"] < 54 * c["views"] for c in r["cameras"])      # some views are partial
    err = errors(truth, out)
    assert err[:, 0].max() < 1.0 and err[:, 2].max() < 0.3 and err[:, 3].max() < 20, err
    assert r["rms_px"] < 0.3
    for params, words in ((dict(marker=0.2), "smaller than the square"), (dict(marker=0.06, dictionary="DICT_9"), "unknown ArUco")):
        with pytest.raises(NodeError, match=words):
            node(tmp_path, **params)


@pytest.mark.slow
def test_calibrated_rig_carves_the_hull_the_true_rig_carves(rig):
    """The use of a calibration: the same silhouettes (two balls, drawn with the true cameras) give, through
    bounds -> hull -> mc -> eval.silhouette with the calibrated cameras, the silhouette IoU of the true rig within
    0.01, and the same volume in cubic metres within 3 % (the board fixes the scale). Measured: IoU 0.9790 vs
    0.9765, volume 0.08362 vs 0.08374 m^3 (-0.14 %)."""
    import trimesh

    from nodes.common.types import MaskSet

    _, truth, out = rig
    u = np.random.default_rng(0).normal(size=(3000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    balls = [(np.array([0.0, 0.0, 1.0]), 0.25), (np.array([0.2, 0.1, 1.35]), 0.15)]
    true_cams = truth["cameras"]
    masks = []
    for v, cam in enumerate(true_cams):
        m = np.zeros((cam.height, cam.width), np.uint8)
        for c, r in balls:
            uv, _ = true_cams.project(c + r * u, v)
            cv2.fillPoly(m, [cv2.convexHull(np.round(uv * 16).astype(np.int32))], 255, cv2.LINE_8, shift=4)
        masks.append(m)
    masks = MaskSet(masks)
    scores = {}
    for label, cams in (("true", true_cams), ("calibrated", out["cameras"])):
        bounds = run_node("bounds", {"masks": masks, "cameras": cams})["bounds"]
        volume = run_node("hull", {"masks": masks, "cameras": cams, "bounds": bounds}, {"resolution": 96})["volume"]
        mesh = run_node("mc", {"volume": volume})["mesh"]
        report = run_node("eval.silhouette", {"mesh": mesh, "masks": masks, "cameras": cams})["report"]
        scores[label] = (report["mean_iou"], abs(trimesh.Trimesh(mesh.vertices, mesh.faces).volume))
    assert scores["true"][0] > 0.9, scores
    assert scores["calibrated"][0] >= scores["true"][0] - 0.01, scores
    assert abs(scores["calibrated"][1] / scores["true"][1] - 1) < 0.03, scores
