"""Rig calibration from board views: OpenCV's per-camera calibration as the start, then one bundle adjustment.

A *view* is one detected board image: a camera, a *shot* (the board's pose at one instant; a shot seen by several
cameras ties them together), the corners' pixels. Unknowns:
    per camera  fx fy cx cy k1 k2 p1 p2 [k3], and its pose world -> camera (rotation vector, translation)
    per shot    the board's pose board -> world
The world is the board of the *reference shot* (the shared shot seen by the most cameras): +Z out of the board's
back, metres (the square's unit). Without shared shots there is no rig, only intrinsics: each camera's pose is
then fixed at the identity and every shot is a board -> camera pose.

Start (what a plain OpenCV script gives): ``cv2.calibrateCamera`` per camera on all its views (intrinsics and a
board pose per view), then camera and shot poses chained from the reference shot through the shots breadth
first. Then ``scipy.optimize.least_squares`` over every corner of every view (sparse Jacobian: a corner depends
on its camera and its shot only), with a soft-L1 loss of 1 px (stopping when an iteration lowers the cost by less than 1e-5 of it: on the
synthetic rig the last 80 iterations of a tighter stop moved no error figure in its third digit); views whose median error is more than
``max(outlier_px, 5 x the median)`` and single corners beyond it are dropped, and the problem is solved again with
a plain squared loss. Per camera the reprojection RMS of what is kept is reported, and the standard deviations
of fx fy cx cy (Gauss-Newton covariance at the solution).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nodegraph.errors import NodeError
from nodes.common.cameras import Camera, Cameras, distort

CAM_PARAMS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "rx", "ry", "rz", "tx", "ty", "tz")
NC, NS = len(CAM_PARAMS), 6


@dataclass
class View:
    cam: int
    shot: str           # the same string in two cameras = the same instant
    uv: np.ndarray      # (n, 2) corners (board.detect)
    source: str         # file (and frame) it came from, for messages
    shared: bool        # from the extrinsics (synchronised) set
    ids: np.ndarray     # (n,) which board corners they are (all of them for a checkerboard)


def rodrigues(r: np.ndarray) -> np.ndarray:
    """Rotation matrices (M, 3, 3) of rotation vectors (M, 3) (cv2.Rodrigues, vectorised)."""
    r = np.asarray(r, dtype=np.float64).reshape(-1, 3)
    th = np.linalg.norm(r, axis=1)
    small = th < 1e-12
    k = r / np.where(small, 1.0, th)[:, None]
    Kx = np.zeros((len(r), 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2], Kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    Kx -= Kx.transpose(0, 2, 1)
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    R = np.eye(3)[None] + s * Kx + (1 - c) * (Kx @ Kx)
    if small.any():  # first order: I + [r]x
        rx = np.zeros((small.sum(), 3, 3))
        rs = r[small]
        rx[:, 0, 1], rx[:, 0, 2], rx[:, 1, 2] = -rs[:, 2], rs[:, 1], -rs[:, 0]
        R[small] = np.eye(3)[None] + rx - rx.transpose(0, 2, 1)
    return R


def _rvec(R: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(R, dtype=np.float64))[0].ravel()


def _pose(R, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, np.ravel(t)
    return T


def project(cam: np.ndarray, shot: np.ndarray, obj: np.ndarray) -> np.ndarray:
    """Pixels of board points ``obj`` (P, 3) seen by cameras ``cam`` (P, 15: CAM_PARAMS) with the board at
    ``shot`` (P, 6: board -> world rotation vector, translation). Same model as nodes.common.cameras."""
    Rs, Rc = rodrigues(shot[:, :3]), rodrigues(cam[:, 9:12])
    Xw = np.einsum("pij,pj->pi", Rs, obj) + shot[:, 3:]
    Xc = np.einsum("pij,pj->pi", Rc, Xw) + cam[:, 12:15]
    z = Xc[:, 2:3]
    xn = Xc[:, :2] / np.where(np.abs(z) < 1e-12, 1e-12, z)
    xd = distort(xn, cam[:, 4:9].T)
    return np.stack([cam[:, 0] * xd[:, 0] + cam[:, 2], cam[:, 1] * xd[:, 1] + cam[:, 3]], axis=1)


def _sigmas(res, free: np.ndarray, ncam: int) -> np.ndarray:
    """Standard deviations of the parameters at the solution (NaN where fixed): the diagonal of
    (J^T J)^-1 scaled by the residuals' variance 2 cost / (m - n), the Gauss-Newton covariance under
    independent pixel noise (what the data pin, not what a different rig of views would give)."""
    J = res.jac
    JtJ = (J.T @ J).toarray() if hasattr(J, "toarray") else J.T @ J
    m, n = J.shape
    s2 = 2 * res.cost / max(m - n, 1)
    out = np.full(free.size, np.nan)
    try:
        out[np.flatnonzero(free)] = np.sqrt(np.clip(np.diag(np.linalg.inv(JtJ)), 0, None) * s2)
    except np.linalg.LinAlgError:
        pass
    return out


@dataclass
class Solution:
    cameras: Cameras | None   # None without shared shots (intrinsics only: Rt = [I | 0])
    intrinsics: Cameras       # every camera with its intrinsics (Rt of the rig, or [I | 0])
    report: dict
    start: Cameras | None     # the OpenCV start (before the bundle adjustment), for comparison


def calibrate_views(views: list[View], names: list[str], sizes: list[tuple[int, int]], obj: np.ndarray, *,
                    k3: bool = False, outlier_px: float = 2.0, min_views: int = 3) -> Solution:
    import cv2

    ncam = len(names)
    per_cam = [[v for v in views if v.cam == c] for c in range(ncam)]
    for c, vs in enumerate(per_cam):
        if len(vs) < min_views:
            raise NodeError(f"calibrate: camera '{names[c]}': the board was found in {len(vs)} image(s), at least "
                            f"{min_views} are needed (different tilts of the board, filling the frame)")
    flags = 0 if k3 else cv2.CALIB_FIX_K3
    K0, D0, board_in_cam = [], [], {}
    for c, vs in enumerate(per_cam):
        w, h = sizes[c]
        o = [obj[v.ids].astype(np.float32) for v in vs]
        p = [v.uv.astype(np.float32) for v in vs]
        try:
            _, K, D, rv, tv = cv2.calibrateCamera(o, p, (w, h), None, None, flags=flags)
        except cv2.error as exc:
            raise NodeError(f"calibrate: camera '{names[c]}': OpenCV could not calibrate it from {len(vs)} views "
                            f"({exc.err}); give views with the board tilted in different directions") from None
        K0.append(K)
        D0.append(np.pad(D.ravel()[:5], (0, max(0, 5 - D.size))))
        for v, r, t in zip(vs, rv, tv):
            board_in_cam[(c, v.shot)] = _pose(cv2.Rodrigues(r)[0], t)

    shots = sorted({v.shot for v in views})
    shot_index = {s: i for i, s in enumerate(shots)}
    shared = sorted({v.shot for v in views if v.shared})
    seen_by = {s: sorted({v.cam for v in views if v.shot == s}) for s in shots}
    cam_pose = [None] * ncam
    shot_pose: dict[str, np.ndarray] = {}
    ref = None
    if shared:
        ref = max(shared, key=lambda s: (len(seen_by[s]), -shared.index(s)))
        shot_pose[ref] = np.eye(4)
        changed = True
        while changed:  # breadth first over the camera - shot graph
            changed = False
            for s in shots:
                for c in seen_by[s]:
                    if s in shot_pose and cam_pose[c] is None:
                        cam_pose[c] = board_in_cam[(c, s)] @ np.linalg.inv(shot_pose[s])
                        changed = True
                    elif cam_pose[c] is not None and s not in shot_pose:
                        shot_pose[s] = np.linalg.inv(cam_pose[c]) @ board_in_cam[(c, s)]
                        changed = True
        lost = [names[c] for c in range(ncam) if cam_pose[c] is None]
        if lost:
            linked = [names[c] for c in range(ncam) if cam_pose[c] is not None]
            raise NodeError(f"calibrate: camera(s) {', '.join(lost)} share no shot (directly or through other cameras) "
                            f"with {', '.join(linked)}: add extrinsic shots where the board is seen by cameras of both "
                            f"groups at once")
    fixed_pose = [False] * ncam
    for c in range(ncam):
        if cam_pose[c] is None:  # intrinsics only: the camera is the world
            cam_pose[c], fixed_pose[c] = np.eye(4), True
            for v in per_cam[c]:
                shot_pose[v.shot] = board_in_cam[(c, v.shot)]

    x = np.zeros(ncam * NC + len(shots) * NS)
    free = np.ones_like(x, dtype=bool)
    for c in range(ncam):
        K, D, T = K0[c], D0[c], cam_pose[c]
        x[c * NC:(c + 1) * NC] = [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *D, *_rvec(T[:3, :3]), *T[:3, 3]]
        if not k3:
            free[c * NC + 8] = False
        if fixed_pose[c]:
            free[c * NC + 9:(c + 1) * NC] = False
    for s, i in shot_index.items():
        T = shot_pose[s]
        x[ncam * NC + i * NS: ncam * NC + (i + 1) * NS] = [*_rvec(T[:3, :3]), *T[:3, 3]]
    if ref is not None:
        free[ncam * NC + shot_index[ref] * NS: ncam * NC + (shot_index[ref] + 1) * NS] = False
    x_start = x.copy()

    keep = [np.ones(len(v.ids), bool) for v in views]
    use = np.ones(len(views), bool)

    def arrays():
        vi = [i for i in range(len(views)) if use[i]]
        cam = np.concatenate([np.full(keep[i].sum(), views[i].cam) for i in vi])
        shot = np.concatenate([np.full(keep[i].sum(), shot_index[views[i].shot]) for i in vi])
        pts = np.concatenate([obj[views[i].ids][keep[i]] for i in vi])
        uv = np.concatenate([views[i].uv[keep[i]] for i in vi])
        return cam, shot, pts, uv

    def residual_fn(cam, shot, pts, uv):
        def fun(xf):
            xx = x.copy()
            xx[free] = xf
            C = xx[:ncam * NC].reshape(ncam, NC)
            S = xx[ncam * NC:].reshape(len(shots), NS)
            return (project(C[cam], S[shot], pts) - uv).ravel()
        return fun

    def sparsity(cam, shot):
        from scipy.sparse import coo_matrix

        P = len(cam)
        rows = np.repeat(np.arange(2 * P), NC + NS)
        cc = (cam[:, None] * NC + np.arange(NC)[None]).repeat(2, axis=0)
        sc = (ncam * NC + shot[:, None] * NS + np.arange(NS)[None]).repeat(2, axis=0)
        cols = np.concatenate([cc, sc], axis=1).ravel()
        J = coo_matrix((np.ones(rows.size, np.int8), (rows, cols)), shape=(2 * P, x.size)).tocsc()
        return J[:, np.flatnonzero(free)]

    iterations = []

    def solve(loss):
        from scipy.optimize import least_squares

        cam, shot, pts, uv = arrays()
        fun = residual_fn(cam, shot, pts, uv)
        res = least_squares(fun, x[free], jac_sparsity=sparsity(cam, shot), loss=loss, f_scale=1.0,
                            x_scale="jac", method="trf", xtol=1e-8, ftol=1e-5, max_nfev=100)
        iterations.append(int(res.nfev))
        x[free] = res.x
        return res

    def errors():
        xx = x
        C = xx[:ncam * NC].reshape(ncam, NC)
        S = xx[ncam * NC:].reshape(len(shots), NS)
        return [np.linalg.norm(project(np.repeat(C[v.cam][None], len(v.ids), 0),
                                       np.repeat(S[shot_index[v.shot]][None], len(v.ids), 0), obj[v.ids]) - v.uv, axis=1)
                for v in views]

    start_err = errors()
    solve("soft_l1")
    err = errors()
    med = float(np.median(np.concatenate([e for e, u in zip(err, use) if u])))
    thr = max(outlier_px, 5.0 * med)
    dropped_views = []
    for i, e in enumerate(err):
        if np.median(e) > thr:
            use[i] = False
            dropped_views.append(views[i].source)
        else:
            keep[i] = e <= thr
    for c in range(ncam):
        if not any(use[i] for i, v in enumerate(views) if v.cam == c):
            raise NodeError(f"calibrate: camera '{names[c]}': every view is an outlier (median error > {thr:.2g} px)")
    final = solve("linear")
    err = errors()
    sigma = _sigmas(final, free, ncam)

    def cameras_of(xx, with_pose):
        out = []
        for c in range(ncam):
            p = xx[c * NC:(c + 1) * NC]
            K = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1]])
            Rt = np.hstack([rodrigues(p[9:12])[0], p[12:15, None]]) if with_pose else np.hstack([np.eye(3), np.zeros((3, 1))])
            out.append(Camera(names[c], sizes[c][0], sizes[c][1], K, Rt, p[4:9]))
        return Cameras(out)

    rig = ref is not None
    cams_rows = []
    for c in range(ncam):
        idx = [i for i, v in enumerate(views) if v.cam == c and use[i]]
        e = np.concatenate([err[i][keep[i]] for i in idx])
        e0 = np.concatenate([start_err[i] for i, v in enumerate(views) if v.cam == c])
        p = x[c * NC:(c + 1) * NC]
        cams_rows.append({
            "camera": names[c], "rms_px": float(np.sqrt(np.mean(e ** 2))), "max_px": float(e.max()),
            "start_rms_px": float(np.sqrt(np.mean(e0 ** 2))),
            "views": len(idx), "shared_views": sum(views[i].shared for i in idx),
            "corners": int(sum(keep[i].sum() for i in idx)),
            "dropped_views": sum(1 for i, v in enumerate(views) if v.cam == c and not use[i]),
            "dropped_corners": int(sum((~keep[i]).sum() for i in idx)),
            **{k: float(v) for k, v in zip(CAM_PARAMS[:9], p[:9])},
            "sigma": {k: float(sigma[c * NC + j]) for j, k in enumerate(CAM_PARAMS[:4])}})
    kept = np.concatenate([err[i][keep[i]] for i in range(len(views)) if use[i]])
    report = {"rms_px": float(np.sqrt(np.mean(kept ** 2))), "iterations": iterations, "cameras": cams_rows, "views": int(use.sum()),
              "shots": len(shots), "shared_shots": len(shared), "reference_shot": ref,
              "outlier_px": thr, "dropped_views": dropped_views,
              "world": ("the board of the reference shot (origin at its first inner corner, +Z out of its back), "
                        "metres") if rig else "none: no shared shots, intrinsics only"}
    return Solution(cameras_of(x, True) if rig else None, cameras_of(x, rig), report,
                    cameras_of(x_start, True) if rig else None)
