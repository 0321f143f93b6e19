"""calibrate on synthetic boards of known truth (a ring of 12 cameras with distortion, boards held close to each
camera and shared shots in the middle of the stage) through the CLI (`volcap calibrate`), against the plain
OpenCV route a user would otherwise script (cv2.calibrateCamera per camera, camera poses chained through the shared
shots from single views: the calibration's start, before the bundle adjustment), same detections, same run; and
pose2sim_single's checkerboard intrinsics against its Qualisys calibration.

    python bench/calibrate.py [--cameras 12] [--width 960] [--height 540]
"""
from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from machine import describe, load_average  # noqa: E402
from nodes.calibrate.board import Board  # noqa: E402
from nodes.calibrate.bundle import calibrate_views  # noqa: E402
from nodes.calibrate.sources import detect_all, find  # noqa: E402
from nodes.common import calibration  # noqa: E402
from nodes.synth.boards import board_rig, write_board_capture  # noqa: E402

BOARD = Board(9, 6, 0.08)
CHARUCO = Board(9, 6, 0.12, marker=0.09)  # bigger: 4x4 markers need ~5 px a cell across the stage
SHARED = "extrinsics/{name}/{shot}.png"


def cli(folder: Path, out: Path, board: Board, *extra) -> float:
    t = time.perf_counter()
    charuco = ["--marker", str(board.marker), "--dictionary", board.dictionary] if board.charuco else []
    subprocess.run([sys.executable, str(ROOT / "app.py"), "--cache", str(out / "cache"), "calibrate", str(folder),
                    "--board", f"{board.cols}x{board.rows}", "--square", str(board.square), "--out", str(out),
                    *charuco, *extra],
                   check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t


def errors(truth_cams, shot, cams) -> np.ndarray:
    Rb, tb = shot
    rows = []
    for c, e in zip(truth_cams, cams):
        R, t = c.Rt[:, :3] @ Rb, c.Rt[:, :3] @ tb + c.Rt[:, 3]
        rot = math.degrees(math.acos(np.clip((np.trace(R.T @ e.Rt[:, :3]) - 1) / 2, -1, 1)))
        rows.append((100 * abs(e.K[0, 0] / c.K[0, 0] - 1), np.abs(e.K[:2, 2] - c.K[:2, 2]).max(), rot,
                     1000 * np.linalg.norm(-R.T @ t - e.center)))
    return np.array(rows)


def synthetic(args, board: Board, noise: float, blur: float, tmp: Path) -> list[str]:
    kind = "ChArUco" if board.charuco else "checkerboard"
    folder = tmp / f"boards_{kind}_{noise}_{blur}"
    cams = board_rig(args.cameras, args.width, args.height)
    t = time.perf_counter()
    truth = write_board_capture(folder, cams, board, intrinsic=args.intrinsic, shared=args.shared, noise=noise, blur=blur)
    render_s = time.perf_counter() - t
    out = tmp / f"out_{kind}_{noise}_{blur}"
    ours_s = cli(folder, out, board, "--extrinsics", SHARED)
    report = json.loads((out / "calibration/report.json").read_text())
    ours = calibration.load_cameras(out / "calibration" / "Calib.toml")
    ref = truth["shots"][int(report["reference_shot"].split(":")[1])]
    # the plain OpenCV route on the same detections: detection time + cv2.calibrateCamera per camera + chaining
    names = ours.names
    t = time.perf_counter()
    sizes: dict = {}
    views = []
    for what, pat in (("intrinsics", "intrinsics/{name}/*"), ("extrinsics", SHARED)):
        views += detect_all(find(folder, pat, what, names), names, board, 10, what == "extrinsics", sizes, folder)[0]
    detect_s = time.perf_counter() - t
    import cv2

    t = time.perf_counter()
    for c in range(len(names)):
        vs = [v for v in views if v.cam == c]
        cv2.calibrateCamera([board.object_points()[v.ids].astype(np.float32) for v in vs], [v.uv.astype(np.float32) for v in vs],
                            sizes[names[c]], None, None, flags=cv2.CALIB_FIX_K3)
    opencv_s = detect_s + time.perf_counter() - t
    sol = calibrate_views(views, names, [sizes[n] for n in names], board.object_points())
    e_ours, e_cv = errors(cams, ref, ours), errors(cams, ref, sol.start)
    start_rms = float(np.sqrt(np.mean([c["start_rms_px"] ** 2 for c in report["cameras"]])))
    label = f"{kind}, {args.cameras} cams {args.width}x{args.height}, noise {noise}, blur {blur} px"
    rows = []
    for what, e, rms, sec in (("OpenCV per camera + chained poses", e_cv, start_rms, opencv_s),
                              ("volcap calibrate (CLI, bundle adjusted)", e_ours, report["rms_px"], ours_s)):
        rows.append(f"| {label} | {what} | {np.median(e[:, 0]):.3f} / {e[:, 0].max():.3f} | "
                    f"{np.median(e[:, 1]):.2f} / {e[:, 1].max():.2f} | {np.median(e[:, 2]):.3f} / {e[:, 2].max():.3f} | "
                    f"{np.median(e[:, 3]):.1f} / {e[:, 3].max():.1f} | {rms:.3f} | {sec:.1f} |")
    print(f"  {label}: rendered {render_s:.1f} s; {len(views)} views, {report['shared_shots']} shared shots, "
          f"dropped {len(report['dropped_views'])} views; load {load_average()}", flush=True)
    return rows


def pose2sim(tmp: Path, data: Path) -> list[str]:
    folder = data / "pose2sim_single/calibration/intrinsics"
    if not folder.is_dir():
        return [f"(pose2sim_single not found under {data})"]
    out = tmp / "p2s"
    board = "4x7"
    t = time.perf_counter()
    subprocess.run([sys.executable, str(ROOT / "app.py"), "--cache", str(out / "cache"), "calibrate", str(folder),
                    "--board", board, "--square", "0.06", "--intrinsics", "int_{name}_img/*.jpg", "--out", str(out)],
                   check=True, stdout=subprocess.DEVNULL)
    sec = time.perf_counter() - t
    report = json.loads((out / "calibration/report.json").read_text())
    q = calibration.load_cameras(data / "pose2sim_single/calibration/Calib.qca.txt", image_sizes=(1088, 1920))
    rows = ["| camera | views found | fx ours / Qualisys (diff %) | cx ours ± σ / Qualisys | cy ours ± σ / Qualisys | k1 ours / Qualisys | RMS px |",
            "|---|---|---|---|---|---|---|"]
    for r, c in zip(report["cameras"], q):
        d = r["detected"]["intrinsics"]
        rows.append(f"| {r['camera']} | {d['found']} of {d['images']} | {r['fx']:.1f} / {c.K[0, 0]:.1f} "
                    f"({100 * (r['fx'] / c.K[0, 0] - 1):+.2f}) | {r['cx']:.1f} ± {r['sigma']['cx']:.1f} / {c.K[0, 2]:.1f} | "
                    f"{r['cy']:.1f} ± {r['sigma']['cy']:.1f} / "
                    f"{c.K[1, 2]:.1f} | {r['k1']:+.4f} / {c.dist[0]:+.4f} | {r['rms_px']:.3f} |")
    rows.append(f"(CLI {sec:.1f} s for the four cameras)")
    rows.append(f"picture: {picture(folder, report)}")
    return rows


def picture(folder: Path, report: dict) -> Path:
    """docs/calibrate_pose2sim.jpg: each camera's first board image, the detected corners (green circles) and the
    corners reprojected through our intrinsics and the view's own pose (red crosses, errors drawn 20x longer)."""
    import cv2

    from nodes.calibrate.board import detect

    board = Board(4, 7, 0.06)
    tiles = []
    for r in report["cameras"]:
        K = np.array([[r["fx"], 0, r["cx"]], [0, r["fy"], r["cy"]], [0, 0, 1]])
        dist = np.array([r[k] for k in ("k1", "k2", "p1", "p2", "k3")])
        for f in sorted((folder / f"int_{r['camera']}_img").glob("*.jpg")):
            img = cv2.imread(str(f))
            uv = detect(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), board)
            if uv is not None:
                break
        ok, rv, tv = cv2.solvePnP(board.object_points(), uv, K, dist)
        rep = cv2.projectPoints(board.object_points(), rv, tv, K, dist)[0].reshape(-1, 2)
        for a, b in zip(uv, rep):
            cv2.circle(img, tuple(np.round(a).astype(int)), 9, (0, 200, 0), 2)
            tip = a + 20 * (b - a)
            cv2.line(img, tuple(np.round(a).astype(int)), tuple(np.round(tip).astype(int)), (0, 0, 255), 2)
            cv2.drawMarker(img, tuple(np.round(tip).astype(int)), (0, 0, 255), cv2.MARKER_CROSS, 12, 2)
        cv2.putText(img, f"{r['camera']} {f.name}: RMS {r['rms_px']:.2f} px", (20, 60), cv2.FONT_HERSHEY_SIMPLEX, 1.6,
                    (255, 255, 255), 4)
        tiles.append(cv2.resize(img, (img.shape[1] * 640 // img.shape[0], 640), interpolation=cv2.INTER_AREA))
    out = ROOT / "docs" / "calibrate_pose2sim.jpg"
    cv2.imwrite(str(out), np.hstack(tiles), [cv2.IMWRITE_JPEG_QUALITY, 85])
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--cameras", type=int, default=12)
    ap.add_argument("--width", type=int, default=960)
    ap.add_argument("--height", type=int, default=540)
    ap.add_argument("--intrinsic", type=int, default=6)
    ap.add_argument("--shared", type=int, default=16)
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    args = ap.parse_args()
    print(describe(), flush=True)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        rows = ["| capture | route | focal error % (median / max) | principal point px | rotation deg | centre mm | "
                "RMS px | seconds |", "|---|---|---|---|---|---|---|---|"]
        for board, noise, blur in ((BOARD, 2.0, 0.7), (BOARD, 6.0, 1.5), (CHARUCO, 6.0, 1.5)):
            rows += synthetic(args, board, noise, blur, tmp)
        print(describe())
        print("\n".join(rows))
        print("\npose2sim_single intrinsics (4x7 board, 60 mm) vs its Qualisys calibration:")
        print("\n".join(pose2sim(tmp, Path(args.data))))
    print(f"load after: {load_average()}")


if __name__ == "__main__":
    main()
