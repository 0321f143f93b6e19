"""Synthetic checkerboard captures with known truth, for ``calibrate``: a ring of cameras with distortion and
differing intrinsics, a board held close to each camera (its intrinsic images) and a board in the middle of
the stage seen by several cameras at once (shared shots). Grey images, supersampled, blurred and noisy.

The board is the calibrate stage's (nodes/calibrate/board.py): inner corners at (c * square, r * square, 0),
the square between the first four corners dark, a white margin of half a square, +Z out of the board's back; a
ChArUco board (``marker`` > 0) is OpenCV's own board image mapped onto the same squares.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from nodes.common.cameras import Camera, Cameras, look_at

DARK, LIGHT = 35.0, 215.0


def board_rig(count: int = 12, width: int = 960, height: int = 540, radius: float = 3.0, seed: int = 1) -> Cameras:
    """``count`` cameras round a ring (heights 1.2 and 2.0 m alternating) looking at (0, 0, 1), focal lengths
    within 4 %, principal points within 12 px of the centre, radial and tangential distortion."""
    rng = np.random.default_rng(seed)
    cams = []
    for i in range(count):
        a = 2 * math.pi * i / count
        eye = (radius * math.cos(a), radius * math.sin(a), 1.2 if i % 2 == 0 else 2.0)
        c = look_at(eye, (0, 0, 1.0), (0, 0, 1), 55.0, width, height, name=f"cam{i + 1:02d}")
        K = c.K.copy()
        K[0, 0] *= 1 + rng.uniform(-0.04, 0.04)
        K[1, 1] = K[0, 0] * (1 + rng.uniform(-0.002, 0.002))
        K[:2, 2] += rng.uniform(-12, 12, 2)
        dist = [rng.uniform(-0.15, 0.0), rng.uniform(0.0, 0.08), rng.uniform(-5e-4, 5e-4), rng.uniform(-5e-4, 5e-4), 0.0]
        cams.append(Camera(c.name, width, height, K, c.Rt, dist))
    return Cameras(cams)


def _frame_facing(z, roll: float) -> np.ndarray:
    """A rotation whose third column is ``z`` (board +Z) and whose first is near-horizontal, turned by ``roll``."""
    z = np.asarray(z, float) / np.linalg.norm(z)
    up = np.array([0, 0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0, 0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = math.cos(roll), math.sin(roll)
    return np.stack([c * x + s * y, -s * x + c * y, z], axis=1)


def _tilted(v, max_deg: float, rng) -> np.ndarray:
    axis = np.cross(v, rng.normal(size=3))
    axis /= np.linalg.norm(axis)
    ang = math.radians(rng.uniform(0.3, 1.0) * max_deg)
    v = np.asarray(v, float)
    return v * math.cos(ang) + np.cross(axis, v) * math.sin(ang) + axis * (axis @ v) * (1 - math.cos(ang))


def board_poses(cameras: Cameras, board, intrinsic: int = 6, shared: int = 16, seed: int = 2):
    """Board poses (R board -> world, t): per camera ``intrinsic`` close views filling about half the frame at
    tilts of 10-35 degrees, and ``shared`` shots in the middle of the stage facing round the ring."""
    rng = np.random.default_rng(seed)
    size = np.array([(board.cols - 1) * board.square, (board.rows - 1) * board.square, 0]) / 2
    per_cam = []
    for c in cameras:
        R, C = c.Rt[:, :3], c.center
        span = (board.cols + 2) * board.square
        d = c.K[0, 0] * span / (0.55 * c.width)
        poses = []
        for _ in range(intrinsic):
            off = rng.uniform(-0.18, 0.18, 2) * [c.width / c.K[0, 0], c.height / c.K[1, 1]]
            ray = R.T @ np.array([off[0], off[1], 1.0])
            centre = C + d * rng.uniform(0.85, 1.15) * ray / np.linalg.norm(ray)
            Rb = _frame_facing(_tilted(R.T @ [0, 0, 1.0], 35, rng), rng.uniform(-0.5, 0.5))
            poses.append((Rb, centre - Rb @ size))
        per_cam.append(poses)
    shots = []
    for k in range(shared):
        yaw = 2 * math.pi * (k + rng.uniform(-0.3, 0.3)) / shared
        facing = -np.array([math.cos(yaw), math.sin(yaw), rng.uniform(-0.3, 0.3)])  # +Z away from the cameras it faces
        Rb = _frame_facing(_tilted(facing, 20, rng), rng.uniform(-0.4, 0.4))
        centre = np.array([0, 0, 1.0]) + rng.uniform(-0.25, 0.25, 3)
        shots.append((Rb, centre - Rb @ size))
    return per_cam, shots


def render_board(cam: Camera, Rb: np.ndarray, tb: np.ndarray, board, background: np.ndarray, *, ss: int = 3,
                 blur: float = 0.7, noise: float = 2.0, rng=None) -> np.ndarray:
    """A grey uint8 image of the board at pose (Rb, tb) (board -> world) through ``cam`` (distortion included),
    over ``background`` (float image); ``ss`` x ``ss`` samples per pixel, Gaussian ``blur`` (px), ``noise`` (grey)."""
    import cv2

    rng = rng or np.random.default_rng(0)
    img = background.astype(np.float64).copy()
    R = cam.Rt[:, :3] @ Rb
    t = cam.Rt[:, :3] @ tb + cam.Rt[:, 3]
    n = R[:, 2]
    s, m = board.square, 0.5 * board.square
    x0, x1, y0, y1 = -s - m, board.cols * s + m, -s - m, board.rows * s + m
    if n @ t > 0:  # the printed face looks at the camera
        edge = np.linspace(0, 1, 9)
        outline = np.concatenate([np.stack([x0 + (x1 - x0) * edge, np.full(9, y), np.zeros(9)], 1) for y in (y0, y1)] +
                                 [np.stack([np.full(9, x), y0 + (y1 - y0) * edge, np.zeros(9)], 1) for x in (x0, x1)])
        pc = outline @ R.T + t
        if np.all(pc[:, 2] > 0.05):
            uv = cv2.projectPoints(outline, cv2.Rodrigues(R)[0], t, cam.K, cam.dist)[0].reshape(-1, 2)
            u0, v0 = np.maximum(np.floor(uv.min(0)).astype(int) - 2, 0)
            u1, v1 = np.minimum(np.ceil(uv.max(0)).astype(int) + 3, [cam.width, cam.height])
            if u1 > u0 and v1 > v0:
                off = (np.arange(ss) + 0.5) / ss - 0.5
                uu = (np.arange(u0, u1)[:, None] + off[None]).ravel()
                vv = (np.arange(v0, v1)[:, None] + off[None]).ravel()
                U, V = np.meshgrid(uu, vv)
                pts = np.stack([U.ravel(), V.ravel()], 1).reshape(-1, 1, 2)
                crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-9)
                xn = cv2.undistortPointsIter(pts, cam.K, cam.dist, None, None, crit).reshape(-1, 2)
                d = np.concatenate([xn, np.ones((len(xn), 1))], 1)
                lam = (n @ t) / (d @ n)
                Xb = (lam[:, None] * d - t) @ R
                bx, by = Xb[:, 0], Xb[:, 1]
                inside = (lam > 0) & (bx >= x0) & (bx <= x1) & (by >= y0) & (by <= y1)
                qx, qy = np.floor(bx / s).astype(int), np.floor(by / s).astype(int)
                squares = (qx >= -1) & (qx <= board.cols - 1) & (qy >= -1) & (qy <= board.rows - 1)
                if board.charuco:  # the OpenCV board image, 40 px a square, nearest texel
                    tex = _charuco_texture(board)
                    tx = np.clip(((bx + s) / s * 40).astype(int), 0, tex.shape[1] - 1)
                    ty = np.clip(((by + s) / s * 40).astype(int), 0, tex.shape[0] - 1)
                    val = np.where(squares, DARK + (LIGHT - DARK) * tex[ty, tx] / 255.0, LIGHT)
                else:
                    val = np.where(squares & ((qx + qy) % 2 == 0), DARK, LIGHT)
                H, W = v1 - v0, u1 - u0
                bg = np.repeat(np.repeat(img[v0:v1, u0:u1], ss, 0), ss, 1).ravel()
                sample = np.where(inside, val, bg).reshape(H, ss, W, ss)
                img[v0:v1, u0:u1] = sample.mean(axis=(1, 3))
    if blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    img += rng.normal(0, noise, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


_TEXTURES: dict = {}


def _charuco_texture(board) -> np.ndarray:
    if board not in _TEXTURES:
        size = ((board.cols + 1) * 40, (board.rows + 1) * 40)
        _TEXTURES[board] = board.opencv_charuco().generateImage(size, marginSize=0).astype(np.float64)
    return _TEXTURES[board]


def background_for(cam: Camera, seed: int) -> np.ndarray:
    import cv2

    rng = np.random.default_rng(seed)
    low = rng.uniform(70, 170, (max(2, cam.height // 40), max(2, cam.width // 40)))
    return cv2.resize(low, (cam.width, cam.height), interpolation=cv2.INTER_CUBIC)


def write_board_capture(folder, cameras: Cameras, board, *, intrinsic: int = 6, shared: int = 16, blur: float = 0.7,
                        noise: float = 2.0, seed: int = 2, ss: int = 3) -> dict:
    """Render and write ``intrinsics/<camera>/NN.png`` and ``extrinsics/<camera>/SSS.png`` (every camera at every
    shared shot, whether it sees the board or not). Returns the truth: cameras and board poses."""
    import cv2

    folder = Path(folder)
    per_cam, shots = board_poses(cameras, board, intrinsic, shared, seed)
    rng = np.random.default_rng(seed + 1)
    for i, c in enumerate(cameras):
        bg = background_for(c, seed + 10 + i)
        for kind, poses in (("intrinsics", per_cam[i]), ("extrinsics", shots)):
            d = folder / kind / c.name
            d.mkdir(parents=True, exist_ok=True)
            for k, (Rb, tb) in enumerate(poses):
                img = render_board(c, Rb, tb, board, bg, ss=ss, blur=blur, noise=noise, rng=rng)
                cv2.imwrite(str(d / f"{k:03d}.png"), img)
    return {"cameras": cameras, "shots": shots, "intrinsic_poses": per_cam}
