"""Camera model shared by every stage.

One camera = (K, Rt, dist, width, height):
    x_cam = Rt @ [X, 1]                      (3x4, world -> camera)
    x_n   = x_cam[:2] / x_cam[2]             (normalised image plane)
    x_d   = distort(x_n, dist)               (OpenCV k1 k2 p1 p2 k3)
    u     = K @ [x_d, 1]                     (pixels, origin at the centre of the top-left pixel)

A camera known only by a bare 3x4 projection matrix P (non-metric datasets such as the Oxford dino,
where decomposing P gives nonsense) is stored as K = I, Rt = P, dist = 0: the same formula then gives
u = dehomog(P X) exactly, and nothing is decomposed. ``metric`` says which of the two it is.
The OpenCL kernels use the very same packing (see ``pack``), so NumPy and OpenCL agree.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field

import numpy as np

from kernels import source
from nodegraph import clrt
from nodegraph.errors import DataError

PACK_FLOATS = 32  # floats per camera in the packed array the kernels read


@dataclass
class Camera:
    name: str
    width: int
    height: int
    K: np.ndarray                     # 3x3 intrinsics (identity for a bare-P camera)
    Rt: np.ndarray                    # 3x4 world -> camera (P itself for a bare-P camera)
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))  # k1 k2 p1 p2 k3
    metric: bool = True               # False: K/Rt come from a bare P and must not be decomposed
    zsign: float = 0.0                # bare P: which sign of w is in front (+1/-1); 0 = sign(det M), right
                                      # for Euclidean frames but not for mirrored ones (Oxford dino)

    def __post_init__(self):
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.Rt = np.asarray(self.Rt, dtype=np.float64).reshape(3, 4)
        d = np.zeros(5)
        src = np.asarray(self.dist, dtype=np.float64).ravel()
        d[: min(5, src.size)] = src[:5]
        self.dist = d
        self.width, self.height = int(self.width), int(self.height)
        values = np.concatenate([self.K.ravel(), self.Rt.ravel(), d])   # one test for all 26 (a frame's 24 cameras
        if not np.isfinite(values).all():                                 # are parsed by every reader of them)
            for label, arr in (("K", self.K), ("R|t", self.Rt), ("distortion", self.dist)):
                if not np.all(np.isfinite(arr)):
                    raise DataError(f"camera '{self.name}': {label} contains NaN or infinity")
        if self.width <= 0 or self.height <= 0:
            raise DataError(f"camera '{self.name}': image size {self.width}x{self.height} is not positive")
        big = float(np.abs(values).max())
        if big > 1e30:  # the kernels read cameras as float32 (max 3.4e38): such values are an error upstream
            raise DataError(f"camera '{self.name}': calibration value {big:.3g} is out of float32 range")
        if self.metric and (self.K[0, 0] <= 0 or self.K[1, 1] <= 0):
            raise DataError(f"camera '{self.name}': focal lengths fx={self.K[0, 0]:g}, fy={self.K[1, 1]:g} must be positive")

    @classmethod
    def from_P(cls, name: str, P, width: int, height: int, zsign: float = 0.0) -> "Camera":
        """A camera known only by its 3x4 projection matrix (kept as is, never decomposed)."""
        return cls(name, width, height, np.eye(3), np.asarray(P, dtype=np.float64), np.zeros(5), metric=False, zsign=zsign)

    @property
    def depth_sign(self) -> float:
        """Factor turning the third coordinate of Rt X into a depth that is positive in front."""
        if self.metric:
            return 1.0
        return float(np.sign(self.zsign) or np.sign(np.linalg.det(self.Rt[:, :3])) or 1.0)

    @property
    def P(self) -> np.ndarray:
        """3x4 projection of the undistorted pinhole part: K @ Rt."""
        return self.K @ self.Rt

    @property
    def center(self) -> np.ndarray:
        """Optical centre in world coordinates (null space of P)."""
        _, _, vt = np.linalg.svd(self.P)
        c = vt[-1]
        return c[:3] / c[3]

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0))

    def cropped(self, x0: int, y0: int, width: int, height: int) -> "Camera":
        """The same camera seeing only the window (x0, y0, width, height) of its image: pixel (u, v) here is
        pixel (u + x0, v + y0) of the full image (principal point shifted; for a bare P, P itself)."""
        shift = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
        if self.metric:
            return Camera(self.name, width, height, shift @ self.K, self.Rt, self.dist, True, self.zsign)
        return Camera(self.name, width, height, self.K, shift @ self.Rt, self.dist, False, self.zsign or self.depth_sign)

    def to_dict(self) -> dict:
        return {"name": self.name, "width": self.width, "height": self.height, "K": self.K.tolist(),
                "Rt": self.Rt.tolist(), "dist": self.dist.tolist(), "metric": self.metric, "zsign": self.zsign}

    @classmethod
    def from_dict(cls, d: dict) -> "Camera":
        return cls(d["name"], d["width"], d["height"], d["K"], d["Rt"], d.get("dist", [0] * 5), d.get("metric", True),
                   d.get("zsign", 0.0))


def distort(xn: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """OpenCV radial-tangential distortion of normalised points (..., 2)."""
    k1, k2, p1, p2, k3 = dist
    x, y = xn[..., 0], xn[..., 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def camera_point_f32(c: np.ndarray, X: np.ndarray):
    """kernels/camera.h ``camera_point``, bit for bit: (x, y, z) of points ``X`` (N, 3 float32) in the camera
    coordinates of the packed camera ``c`` (float32, camera.h's order of operations)."""
    x, y, z = X[:, 0], X[:, 1], X[:, 2]
    return (((c[0] * x + c[1] * y) + c[2] * z) + c[3], ((c[4] * x + c[5] * y) + c[6] * z) + c[7],
            ((c[8] * x + c[9] * y) + c[10] * z) + c[11])


def project_camera_f32(c: np.ndarray, xc) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """kernels/camera.h ``project_camera``, bit for bit: (u, v, depth) of points in camera coordinates ``xc``;
    depth = z * c[24] (> 0 in front of the camera)."""
    f = np.float32
    xr, yr, zr = xc
    with np.errstate(all="ignore"):
        xn, yn = xr / zr, yr / zr
        if np.any(c[17:22] != 0):
            k1, k2, p1, p2, k3 = c[17:22]
            r2 = xn * xn + yn * yn
            radial = f(1) + r2 * (k1 + r2 * (k2 + r2 * k3))
            xd = (xn * radial + ((f(2) * p1) * xn) * yn) + p2 * (r2 + (f(2) * xn) * xn)
            yd = (yn * radial + p1 * (r2 + (f(2) * yn) * yn)) + ((f(2) * p2) * xn) * yn
            xn, yn = xd, yd
        u = (c[12] * xn + c[13] * yn) + c[14]
        v = c[15] * yn + c[16]
    return u, v, zr * c[24]


def project_packed_f32(cam_row: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """NumPy mirror of kernels/camera.h, bit for bit: points ``X`` (N, 3 float32) into the camera ``cam_row``
    (one row of ``Cameras.pack()``), float32 operations in camera.h's order (kernels compiled without FP
    contraction). Returns (u, v, front): pixel coordinates (non-finite behind the camera plane) and the
    in-front test z * cam[24] > 0."""
    c = np.asarray(cam_row).astype(np.float32)
    u, v, depth = project_camera_f32(c, camera_point_f32(c, X))
    return u, v, depth > 0


def unique_names(names: list[str], what: str) -> None:
    """DataError naming the repeated names: per-camera data are stored and matched by name, so two cameras of one
    name would lose one's data in silence."""
    seen, repeated = set(), []
    for n in names:
        if n in seen and n not in repeated:
            repeated.append(n)
        seen.add(n)
    if repeated:
        shown = ", ".join(f"'{n}' ({names.count(n)}x)" for n in repeated[:5])
        raise DataError(f"{what} names must be unique: {shown} of {len(names)}")


class Cameras:
    """An ordered set of cameras (one per view). Indexable and iterable."""

    def __init__(self, cameras: list[Camera]):
        if not cameras:
            raise DataError("a camera set needs at least one camera")
        self.cameras = list(cameras)
        unique_names([c.name for c in self.cameras], "camera")

    def __len__(self):
        return len(self.cameras)

    def __getitem__(self, i) -> Camera:
        return self.cameras[i]

    def __iter__(self):
        return iter(self.cameras)

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    @property
    def centers(self) -> np.ndarray:
        return np.array([c.center for c in self.cameras])

    def project(self, points: np.ndarray, view: int) -> tuple[np.ndarray, np.ndarray]:
        """Project world points (N,3) into view ``view``.

        Returns (uv (N,2) pixels, depth (N,) = camera z, positive in front of the camera).
        """
        cam = self.cameras[view]
        X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        xc = X @ cam.Rt[:, :3].T + cam.Rt[:, 3]
        z = xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xn = xc[:, :2] / z[:, None]
        if cam.has_distortion:
            xn = distort(xn, cam.dist)
        uv = xn @ cam.K[:2, :2].T + cam.K[:2, 2]
        if not cam.metric:
            # bare P: the sign of the third row is arbitrary; 'in front' means the same side as the scene
            z = z * cam.depth_sign
        return uv, z

    def pack(self, origin=None) -> np.ndarray:
        """(N, 32) float32 array read by the OpenCL kernels: Rt (12), K (fx, skew, cx, fy, cy), dist (5),
        width, height, z sign (1 or -1 for bare-P cameras whose third row points backwards), padding.

        ``origin`` (3,): pack for points given relative to ``origin`` (t becomes t + R @ origin, computed in
        float64), so float32 kernels keep their precision far from the world origin. A bare-P camera is
        then packed as K = [[1, 0, u0], [0, 1, v0]] (u0, v0: the origin's pixel) and Rt = K^-1 P, which
        projects identically but keeps the float32 sums small."""
        out = np.zeros((len(self), PACK_FLOATS), dtype=np.float32)
        o = None if origin is None else np.asarray(origin, dtype=np.float64).reshape(3)
        for i, c in enumerate(self.cameras):
            Rt, K = c.Rt.copy(), c.K.copy()
            if o is not None:
                Rt[:, 3] += Rt[:, :3] @ o
                if not c.metric and Rt[2, 3] != 0:
                    K = np.array([[1.0, 0, Rt[0, 3] / Rt[2, 3]], [0, 1.0, Rt[1, 3] / Rt[2, 3]], [0, 0, 1.0]])
                    Rt = np.linalg.solve(K, Rt)
            out[i, 0:12] = Rt.ravel()
            out[i, 12:17] = [K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]]
            out[i, 17:22] = c.dist
            out[i, 22:24] = [c.width, c.height]
            out[i, 24] = c.depth_sign
        return out

    def rays(self, view: int, uv) -> tuple[np.ndarray, np.ndarray]:
        """Viewing rays through pixels ``uv`` (N,2) of view ``view``: (origins (N,3), unit directions (N,3)).

        Distortion is removed with cv2.undistortPointsIter (metric cameras); a point at depth d along the
        ray (d = camera z for metric cameras) projects back onto ``uv``."""
        cam = self.cameras[view]
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if cam.metric:
            if cam.has_distortion:
                import cv2

                crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
                xn = cv2.undistortPointsIter(uv[:, None, :], cam.K, cam.dist, None, None, crit)[:, 0, :]
            else:
                Kinv = np.linalg.inv(cam.K)
                xn = uv @ Kinv[:2, :2].T + Kinv[:2, 2]
            d_cam = np.hstack([xn, np.ones((len(uv), 1))])
            dirs = d_cam @ cam.Rt[:, :3]          # R^T d for every row
        else:
            M = cam.Rt[:, :3]
            dirs = np.linalg.solve(M, np.hstack([uv, np.ones((len(uv), 1))]).T).T * cam.depth_sign
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        return np.repeat(cam.center[None, :], len(uv), axis=0), dirs

    def to_json(self) -> str:
        return json.dumps({"cameras": [c.to_dict() for c in self.cameras]}, indent=1)

    @classmethod
    def from_json(cls, text: str) -> "Cameras":
        return cls([Camera.from_dict(d) for d in json.loads(text)["cameras"]])


def look_at(eye, target, up, fov_deg: float, width: int, height: int, name: str = "cam") -> Camera:
    """A metric pinhole camera at ``eye`` looking at ``target`` (OpenCV axes: x right, y down, z forward)."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    t = -R @ eye
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]])
    return Camera(name, width, height, K, np.hstack([R, t[:, None]]))


class ProjectCL(clrt.Runner):
    """kernels/project.cl: points into every view at once."""

    source = source("project.cl")


def project_points_cl(cameras: Cameras, points, origin=None) -> tuple[np.ndarray, np.ndarray]:
    """OpenCL twin of ``Cameras.project`` for all views at once (kernels/project.cl).

    Points are shifted to ``origin`` (default: their mean) in float64 before the float32 kernel runs.
    Returns (uv (V, N, 2) float64, depth (V, N) float64)."""
    X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n, v = len(X), len(cameras)
    if n == 0:
        return np.zeros((v, 0, 2)), np.zeros((v, 0))
    o = X.mean(axis=0) if origin is None else np.asarray(origin, dtype=np.float64)
    run = ProjectCL.get()
    uv_buf, depth_buf = run.buffer("uv", v * n * 8), run.buffer("depth", v * n * 4)
    run.launch("project_points", (n, v), None, run.upload("cams", cameras.pack(origin=o)),
               run.upload("points", (X - o).astype(np.float32)), np.int32(n), uv_buf, depth_buf)
    uv = run.read(uv_buf, (v, n, 2), np.float32)
    depth = run.read(depth_buf, (v, n), np.float32)
    return uv.astype(np.float64), depth.astype(np.float64)
