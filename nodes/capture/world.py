"""The capture's world frame: +Z up, metres, origin on the floor under the subject (right-handed).

Every stage after capture works in this frame, so every export says the truth without a per-format trick:
USD ``upAxis`` Z and ``metersPerUnit`` 1 as written, glTF (+Y up, metres) by the one fixed change of basis in
nodes/common/gltf.py. A dataset's own frame is anything (camera 0's frame with y down in tenths of a metre,
a floor board in millimetres with -Z up, ...); the frame is found, in this order of trust:

    up      the graph's ``up`` (a vector in the dataset's frame), else the layout's (layouts.yaml), else the
            direction most orthogonal to every camera's image-right vector (cameras stand upright on a stage,
            however they pitch towards the subject), signed like their image-up vectors
    units   the graph's ``units`` (metres per dataset unit), else the layout's, else 1 (said in the report)
    origin  the graph's ``origin`` (a point in the dataset's frame, on the floor), else: horizontally the centre
            of the subject (a coarse visual hull of the masks of frame ``origin_frame``; without masks the point
            nearest to all optical axes), vertically the layout's ``floor`` (its height along ``up`` in dataset
            units), else the subject's lowest point
The horizontal axes keep the dataset's: world x is the dataset's x made horizontal (its y when x is near up).
The frame of a dataset is one for all its frames (found from ``origin_frame``, never from the frame loaded).
Warnings when it is implausible: a subject not 0.05-4 m tall (wrong units?), most cameras below the floor
(up upside down?), the stated up more than 45 degrees from the cameras' (wrong layout up?), cameras whose ups
disagree (rolled cameras: Middlebury's images are turned 90 degrees, its layout states +y).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nodegraph import NodeError
from nodes.common.cameras import Camera, Cameras

AXES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}
SUBJECT_HEIGHT_M = (0.05, 4.0)   # outside: a warning (units?)
UP_DISAGREE_DEG = 45.0
CAMERAS_AGREE = 0.5              # the mean of the cameras' unit up vectors is shorter: they do not agree


@dataclass(frozen=True)
class WorldFrame:
    """X_world = scale * rotation @ (X_dataset - origin); rotation's rows are the world axes in the dataset."""
    rotation: np.ndarray
    scale: float
    origin: np.ndarray

    @classmethod
    def identity(cls) -> "WorldFrame":
        return cls(np.eye(3), 1.0, np.zeros(3))

    @classmethod
    def from_report(cls, report: dict) -> "WorldFrame":
        """The frame a capture node's ``world`` report describes (identity for world: dataset)."""
        if report.get("frame") != "world":
            return cls.identity()
        return cls(_axes(np.asarray(report["up_dataset"], np.float64)), float(report["metres_per_unit"]),
                   np.asarray(report["origin_dataset"], np.float64))

    def points(self, X) -> np.ndarray:
        """Dataset points (N, 3) in the world frame."""
        return self.scale * (np.asarray(X, np.float64) - self.origin) @ self.rotation.T

    def camera(self, c: Camera) -> Camera:
        """The camera seeing the same pixels for world points: metric cameras keep K and an orthonormal R
        (the camera frame scales with the world: x_cam' = scale x_cam); bare-P cameras P' = P H^-1."""
        Q, s, o = self.rotation, self.scale, self.origin
        if c.metric:
            R, t = c.Rt[:, :3], c.Rt[:, 3]
            Rt = np.column_stack([R @ Q.T, s * (R @ o + t)])
        else:
            M, p = c.Rt[:, :3], c.Rt[:, 3]
            Rt = np.column_stack([M @ Q.T / s, M @ o + p])
        return Camera(c.name, c.width, c.height, c.K, Rt, c.dist, c.metric, c.zsign)

    def cameras(self, cams: Cameras) -> Cameras:
        return Cameras([self.camera(c) for c in cams])


