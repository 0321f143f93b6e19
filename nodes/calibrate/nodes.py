"""The `calibrate` node: a rig from checkerboard images or videos (sources.py -> board.py -> bundle.py)."""
from __future__ import annotations

import json
import tempfile
from pathlib import Path

from nodegraph import REQUIRED, InPath, Node, NodeError, Output, Param, Table
from nodegraph.types import Files
from nodes.common import calibration
from nodes.common.types import CameraSet

from .board import Board
from .bundle import calibrate_views
from .sources import detect_all, find


class Calibrate(Node):
    """Calibrate a camera rig from a checkerboard or a ChArUco board: intrinsics per camera from its own board images (or video
    frames), extrinsics from shots where several cameras see the board at once, then one bundle adjustment over
    all cameras and board poses with outliers dropped; per-camera reprojection RMS in the report. Writes OpenCV
    YAML (one per camera), COLMAP text and a Pose2Sim/anipose TOML under ``out``. Without extrinsic shots it
    gives the intrinsics only (no ``cameras``). The world is the board of the shot seen by the most cameras
    (metres; ``capture`` then puts it upright)."""

    type_name = "calibrate"
    version = 1
    publishes = True
    outputs = {
        "cameras": Output(CameraSet, "the calibrated rig (None without extrinsic shots)", optional=True),
        "report": Output(Table, "reprojection RMS and max per camera (px), views used and dropped, intrinsics, the "
                         "OpenCV start's RMS, the reference shot and the world frame"),
        "files": Files,
    }
    params = {
        "path": Param(InPath, doc="folder holding the board images or videos"),
        "board": Param(list, REQUIRED, item=int, length=2, doc="inner corners [along a row, along a column], e.g. "
                       "[9, 6]; one even and one odd for extrinsic shots"),
        "square": Param(float, REQUIRED, range=(1e-4, 10.0), doc="side of a square in metres"),
        "marker": Param(float, 0.0, range=(0.0, 10.0), doc="ChArUco: side of a marker in metres (0 = a plain "
                        "checkerboard); the board has (cols + 1) x (rows + 1) squares and partial views count"),
        "dictionary": Param(str, "DICT_4X4_50", doc="ChArUco: the ArUco dictionary (OpenCV's name)"),
        "intrinsics": Param(str, "intrinsics/{name}/*", doc="pattern of each camera's own board images or videos "
                            "({name} = camera, * = any); '' = none"),
        "extrinsics": Param(str, "", doc="pattern of the shared shots ({name}, {shot} = the same instant in every "
                            "camera; or synchronised videos); '' = intrinsics only"),
        "cameras": Param(list, [], item=str, doc="camera names (order of the output); [] = every {name} found"),
        "every": Param(int, 10, range=(1, 10000), doc="videos: use every k-th frame"),
        "k3": Param(bool, False, doc="also fit the third radial coefficient k3 (wide lenses)"),
        "outlier_px": Param(float, 2.0, range=(0.1, 100.0), doc="views and corners with errors above "
                            "max(outlier_px, 5 x the median) are dropped before the final solve"),
        "out": Param(str, "calibration", doc="folder of the written files, relative to the run's output folder"),
    }

    def run(self, *, path, board, square, marker, dictionary, intrinsics, extrinsics, cameras, every, k3, outlier_px,
            out):
        root = Path(path)
        if not root.is_dir():
            raise NodeError(f"calibrate: {root} is not a folder")
        b = Board(board[0], board[1], square, marker, dictionary)
        if not intrinsics and not extrinsics:
            raise NodeError("calibrate: give an intrinsics or an extrinsics pattern (or both)")
        if extrinsics and not b.unambiguous:
            raise NodeError(f"calibrate: board {b.cols}x{b.rows} looks the same turned half round, so cameras sharing a "
                            f"shot could number its corners differently: use one even and one odd count (e.g. "
                            f"{b.cols}x{b.rows + 1})")
        names = list(cameras) or None
        srcs = {k: find(root, p, k, names) if p else [] for k, p in (("intrinsics", intrinsics), ("extrinsics", extrinsics))}
        found = sorted({s.name for v in srcs.values() for s in v})
        if not found:
            raise NodeError(f"calibrate: no file under {root} matches "
                            + " or ".join(f"'{p}'" for p in (intrinsics, extrinsics) if p))
        names = names or found
        missing = [n for n in names if n not in found]
        if missing:
            raise NodeError(f"calibrate: no board images for camera(s) {', '.join(missing)}")
        sizes: dict = {}
        views, counts = [], {}
        for kind, s in srcs.items():
            v, c = detect_all(s, names, b, every, kind == "extrinsics", sizes, root)
            views += v
            for n, (f, t) in c.items():
                counts.setdefault(n, {})[kind] = {"found": f, "images": t}
        if not views:
            looked = sum(t["images"] for c in counts.values() for t in c.values())
            raise NodeError(f"calibrate: a {b.cols}x{b.rows} board was found in none of the {looked} images: check "
                            f"'board' (inner corners, not squares: a board of 10x7 squares has 9x6)")
        if extrinsics and not any(v.shared for v in views):
            looked = sum(c.get("extrinsics", {}).get("images", 0) for c in counts.values())
            raise NodeError(f"calibrate: the board was found in none of the {looked} shared images ('{extrinsics}'), so "
                            f"no camera can be placed: the board is too small or too far in those views (markers of a "
                            f"ChArUco board need about 5 pixels a cell)")
        sol = calibrate_views(views, names, [sizes[n] for n in names], b.object_points(), k3=k3, outlier_px=outlier_px)
        for row in sol.report["cameras"]:
            row["detected"] = counts.get(row["camera"], {})
            if row["rms_px"] > 1.0:
                self.log.warning(f"camera '{row['camera']}': reprojection RMS {row['rms_px']:.2f} px (> 1 px: blurred or "
                                 f"mis-detected boards, or a lens the model does not fit; try k3: true)")
        report = {**sol.report, "board": [b.cols, b.rows], "square_m": b.square,
                  **({"charuco": {"marker_m": b.marker, "dictionary": b.dictionary}} if b.charuco else {})}
        return {"cameras": sol.cameras, "report": report, "files": _files(sol, report, out)}


def _files(sol, report: dict, out: str) -> dict:
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        if sol.cameras is not None:
            calibration.save_opencv(sol.cameras, d / "opencv")
            calibration.save_colmap(sol.cameras, d / "colmap")
            calibration.save_toml(sol.cameras, d / "Calib.toml", error=report["rms_px"])
        else:
            calibration.save_opencv(sol.intrinsics, d / "opencv", pose=False)
        (d / "report.json").write_text(json.dumps(report, indent=1))
        return {f"{out}/{p.relative_to(d).as_posix()}": p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}
