"""Checkerboard detection in one canonical corner order.

A board of ``cols`` x ``rows`` inner corners and square side ``square`` (metres) has its corners at
(c * square, r * square, 0), row-major (r = 0 .. rows-1, c = 0 .. cols-1), the board's +Z pointing away from a
camera that sees its printed face. OpenCV's ``findChessboardCorners`` returns the grid in any of its four
orientations; ``detect`` turns it into that one order, so that cameras sharing a shot agree on every corner:
    1. handedness: columns flipped if the grid's column and row directions turn the image's way round the
       other way (a camera can only see the printed face, so the image order must keep the board's hand);
    2. half turn: the grid turned 180 degrees if the square between corners (0,0), (0,1), (1,0), (1,1) is the
       lighter of it and its neighbour. A half turn changes that square's colour only when cols + rows is
       odd (4x7, 9x6): boards with cols + rows even are ambiguous and are refused for shared shots.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nodegraph.errors import NodeError


DICTIONARIES = ("DICT_4X4_50", "DICT_4X4_100", "DICT_4X4_250", "DICT_5X5_50", "DICT_5X5_100", "DICT_5X5_250",
                "DICT_6X6_50", "DICT_6X6_250", "DICT_7X7_50", "DICT_ARUCO_ORIGINAL")


@dataclass(frozen=True)
class Board:
    cols: int          # inner corners along a row
    rows: int          # inner corners along a column
    square: float      # side of a square, metres
    marker: float = 0.0            # ChArUco: side of a marker, metres (0 = a plain checkerboard)
    dictionary: str = "DICT_4X4_50"

    def __post_init__(self):
        if self.cols < 2 or self.rows < 2:
            raise NodeError(f"calibrate: board {self.cols}x{self.rows}: needs at least 2x2 inner corners")
        if not self.square > 0:
            raise NodeError(f"calibrate: square {self.square} must be a positive length (metres)")
        if self.marker and not 0 < self.marker < self.square:
            raise NodeError(f"calibrate: marker {self.marker} must be smaller than the square {self.square}")
        if self.marker and self.dictionary not in DICTIONARIES:
            raise NodeError(f"calibrate: unknown ArUco dictionary '{self.dictionary}' (have: {', '.join(DICTIONARIES)})")

    @property
    def charuco(self) -> bool:
        return self.marker > 0

    @property
    def unambiguous(self) -> bool:
        """True when every view numbers the corners the same way: a ChArUco board (its markers say which corner is
        which), or a checkerboard a half turn changes the colours of (cols + rows odd, so cols != rows)."""
        return self.charuco or (self.cols + self.rows) % 2 == 1

    def opencv_charuco(self):
        """cv2.aruco.CharucoBoard of (cols + 1) x (rows + 1) squares; its corner i is our corner i."""
        import cv2

        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols + 1, self.rows + 1), self.square, self.marker, d)

    def object_points(self) -> np.ndarray:
        r, c = np.mgrid[0:self.rows, 0:self.cols]
        return np.stack([c.ravel() * self.square, r.ravel() * self.square, np.zeros(r.size)], axis=1)


def _mean_in(gray: np.ndarray, quad: np.ndarray) -> float:
    """Mean grey value inside a quadrilateral shrunk to half its size about its centre."""
    import cv2

    centre = quad.mean(axis=0)
    poly = (centre + 0.5 * (quad - centre)).astype(np.float32)
    x0, y0 = np.floor(poly.min(axis=0)).astype(int)
    x1, y1 = np.ceil(poly.max(axis=0)).astype(int) + 1
    h, w = gray.shape
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    if x1 <= x0 or y1 <= y0:
        return float(gray[int(np.clip(centre[1], 0, h - 1)), int(np.clip(centre[0], 0, w - 1))])
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillConvexPoly(mask, np.round(poly - [x0, y0]).astype(np.int32), 1)
    patch = gray[y0:y1, x0:x1]
    return float(patch[mask > 0].mean()) if mask.any() else float(patch.mean())


def canonical(grid: np.ndarray, gray: np.ndarray) -> np.ndarray:
    """(rows, cols, 2) corners in OpenCV's order -> the canonical order of the module docstring."""
    a = grid[0, 1] - grid[0, 0]
    b = grid[1, 0] - grid[0, 0]
    if a[0] * b[1] - a[1] * b[0] < 0:
        grid = grid[:, ::-1]
    first = _mean_in(gray, np.array([grid[0, 0], grid[0, 1], grid[1, 1], grid[1, 0]]))
    second = _mean_in(gray, np.array([grid[0, 1], grid[0, 2], grid[1, 2], grid[1, 1]])) if grid.shape[1] > 2 else \
        _mean_in(gray, np.array([grid[1, 0], grid[1, 1], grid[2, 1], grid[2, 0]]))
    if first > second:
        grid = grid[::-1, ::-1]
    return np.ascontiguousarray(grid)


MIN_CHARUCO = 8  # corners a ChArUco view needs (a homography's worth, not all on one line)


def detect_charuco(gray: np.ndarray, board: Board) -> tuple[np.ndarray, np.ndarray] | None:
    """(corner indices, pixels) of the ChArUco corners found (at least MIN_CHARUCO, not all on one row or
    column), or None. Partial views count: the markers say which corners they are."""
    import cv2

    det = cv2.aruco.CharucoDetector(board.opencv_charuco())
    corners, ids, _, _ = det.detectBoard(gray)
    if ids is None or len(ids) < MIN_CHARUCO:
        return None
    ids = ids.ravel().astype(int)
    r, c = ids // board.cols, ids % board.cols
    if len(set(r)) < 2 or len(set(c)) < 2:
        return None
    order = np.argsort(ids)
    return ids[order], corners.reshape(-1, 2)[order].astype(np.float64)


def detect(gray: np.ndarray, board: Board):
    """Inner corners of ``board`` in a grey image (uint8), sub-pixel, canonical order, (rows * cols, 2) float64;
    None when the whole board is not found. A ChArUco board gives (indices, pixels) of the corners found."""
    import cv2

    if board.charuco:
        return detect_charuco(gray, board)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    scale = 1.0
    small = gray
    if max(gray.shape) > 2000:  # detect on a half-size image, refine on the full one
        scale = 0.5
        small = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    ok, corners = cv2.findChessboardCorners(small, (board.cols, board.rows), flags=flags)
    if not ok:
        return None
    corners = corners.reshape(-1, 2).astype(np.float32) / scale
    grid = corners.reshape(board.rows, board.cols, 2)
    step = min(np.linalg.norm(np.diff(grid, axis=0), axis=2).min(), np.linalg.norm(np.diff(grid, axis=1), axis=2).min())
    win = int(np.clip(0.4 * step, 2, 11))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 0.01)
    corners = cv2.cornerSubPix(gray, corners.reshape(-1, 1, 2), (win, win), (-1, -1), crit).reshape(-1, 2)
    grid = canonical(corners.reshape(board.rows, board.cols, 2).astype(np.float64), gray)
    return grid.reshape(-1, 2)