def camera_axes(cams: Cameras) -> tuple[np.ndarray, np.ndarray]:
    """(ups, rights), each (N, 3) unit vectors per camera: the world directions that move a point at the image
    centre up and right in the image, perpendicular to the viewing ray (bare-P and mirrored calibrations alike)."""
    ups, rights = [], []
    for v, c in enumerate(cams):
        o, d = cams.rays(v, [[c.width / 2, c.height / 2]])
        o, d = o[0], d[0]
        dist = max(1.0, float(np.linalg.norm(o)))
        X0 = o + d * dist
        eps = 1e-4 * dist
        J = np.array([(cams.project(X0 + eps * e, v)[0][0] - cams.project(X0 - eps * e, v)[0][0]) / (2 * eps)
                      for e in np.eye(3)]).T                      # (2, 3): d(u, v) / dX
        for out, g in ((ups, -J[1]), (rights, J[0])):
            g = g - d * (g @ d)
            out.append(g / (np.linalg.norm(g) or 1.0))
    return np.array(ups), np.array(rights)


def cameras_up(cams: Cameras) -> tuple[np.ndarray, float]:
    """(up, agreement) from the cameras: the direction most orthogonal to every camera's image-right vector
    (upright cameras keep it level however they pitch towards the subject), signed like their mean image-up;
    the mean image-up itself when the right vectors do not span a plane (cameras facing one way). Agreement:
    the length of the mean of the unit image-ups (1: all alike; small: rolled or upside-down cameras)."""
    ups, rights = camera_axes(cams)
    mean = ups.mean(0)
    agree = float(np.linalg.norm(mean))
    mean = mean / (agree or 1.0)
    w, vec = np.linalg.eigh(rights.T @ rights)
    if len(cams) >= 2 and w[1] > 0.05 * w[2]:
        up = vec[:, 0] * (1.0 if vec[:, 0] @ mean >= 0 else -1.0)
    else:
        up = mean - rights.mean(0) * (mean @ rights.mean(0)) / max(rights.mean(0) @ rights.mean(0), 1e-12)
        up /= np.linalg.norm(up) or 1.0
    return up, agree


def look_at_point(cams: Cameras) -> np.ndarray:
    """The point nearest (least squares) to every camera's optical axis (the ray through the image centre)."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for v, c in enumerate(cams):
        o, d = cams.rays(v, [[c.width / 2, c.height / 2]])
        P = np.eye(3) - np.outer(d[0], d[0])
        A += P
        b += P @ o[0]
    return np.linalg.lstsq(A, b, rcond=None)[0]


def _axes(up: np.ndarray) -> np.ndarray:
    """Rotation (rows: world x, y, z) with z = up and x the dataset's x axis levelled (its y when x is within
    25 degrees of up): a stable choice, the same for an up that differs in its last digits."""
    z = up / np.linalg.norm(up)
    a = np.eye(3)[0 if abs(z[0]) < 0.9 else 1]
    x = a - z * (a @ z)
    x /= np.linalg.norm(x)
    return np.array([x, np.cross(z, x), z])


def _vector(value, what: str, node: str, zero: bool = False) -> np.ndarray:
    v = np.asarray(AXES[value] if isinstance(value, str) and value in AXES else value, np.float64).ravel()
    if v.shape != (3,) or not np.all(np.isfinite(v)) or (np.linalg.norm(v) == 0 and not zero):
        raise NodeError(f"{node}: {what} must be three numbers (not all zero) or one of {', '.join(AXES)}, got {value!r}")
    return v


def subject_points(masks, cams: Cameras) -> np.ndarray | None:
    """Voxel centres (N, 3) of a coarse visual hull of ``masks`` (None when too few views see anything)."""
    from nodes.common.bounds import auto_bounds, coarse_hull

    try:
        box = auto_bounds(masks, cams, resolution=32, margin=0.0)
    except NodeError:
        return None
    occ = coarse_hull(masks, cams, box, 64)
    if not occ.any():
        return None
    size = (box[1] - box[0]) / np.array(occ.shape)
    return box[0] + (np.argwhere(occ) + 0.5) * size


def find_world(cams: Cameras, masks, layout: dict, up=None, units: float = 0.0, origin=None,
               node: str = "capture", log=None) -> tuple[WorldFrame, dict]:
    """The world frame of a capture (module docstring) and its report: what was used and where it came from.
    ``masks``: the origin frame's masks (or None); ``layout``: the known layout's world keys (up, units, floor)."""
    report, warnings = {}, []
    cam_up, agree = cameras_up(cams)
    if up is not None and len(up):
        u, report["up_from"] = _vector(up, "up", node), "graph"
    elif layout.get("up"):
        u, report["up_from"] = _vector(layout["up"], "layouts.yaml up", node), "layout"
    else:
        u, report["up_from"] = cam_up, "cameras"
    u = u / np.linalg.norm(u)
    if agree < CAMERAS_AGREE and report["up_from"] == "cameras":
        warnings.append(f"the cameras' up vectors disagree (length of their mean {agree:.2f}: rolled or "
                        "upside-down cameras?): give `up`")
    angle = float(np.degrees(np.arccos(np.clip(u @ cam_up, -1, 1))))
    if report["up_from"] != "cameras" and angle > UP_DISAGREE_DEG and agree >= CAMERAS_AGREE:
        warnings.append(f"the {report['up_from']}'s up is {angle:.0f} degrees from the cameras' mean up "
                        f"{np.round(cam_up, 3).tolist()}: check `up`")
    if units:
        s, report["units_from"] = float(units), "graph"
    elif layout.get("units"):
        s, report["units_from"] = float(layout["units"]), "layout"
    else:
        s, report["units_from"] = 1.0, "assumed metres"
    if not s > 0:
        raise NodeError(f"{node}: units must be positive (metres per dataset unit), got {s}")
    Q = _axes(u)
    pts = subject_points(masks, cams) if masks is not None else None
    if origin is not None and len(origin):
        o, report["origin_from"] = _vector(origin, "origin", node, zero=True), "graph"
    else:
        centre = pts.mean(0) if pts is not None else look_at_point(cams)
        report["origin_from"] = "subject" if pts is not None else "cameras' look-at point"
        if layout.get("floor") is not None:
            floor, report["floor_from"] = float(layout["floor"]), "layout"
        elif pts is not None:
            floor, report["floor_from"] = float((pts @ u).min()), "subject's lowest point"
        else:
            floor, report["floor_from"] = float(centre @ u), "none: the look-at point's height (no masks)"
        o = centre - u * (centre @ u - floor)
    frame = WorldFrame(Q, s, o)
    heights = frame.points(cams.centers)[:, 2]
    report.update(up_dataset=np.round(u, 6).tolist(), metres_per_unit=s, origin_dataset=np.round(o, 6).tolist(),
                  camera_up_dataset=np.round(cam_up, 6).tolist(), up_vs_cameras_deg=round(angle, 2),
                  camera_height_m=[round(float(heights.min()), 4), round(float(heights.max()), 4)])
    if pts is not None:
        w = frame.points(pts)
        lo, hi = w.min(0), w.max(0)
        report["subject_box_m"] = [np.round(lo, 3).tolist(), np.round(hi, 3).tolist()]
        height = float(hi[2] - min(lo[2], 0.0))
        report["subject_height_m"] = round(height, 3)
        if not SUBJECT_HEIGHT_M[0] <= height <= SUBJECT_HEIGHT_M[1]:
            warnings.append(f"the subject is {height:.3g} m tall in the world frame ({s:g} m per dataset unit): "
                            "give `units` (metres per dataset unit)")
    if np.median(heights) < 0:
        warnings.append(f"most cameras are below the floor (heights {heights.min():.2f} to {heights.max():.2f} m): "
                        "is `up` upside down?")
    report["warnings"] = warnings
    for w in warnings if log else ():
        log.warning("%s: world frame: %s", node, w)
    return frame, report
