"""Camera calibration importers and exporters.

``load_cameras(path, fmt="auto", image_sizes=None) -> Cameras`` reads:
    colmap      COLMAP text model (cameras.txt + images.txt): SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL,
                OPENCV, FULL_OPENCV (k4..k6 = 0)
    nerf        NeRF / instant-ngp transforms.json (camera_angle_x or fl_x/fl_y/cx/cy; OpenGL camera axes)
    middlebury  Middlebury multi-view *_par.txt (name, K, R, t per line)
    opencv      OpenCV FileStorage XML/YAML: camera_matrix + distortion + R or rvec + T, or lists of P
    ptext       plain 3x4 P matrices as text, 12 numbers a line (optional count line and leading names)
    inria       <camera> XML with 12 numbers (INRIA platform): one file per camera
    idr         IDR / NeuS cameras_sphere.npz (world_mat_i, scale_mat_i)
    tsinghua    calibParamsI.txt blocks: index, K, k1 k2, [R|t]
    matlab      .mat file holding a cell array of 3x4 P matrices (Oxford VGG)
    qualisys    Qualisys QTM calibration XML (.qca, Calib.qca.txt, or .xml): camera centre in mm, rotation,
                intrinsics in 1/64 px, distortion as written (not /64; read_qualisys); positions in metres
    toml        Pose2Sim / anipose calibration TOML: a table per camera with name, size [w, h], matrix,
                distortions (k1 k2 p1 p2 [k3]), rotation (a rotation vector, world -> camera), translation
Writers: save_colmap, save_nerf, save_opencv (one FileStorage YAML per camera, as read_opencv reads it), save_toml.
A folder is searched for these files (also calibration/*.qca.txt); per-camera files (calibration/*.xml,
cam*/config.xml) make one set.

Pixel convention: (0, 0) is the centre of the top-left pixel (nodes.common.cameras, as OpenCV's projectPoints).
Each importer's convention for its files (CONVENTIONS; tests/stages/common/test_pixel_conventions.py checks
every one against cv2.projectPoints on hand-written files):
    colmap      corner  (0, 0) is the top-left pixel's corner: principal point - 0.5 on import, + 0.5 on export
    nerf        corner  (cx, cy; default w/2, h/2, the image centre): - 0.5 on import, + 0.5 on export
    middlebury  centre  K as given (the Middlebury evaluation projects with P = K [R|t] onto pixel centres)
    opencv      centre  OpenCV's own calibration convention
    ptext, inria, matlab, idr   centre   P = K [R|t] maps onto pixel centres at integers (Oxford VGG, INRIA,
                        IDR/NeuS cast rays through integer pixel coordinates)
    tsinghua    centre  K as given
    qualisys    centre  centerPointU/64 - fov_video.left taken as OpenCV's cx (as Pose2Sim reads it; the file
                        does not say where its 1/64-pixel grid starts)
    toml        centre  OpenCV's matrices as Pose2Sim and anipose write them
Units: the cameras keep their file's length unit, except qualisys (millimetres), which is converted to metres
(the unit of the synthetic rigs).
P matrices are decomposed (cv2.decomposeProjectionMatrix) into a metric camera when the result is physical
(positive focal lengths of similar size, little skew, principal point near the image); otherwise they are
kept as bare-P cameras (``Camera.from_P``), as for the non-metric Oxford dino.
"""
from __future__ import annotations

import json
import re
import xml.etree.ElementTree as ET
from pathlib import Path, PurePosixPath

import numpy as np

from .cameras import Camera, Cameras
from nodegraph.errors import DataError

FORMATS = ("colmap", "nerf", "middlebury", "opencv", "ptext", "inria", "idr", "tsinghua", "matlab", "qualisys", "toml")
# where a format puts pixel coordinate (0, 0): the top-left pixel's centre or its corner (see the docstring)
CONVENTIONS = {"colmap": "corner", "nerf": "corner", "middlebury": "centre", "opencv": "centre", "ptext": "centre",
               "inria": "centre", "idr": "centre", "tsinghua": "centre", "matlab": "centre",
               "qualisys": "centre", "toml": "centre"}
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".exr")


class MissingImageSize(DataError):
    """The calibration does not store image sizes and no image was found to read them from."""


# ------------------------------------------------------------------ helpers
def _numbers(text: str) -> list[float]:
    return [float(x) for x in text.split()]


def _finite(arr, what: str, path) -> np.ndarray:
    arr = np.asarray(arr, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise DataError(f"{path}: {what} contains NaN or infinity")
    return arr


class _NamesOnly:
    """image_sizes for ``camera_names``: every camera gets a large placeholder size, so a reader can build its
    cameras (and name them) before the images that give the real sizes are found."""

    size = (1 << 14, 1 << 14)


def camera_names(path, fmt: str = "auto") -> list[str]:
    """The camera names of a calibration, in order, without knowing the image sizes (which a capture reads
    from the images it finds through these names)."""
    return load_cameras(path, fmt, image_sizes=_NamesOnly()).names


def _size_for(i: int, name: str, image_sizes, path, folder: Path | None = None):
    """Image size of camera i: from image_sizes (one (w, h) for all, a list, or a dict by name), else read
    from an image file called ``name`` in ``folder``."""
    if isinstance(image_sizes, _NamesOnly):
        return image_sizes.size
    if image_sizes is not None:
        if isinstance(image_sizes, dict):
            if name not in image_sizes:
                raise DataError(f"{path}: no image size given for camera '{name}'")
            return image_sizes[name]
        sizes = list(image_sizes)
        if len(sizes) == 2 and np.isscalar(sizes[0]):
            return sizes
        if i >= len(sizes):
            raise DataError(f"{path}: {len(sizes)} image sizes given for more cameras (camera {i} '{name}')")
        return sizes[i]
    if folder is not None:
        for cand in [folder / name, *(folder / (name + e) for e in IMAGE_EXTS), *(folder.glob(f"**/{name}"))]:
            if cand.is_file():
                return image_size(cand)
    raise MissingImageSize(f"{path}: the calibration does not give image sizes and no image '{name}' was found: "
                    "pass image_sizes=(width, height) or a list per camera")


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DataError(f"{path}: unreadable or corrupt image")
    return img.shape[1], img.shape[0]


def camera_from_P(name: str, P, width: int, height: int, metric: str = "auto") -> Camera:
    """A camera from a 3x4 projection matrix: decomposed into K [R|t] when that is physical (or
    metric="yes"), else kept as a bare-P camera (metric="no" forces that)."""
    import cv2

    P = np.asarray(P, dtype=np.float64).reshape(3, 4)
    if not np.any(P):
        raise DataError(f"camera '{name}': projection matrix is all zero")
    if np.all(np.isfinite(P)) and np.linalg.matrix_rank(P / np.abs(P).max()) < 3:
        raise DataError(f"camera '{name}': projection matrix has rank {np.linalg.matrix_rank(P / np.abs(P).max())} "
                        "(a camera's P has rank 3)")
    if metric == "no":
        return Camera.from_P(name, P, width, height)
    M = P[:, :3]
    if abs(np.linalg.det(M)) < 1e-12 * np.abs(M).max() ** 3:
        raise DataError(f"camera '{name}': projection matrix is singular")
    Pn = P * np.sign(np.linalg.det(M))          # det(M) > 0: then det(R) = +1 and w > 0 in front
    K, R, c = cv2.decomposeProjectionMatrix(Pn)[:3]
    S = np.diag(np.sign(np.diag(K)))             # make the diagonal of K positive
    K, R = K @ S, S @ R
    scale = K[2, 2]
    K = K / scale
    C = c[:3, 0] / c[3, 0]
    Rt = np.hstack([R, (-R @ C)[:, None]])
    physical = (np.linalg.det(R) > 0 and K[0, 0] > 0 and K[1, 1] > 0 and 0.5 < K[1, 1] / K[0, 0] < 2
                and abs(K[0, 1]) < 0.01 * K[0, 0] and -width < K[0, 2] < 2 * width and -height < K[1, 2] < 2 * height)
    if metric == "yes" and not physical:
        raise DataError(f"camera '{name}': P does not decompose into a physical K [R|t] (K = {np.round(K, 2).tolist()})")
    if not physical:
        return Camera.from_P(name, P, width, height)
    err = np.abs(K @ Rt * scale - Pn).max() / np.abs(Pn).max()
    if err > 1e-8:
        raise DataError(f"camera '{name}': decomposition of P is inconsistent (relative error {err:.2g})")
    return Camera(name, width, height, K, Rt)


# ------------------------------------------------------------------ importers
def image_name(path: str) -> str:
    """A camera's name from its image's path relative to the image folder, without the image extension
    ("cam0/0001.png" -> "cam0/0001"): the stem alone would give cam0/0001.png and cam1/0001.png one name."""
    p = PurePosixPath(path.replace("\\", "/"))
    return str(p.with_suffix("")) if p.suffix.lower() in IMAGE_EXTS else str(p)


def read_colmap(folder: Path, image_sizes=None) -> Cameras:
    """COLMAP text model: cameras.txt + images.txt (cameras sorted by image name)."""
    cams_txt, imgs_txt = folder / "cameras.txt", folder / "images.txt"
    intr = {}
    for ln, line in enumerate(cams_txt.read_text().splitlines(), 1):
        if not line.strip() or line.startswith("#"):
            continue
        f = line.split()
        try:
            cid, model, w, h = f[0], f[1], int(f[2]), int(f[3])
            p = _finite([float(x) for x in f[4:]], f"camera {cid} parameters", f"{cams_txt}:{ln}")
        except (ValueError, IndexError):
            raise DataError(f"{cams_txt}:{ln}: expected 'ID MODEL WIDTH HEIGHT PARAMS...'") from None
        need = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8, "FULL_OPENCV": 12}
        if model not in need:
            raise DataError(f"{cams_txt}:{ln}: camera model {model} is not supported (have: {', '.join(need)})")
        if len(p) != need[model]:
            raise DataError(f"{cams_txt}:{ln}: {model} needs {need[model]} parameters, got {len(p)}")
        dist = np.zeros(5)
        if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
            fx = fy = p[0]
            cx, cy = p[1], p[2]
            dist[: len(p) - 3] = p[3:]
        else:
            fx, fy, cx, cy = p[:4]
            if model == "OPENCV":
                dist[:4] = p[4:8]
            elif model == "FULL_OPENCV":
                if np.any(p[9:12] != 0):
                    raise DataError(f"{cams_txt}:{ln}: FULL_OPENCV with rational terms k4..k6 is not supported")
                dist[:] = [p[4], p[5], p[6], p[7], p[8]]
        K = np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1]])
        intr[cid] = (w, h, K, dist)
    from scipy.spatial.transform import Rotation

    cams = []
    lines = [ln for ln in imgs_txt.read_text().splitlines() if not ln.startswith("#")]
    for k in range(0, len(lines), 2):
        if not lines[k].strip():
            continue
        f = lines[k].split()
        if len(f) < 10:
            raise DataError(f"{imgs_txt}: image line '{lines[k][:60]}' needs 10 fields")
        try:
            q = _finite([float(x) for x in f[1:5]], "quaternion", imgs_txt)
            t = _finite([float(x) for x in f[5:8]], "translation", imgs_txt)
        except ValueError:
            raise DataError(f"{imgs_txt}: not a number in image line '{lines[k][:60]}'") from None
        cid, name = f[8], " ".join(f[9:])
        if cid not in intr:
            raise DataError(f"{imgs_txt}: image '{name}' uses camera {cid}, which cameras.txt does not define")
        R = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
        w, h, K, dist = intr[cid]
        cams.append(Camera(image_name(name), w, h, K, np.hstack([R, t[:, None]]), dist))
    if not cams:
        raise DataError(f"{imgs_txt}: no images")
    return Cameras(sorted(cams, key=lambda c: c.name))


def read_nerf(path: Path, image_sizes=None) -> Cameras:
    """NeRF / instant-ngp transforms.json: camera-to-world matrices in OpenGL axes (flip y and z)."""
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise DataError(f"{path}: not valid JSON ({exc})") from None
    if not doc.get("frames"):
        raise DataError(f"{path}: no 'frames' in transforms file")
    cams = []
    for i, fr in enumerate(doc["frames"]):
        g = {**doc, **fr}
        name = Path(fr.get("file_path", f"frame{i:04d}")).name
        if Path(name).suffix.lower() in IMAGE_EXTS:
            name = Path(name).stem
        if "w" in g and "h" in g:
            w, h = int(g["w"]), int(g["h"])
        else:
            fp = path.parent / fr.get("file_path", "")
            w, h = _size_for(i, fp.name, image_sizes, path, fp.parent)
        if "fl_x" in g:
            fx = float(g["fl_x"])
            fy = float(g.get("fl_y", fx))
        elif "camera_angle_x" in g:
            fx = 0.5 * w / np.tan(0.5 * float(g["camera_angle_x"]))
            fy = 0.5 * h / np.tan(0.5 * float(g["camera_angle_y"])) if "camera_angle_y" in g else fx
        else:
            raise DataError(f"{path}: frame {i} has neither fl_x nor camera_angle_x")
        cx, cy = float(g.get("cx", w / 2)), float(g.get("cy", h / 2))
        dist = [float(g.get(k, 0.0)) for k in ("k1", "k2", "p1", "p2", "k3")]
        T = _finite(fr.get("transform_matrix", np.full((4, 4), np.nan)), f"frame {i} transform_matrix", path)
        if T.shape != (4, 4):
            raise DataError(f"{path}: frame {i} transform_matrix must be 4x4")
        R_c2w = T[:3, :3] @ np.diag([1.0, -1.0, -1.0])
        R = R_c2w.T
        t = -R @ T[:3, 3]
        K = np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1]])
        cams.append(Camera(name, w, h, _finite(K, f"frame {i} intrinsics", path), np.hstack([R, t[:, None]]), dist))
    return Cameras(cams)


def read_middlebury(path: Path, image_sizes=None) -> Cameras:
    """Middlebury *_par.txt: count, then `name k11..k33 r11..r33 t1 t2 t3` lines; P = K [R|t]."""
    lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    body = lines[1:] if len(lines[0]) == 1 else lines
    if len(lines[0]) == 1 and int(lines[0][0]) != len(body):
        raise DataError(f"{path}: header says {lines[0][0]} cameras but {len(body)} lines follow")
    cams = []
    for i, f in enumerate(body):
        if len(f) != 22:
            raise DataError(f"{path}:{i + 2}: expected name + 21 numbers, got {len(f)} fields")
        try:
            v = _finite([float(x) for x in f[1:]], f"camera '{f[0]}'", path)
        except ValueError:
            raise DataError(f"{path}:{i + 2}: not a number in the line of '{f[0]}'") from None
        w, h = _size_for(i, f[0], image_sizes, path, path.parent)
        Rt = np.hstack([v[9:18].reshape(3, 3), v[18:21, None]])
        cams.append(Camera(Path(f[0]).stem, w, h, v[:9].reshape(3, 3), Rt))
    return Cameras(cams)


def read_ptext(path: Path, image_sizes=None) -> Cameras:
    """Plain P matrices: 12 numbers a line (row-major), '#' comments, optional count line, optional name
    as the first field (then image sizes are read from that image beside the file)."""
    rows = []
    for ln, line in enumerate(path.read_text().splitlines(), 1):
        line = line.split("#")[0].strip()
        if not line:
            continue
        f = line.split()
        if len(f) == 1 and not rows:
            continue  # count line
        name, nums = (f[0], f[1:]) if len(f) == 13 else (None, f)
        if len(nums) != 12:
            raise DataError(f"{path}:{ln}: expected 12 numbers (a 3x4 P), got {len(nums)}")
        try:
            rows.append((name, ln, [float(x) for x in nums]))
        except ValueError:
            raise DataError(f"{path}:{ln}: not a number in '{line[:60]}'") from None
    cams = []
    for i, (name, ln, nums) in enumerate(rows):
        P = _finite(nums, "P", f"{path}:{ln}")
        cname = Path(name).stem if name else f"cam{i:03d}"
        w, h = _size_for(i, name or cname, image_sizes, path, path.parent if name else None)
        cams.append(_named(f"{path}:{ln}", camera_from_P, cname, P, w, h))
    return _checked(cams, path)


def _named(where, fn, *args, **kw):
    """fn(*args) with a DataError's message prefixed by ``where`` (the file, or file:line)."""
    try:
        return fn(*args, **kw)
    except MissingImageSize:
        raise
    except DataError as exc:
        raise DataError(f"{where}: {exc}") from None


def read_inria(paths: list[Path], image_sizes=None) -> Cameras:
    """One `<camera>12 numbers</camera>` XML file per camera (INRIA platform), sorted by file name."""
    cams = []
    for i, p in enumerate(paths):
        try:
            nums = _numbers(ET.parse(p).getroot().text or "")
        except (ET.ParseError, ValueError) as exc:
            raise DataError(f"{p}: unreadable camera XML ({exc})") from None
        if len(nums) != 12:
            raise DataError(f"{p}: expected 12 numbers (a 3x4 P), got {len(nums)}")
        w, h = _size_for(i, p.stem, image_sizes, p)
        cams.append(_named(p, camera_from_P, p.stem, _finite(nums, "P", p), w, h))
    return _checked(cams, paths[0].parent)


def read_tsinghua(path: Path, image_sizes=None) -> Cameras:
    """calibParamsI.txt: per camera `index`, K (3 rows), `k1 k2`, [R|t] (3 rows of 4)."""
    try:
        v = _numbers(path.read_text())
    except ValueError:
        raise DataError(f"{path}: not a whitespace-separated list of numbers") from None
    if len(v) % 24:
        raise DataError(f"{path}: expected blocks of 24 numbers (index, K, k1 k2, R|t), got {len(v)} numbers")
    cams = []
    for i in range(len(v) // 24):
        b = _finite(v[24 * i: 24 * (i + 1)], f"camera block {i}", path)
        name = str(int(b[0]))
        w, h = _size_for(i, name, image_sizes, path)
        cams.append(Camera(name, w, h, b[1:10].reshape(3, 3), b[12:24].reshape(3, 4), [b[10], b[11], 0, 0, 0]))
    return Cameras(cams)


def read_idr(path: Path, image_sizes=None) -> Cameras:
    """IDR / NeuS cameras_sphere.npz: P = world_mat_i @ scale_mat_i (scene normalised to the unit sphere)."""
    with np.load(path) as z:
        keys = sorted((k for k in z.files if re.fullmatch(r"world_mat_\d+", k)), key=lambda k: int(k.rsplit("_", 1)[1]))
        if not keys:
            raise DataError(f"{path}: no world_mat_i arrays")
        cams = []
        for i, k in enumerate(keys):
            idx = k.rsplit("_", 1)[1]
            W = _finite(z[k], k, path)
            S = _finite(z[f"scale_mat_{idx}"], f"scale_mat_{idx}", path) if f"scale_mat_{idx}" in z.files else np.eye(4)
            P = (W @ S)[:3, :4]
            name = f"{int(idx):03d}"
            w, h = _size_for(i, name, image_sizes, path)
            cams.append(_named(f"{path} ({k})", camera_from_P, name, P, w, h, metric="yes"))
    return Cameras(cams)


def read_matlab(path: Path, image_sizes=None) -> Cameras:
    """A .mat file with one cell array of 3x4 P matrices (e.g. Oxford dino_Ps.mat, variable P)."""
    from scipy.io import loadmat

    try:
        m = loadmat(path)
    except Exception as exc:
        raise DataError(f"{path}: unreadable .mat file ({exc})") from None
    cells = [k for k, v in m.items() if not k.startswith("__") and isinstance(v, np.ndarray) and v.dtype == object]
    if len(cells) != 1:
        raise DataError(f"{path}: expected one cell array of P matrices, found {cells or 'none'}")
    Ps = [np.asarray(p, dtype=np.float64) for p in m[cells[0]].ravel()]
    cams = []
    for i, P in enumerate(Ps):
        if P.shape != (3, 4):
            raise DataError(f"{path}: cell {i + 1} of '{cells[0]}' is {P.shape}, not 3x4")
        w, h = _size_for(i, f"cam{i:03d}", image_sizes, path)
        cams.append(_named(f"{path} (P{{{i + 1}}})", camera_from_P, f"cam{i:03d}", _finite(P, f"P{{{i + 1}}}", path), w, h))
    return _checked(cams, path)


# Qualisys distortion coefficients are taken as they are (OpenCV's k1 k2 p1 p2 k3), not divided by 64 as
# Pose2Sim does: on pose2sim_single's checkerboard images (4x7 corners) the file's coefficients as they are
# give a lower PnP reprojection error than /64 (= almost none) in 3 cameras of 4 (0.45 vs 0.52 px in cam02)
# and equal in the 4th, and a free cv2.calibrateCamera of cam01 finds k1 -0.050, k2 0.113 (file: -0.046, 0.140).
_QCA_DIST_SCALE = 1.0


def _qca_attrs(el, keys, where) -> list[float]:
    """The attributes ``keys`` of XML element ``el`` as finite floats; a missing one or a non-number is a
    DataError naming ``where`` (the file and the camera)."""
    out = []
    for k in keys:
        v = el.get(k)
        if v is None:
            raise DataError(f"{where}: <{el.tag}> has no attribute {k}")
        try:
            out.append(float(v))
        except ValueError:
            raise DataError(f"{where}: <{el.tag}> {k}=\"{v}\" is not a number") from None
    return list(_finite(out, f"<{el.tag}>", where))


def read_qualisys(path: Path, image_sizes=None) -> Cameras:
    """Qualisys QTM calibration XML (``<calibration><cameras><camera serial=...>``), as Pose2Sim reads it.

    Per camera: ``transform`` x, y, z = the camera centre C in the world (mm) and r11..r33 a rotation whose
    columns are written row by row: with A = [[r11, r12, r13], [r21, r22, r23], [r31, r32, r33]]^T the
    camera's axes in the world are the columns of A diag(1, -1, -1) in OpenCV's axes, so R = (A diag(1, -1,
    -1))^T and t = -R C (C converted to metres). ``intrinsic`` in 1/64 pixel: fx = focalLengthU / 64, fy =
    focalLengthV / 64, cx = centerPointU / 64 - fov_video.left, cy = centerPointV / 64 - fov_video.top;
    distortion k1 k2 k3 = radialDistortion1..3, p1 p2 = tangentalDistortion1..2 (see _QCA_DIST_SCALE). The
    image size is fov_video's (right - left + 1) x (bottom - top + 1). Names: the ``serial`` attribute."""
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise DataError(f"{path}: unreadable Qualisys XML ({exc})") from None
    cams_el = root.findall("./cameras/camera")
    if root.tag != "calibration" or not cams_el:
        raise DataError(f"{path}: not a Qualisys calibration (expected <calibration><cameras><camera ...>)")
    flip = np.diag([1.0, -1.0, -1.0])
    cams = []
    for i, el in enumerate(cams_el):
        name = el.get("serial") or f"cam{i + 1:02d}"
        where = f"{path}: camera {i} '{name}'"
        parts = {}
        for tag in ("transform", "intrinsic", "fov_video"):
            parts[tag] = el.find(tag)
            if parts[tag] is None:
                raise DataError(f"{where}: no <{tag}>")
        tr, intr, fov = parts["transform"], parts["intrinsic"], parts["fov_video"]
        if el.get("viewrotation", "0") not in ("0", ""):
            raise DataError(f"{where}: viewrotation={el.get('viewrotation')} (rotated images) is not supported")
        r = _qca_attrs(tr, [f"r{a}{b}" for a in "123" for b in "123"], where)
        C = np.array(_qca_attrs(tr, "xyz", where)) / 1000.0                       # mm -> m
        A = np.reshape(r, (3, 3)).T
        R = (A @ flip).T
        if abs(np.linalg.det(R) - 1) > 1e-6 or np.abs(R @ R.T - np.eye(3)).max() > 1e-6:
            raise DataError(f"{where}: transform r11..r33 is not a rotation (det {np.linalg.det(R):.6g})")
        left, top, right, bottom = _qca_attrs(fov, ("left", "top", "right", "bottom"), where)
        fu, fv, cu, cv = _qca_attrs(intr, ("focalLengthU", "focalLengthV", "centerPointU", "centerPointV"), where)
        skew = _qca_attrs(intr, ("skew",), where)[0] if intr.get("skew") is not None else 0.0
        if skew != 0:
            raise DataError(f"{where}: intrinsic skew={skew:g} is not supported")
        dk = {k: (_qca_attrs(intr, (k,), where)[0] if intr.get(k) is not None else 0.0)
              for k in ("radialDistortion1", "radialDistortion2", "radialDistortion3", "tangentalDistortion1",
                        "tangentalDistortion2")}
        dist = np.array([dk["radialDistortion1"], dk["radialDistortion2"], dk["tangentalDistortion1"],
                         dk["tangentalDistortion2"], dk["radialDistortion3"]]) / _QCA_DIST_SCALE
        K = np.array([[fu / 64, 0, cu / 64 - left], [0, fv / 64, cv / 64 - top], [0, 0, 1]])
        w, h = int(round(right - left + 1)), int(round(bottom - top + 1))
        if w <= 0 or h <= 0:
            raise DataError(f"{where}: fov_video gives an empty image ({w}x{h})")
        cams.append(_named(where, Camera, name, w, h, K, np.hstack([R, (-R @ C)[:, None]]), dist))
    return Cameras(cams)


_K_KEYS = ("camera_matrix", "CameraMatrix", "K", "intrinsic", "Intrinsics", "cameraMatrix")
_D_KEYS = ("distortion_coefficients", "distortion", "DistortionCoeffs", "dist_coeffs", "distCoeffs", "D", "dist")
_R_KEYS = ("R", "rotation_matrix", "RotationMatrix")
_RVEC_KEYS = ("rvec", "Rotation", "rotation", "rvecs")
_T_KEYS = ("T", "t", "tvec", "Translation", "translation", "tvecs")


def _fs_node(fs, keys):
    for k in keys:
        n = fs.getNode(k)
        if not n.empty():
            return k, n
    return None, None


def _fs_value(node):
    if node.isSeq():
        return [_fs_value(node.at(i)) for i in range(node.size())]
    if node.isReal() or node.isInt():
        return node.real()
    m = node.mat()
    return None if m is None else np.asarray(m, dtype=np.float64)


def read_opencv(path: Path, image_sizes=None, name: str | None = None) -> Cameras:
    """OpenCV FileStorage (XML/YAML): camera_matrix + distortion + (R | rvec) + T, or 3x4 P matrices
    (one per node, or a sequence)."""
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise DataError(f"{path}: not an OpenCV FileStorage file ({exc.err})") from None
    if not fs.isOpened():
        raise DataError(f"{path}: not an OpenCV FileStorage file")
    try:
        kk, kn = _fs_node(fs, _K_KEYS)
        cname = name or path.stem
        if kn is not None:
            K = _fs_value(kn)
            if K is None or K.shape != (3, 3):
                raise DataError(f"{path}: {kk} must be a 3x3 matrix")
            _, dn = _fs_node(fs, _D_KEYS)
            dist = np.zeros(5) if dn is None else _fs_value(dn).ravel()
            if dist.size > 5 and np.any(dist[5:] != 0):
                raise DataError(f"{path}: only 5 distortion coefficients (k1 k2 p1 p2 k3) are supported, got {dist.size}")
            _, rn = _fs_node(fs, _R_KEYS)
            _, vn = _fs_node(fs, _RVEC_KEYS)
            tk, tn = _fs_node(fs, _T_KEYS)
            if tn is None or (rn is None and vn is None):
                raise DataError(f"{path}: needs a rotation ({'/'.join(_R_KEYS + _RVEC_KEYS)}) and a translation ({'/'.join(_T_KEYS)})")
            Rv = _fs_value(rn if rn is not None else vn)
            R = Rv if Rv.shape == (3, 3) else cv2.Rodrigues(Rv.reshape(3, 1))[0]
            t = _fs_value(tn).reshape(3)
            if image_sizes is None and not fs.getNode("image_width").empty():
                w, h = int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real())
            else:
                w, h = _size_for(0, cname, image_sizes, path)
            dist = _finite(dist[:5], "distortion", path)
            return Cameras([Camera(cname, w, h, _finite(K, kk, path), np.hstack([_finite(R, "rotation", path), _finite(t, tk, path)[:, None]]), dist)])
        Ps = []
        root = fs.root()
        for key in root.keys():
            v = _fs_value(root.getNode(key))
            items = v if isinstance(v, list) else [v]
            for j, m in enumerate(items):
                if isinstance(m, np.ndarray) and m.shape == (3, 4):
                    Ps.append((key if len(items) == 1 else f"{key}_{j:03d}", m))
        if not Ps:
            raise DataError(f"{path}: no camera_matrix and no 3x4 P matrices found")
        cams = []
        for i, (key, P) in enumerate(Ps):
            w, h = _size_for(i, key, image_sizes, path)
            cams.append(_named(f"{path} ({key})", camera_from_P, key, _finite(P, key, path), w, h))
        return _checked(cams, path)
    finally:
        fs.release()


def read_toml(path: Path, image_sizes=None) -> Cameras:
    """Pose2Sim / anipose calibration TOML: one table per camera (``metadata`` skipped) with ``matrix`` (3x3),
    ``distortions`` (k1 k2 p1 p2 [k3]), ``rotation`` (rotation vector, world -> camera), ``translation`` and
    ``size`` [width, height]; ``name`` when present, else the table's key."""
    import tomllib

    import cv2

    try:
        doc = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise DataError(f"{path}: not TOML ({exc})") from None
    cams = []
    for i, (key, tab) in enumerate((k, v) for k, v in doc.items() if isinstance(v, dict) and "matrix" in v):
        name = str(tab.get("name", key))
        missing = [f for f in ("matrix", "rotation", "translation") if f not in tab]
        if missing:
            raise DataError(f"{path}: [{key}] has no {', '.join(missing)}")
        if tab.get("fisheye", False):
            raise DataError(f"{path}: [{key}] is a fisheye camera (not supported: OpenCV radial-tangential only)")
        K = _finite(tab["matrix"], f"[{key}] matrix", path).reshape(3, 3)
        dist = _finite(tab.get("distortions", [0] * 4), f"[{key}] distortions", path).ravel()
        if dist.size > 5:
            raise DataError(f"{path}: [{key}] has {dist.size} distortion coefficients (k1 k2 p1 p2 [k3] supported)")
        R = cv2.Rodrigues(_finite(tab["rotation"], f"[{key}] rotation", path).reshape(3, 1))[0]
        t = _finite(tab["translation"], f"[{key}] translation", path).reshape(3)
        if "size" in tab and image_sizes is None:
            w, h = (int(round(v)) for v in tab["size"])
        else:
            w, h = _size_for(i, name, image_sizes, path)
        cams.append(Camera(name, w, h, K, np.hstack([R, t[:, None]]), dist))
    if not cams:
        raise DataError(f"{path}: no camera table (with a 'matrix') in the TOML file")
    return Cameras(cams)


def _checked(cams: list[Camera], path) -> Cameras:
    """A camera set may not mix metric and bare-P cameras: if some P matrices decompose and others do not,
    keep them all as bare P. Bare-P cameras get their front side from the scene (orient_bare_P)."""
    if len({c.metric for c in cams}) > 1:
        cams = [c if not c.metric else Camera.from_P(c.name, c.P, c.width, c.height) for c in cams]
    if not cams[0].metric:
        cams = orient_bare_P(cams)
    return Cameras(cams)


def orient_bare_P(cams: list[Camera]) -> list[Camera]:
    """Set each bare-P camera's zsign so that the point nearest to all viewing rays through the image
    centres lies in front of every camera (needed in mirrored frames, where sign(det M) is wrong)."""
    if len(cams) < 2:
        return cams
    A, b = np.zeros((3, 3)), np.zeros(3)
    for c in cams:
        try:
            d = np.linalg.solve(c.Rt[:, :3], [(c.width - 1) / 2, (c.height - 1) / 2, 1.0])
        except np.linalg.LinAlgError:
            raise DataError(f"camera '{c.name}': the left 3x3 part of its projection matrix is singular "
                            "(not a pinhole camera)") from None
        d /= np.linalg.norm(d)
        Pm = np.eye(3) - np.outer(d, d)
        A += Pm
        b += Pm @ c.center
    p = np.linalg.lstsq(A, b, rcond=None)[0]
    out = []
    for c in cams:
        w = c.Rt[2, :3] @ p + c.Rt[2, 3]
        out.append(Camera.from_P(c.name, c.Rt, c.width, c.height, zsign=float(np.sign(w) or 1.0)))
    return out


# ------------------------------------------------------------------ detection
def _sniff_file(p: Path) -> str | None:
    name, suf = p.name.lower(), p.suffix.lower()
    if name in ("cameras.txt", "images.txt"):
        return "colmap"
    if suf == ".json":
        return "nerf"
    if suf == ".npz":
        return "idr"
    if suf == ".mat":
        return "matlab"
    if name.endswith((".qca", ".qca.txt")):
        return "qualisys"
    if suf == ".toml":
        return "toml" if re.search(r"^\s*matrix\s*=", p.read_text(errors="replace"), re.M) else None
    if suf in (".xml", ".yml", ".yaml"):
        head = p.read_text(errors="replace")[:400]
        if suf == ".xml" and re.search(r"<calibration[\s>]", head) and "<cameras" in p.read_text(errors="replace")[:4000]:
            return "qualisys"
        return "inria" if re.search(r"<camera>", head) and "opencv_storage" not in head else "opencv"
    if suf == ".txt":
        lines = [ln.split() for ln in p.read_text(errors="replace").splitlines() if ln.strip() and not ln.startswith("#")]
        body = lines[1:] if lines and len(lines[0]) == 1 else lines
        if body and all(len(f) == 22 for f in body):
            return "middlebury"
        if body and all(len(f) in (12, 13) for f in body):
            return "ptext"
        if lines and len(lines[0]) == 1 and lines[0][0].isdigit():
            try:
                blocks = len(_numbers(" ".join(" ".join(f) for f in lines))) % 24 == 0
            except ValueError:
                blocks = True       # a typo in a number: let the reader name the problem
            if blocks:
                return "tsinghua"
    return None


def _folder_candidates(folder: Path) -> list[tuple[str, object]]:
    """(fmt, path or list of paths) for every calibration found in a dataset folder."""
    out = []
    for sub in (folder, folder / "sparse", folder / "sparse" / "0"):
        if (sub / "cameras.txt").is_file() and (sub / "images.txt").is_file():
            out.append(("colmap", sub))
    for p in sorted(folder.iterdir()):
        if p.is_file() and p.name.lower() not in ("cameras.txt", "images.txt"):
            try:
                fmt = _sniff_file(p)
            except (OSError, ValueError):
                fmt = None
            if fmt and not (fmt == "opencv" and "checkerboard" in p.name.lower()):
                out.append((fmt, p))
    npz = [p for f, p in out if f == "idr"]
    if len(npz) > 1 and any(p.name == "cameras_sphere.npz" for p in npz):  # NeuS ships cameras_sphere + cameras_large
        out = [c for c in out if c[0] != "idr" or c[1].name == "cameras_sphere.npz"]
    singles = [p for f, p in out if f == "inria"]
    if len(singles) > 1:  # one <camera> file per camera: one set
        out = [c for c in out if c[0] != "inria"] + [("inria+", singles)]
    calib = folder / "calibration"
    if calib.is_dir():
        out += [("qualisys", p) for p in sorted(calib.glob("*.qca*")) if p.name.lower().endswith((".qca", ".qca.txt"))]
        xmls = [p for p in sorted(calib.glob("*.xml")) if _sniff_file(p) != "qualisys"]
        if xmls:
            out.append((_sniff_file(xmls[0]) + "+", xmls))
    configs = sorted(folder.glob("*/config.xml"))
    if configs:
        out.append(("opencv+", configs))
    return out


def load_cameras(path, fmt: str = "auto", image_sizes=None) -> Cameras:
    """Read a calibration (file or dataset folder) as Cameras.

    fmt: "auto" or one of FORMATS. image_sizes: (w, h) for all cameras, a list per camera, or a dict by
    camera name, for formats that do not store sizes (else they are read from the images beside the file).
    A folder holding several calibrations is accepted when they agree (same projections), else a DataError
    names them."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: calibration not found")
    if fmt != "auto" and fmt not in FORMATS:
        raise DataError(f"unknown calibration format '{fmt}' (have: auto, {', '.join(FORMATS)})")
    if path.is_file():
        try:
            f = _sniff_file(path) if fmt == "auto" else fmt
        except (OSError, ValueError):
            f = None
        if f is None:
            raise DataError(f"{path}: unknown calibration format (give fmt=, one of {', '.join(FORMATS)})")
        return _read(f, path.parent if f == "colmap" else path, image_sizes)
    cands = _folder_candidates(path)
    if fmt != "auto":
        cands = [c for c in cands if c[0].rstrip("+") == fmt]
    if not cands:
        raise DataError(f"{path}: no calibration file found (looked for COLMAP, transforms.json, *_par.txt, P text, "
                        "OpenCV XML/YAML, cameras*.npz, .mat, Qualisys .qca, calibration/*.xml, */config.xml)")
    loaded = [(c, _read(c[0], c[1], image_sizes)) for c in cands]
    first = loaded[0][1]
    for (fmt_i, p_i), cams in loaded[1:]:
        if not _same_projection(first, cams):
            names = ", ".join(f"{f.rstrip('+')}: {_short(p)}" for f, p in cands)
            raise DataError(f"{path}: several calibrations that disagree ({names}); pass the file or fmt= explicitly")
    return first


def _short(p) -> str:
    return f"{p[0].parent.name}/*{p[0].suffix} ({len(p)} files)" if isinstance(p, list) else Path(p).name


def _read(fmt: str, p, image_sizes) -> Cameras:
    """Read one calibration; a file the reader cannot make sense of, or cameras the kernels cannot use
    (Camera checks NaN, float32 range, positive focal lengths), are a DataError naming the file."""
    import cv2

    where = _short(p) if isinstance(p, list) else p
    try:
        return _read_unchecked(fmt.rstrip("+"), p, image_sizes)
    except MissingImageSize:
        raise
    except DataError as exc:
        raise DataError(str(exc) if str(where) in str(exc) else f"{where}: {exc}") from None
    except (ValueError, TypeError, KeyError, IndexError, AttributeError, SystemError, OSError, cv2.error) as exc:
        raise DataError(f"{where}: unreadable {fmt.rstrip('+')} calibration ({type(exc).__name__}: {exc})") from None


def _read_unchecked(fmt: str, p, image_sizes) -> Cameras:
    if isinstance(p, list):
        if fmt == "inria":
            return read_inria(p, image_sizes)
        sizes = image_sizes
        cams = []
        for i, q in enumerate(p):
            name = q.parent.name if q.name == "config.xml" else q.stem
            size_i = None if sizes is None else [_size_for(i, name, sizes, q)]
            cams.extend(read_opencv(q, size_i, name=name).cameras)
        return Cameras(cams)
    readers = {"colmap": read_colmap, "nerf": read_nerf, "middlebury": read_middlebury, "ptext": read_ptext,
               "inria": lambda q, s: read_inria([q], s), "idr": read_idr, "tsinghua": read_tsinghua,
               "matlab": read_matlab, "opencv": read_opencv, "qualisys": read_qualisys, "toml": read_toml}
    return readers[fmt](Path(p), image_sizes)


def _same_projection(a: Cameras, b: Cameras, tol_px: float = 1e-3) -> bool:
    if len(a) != len(b):
        return False
    for i in range(len(a)):
        # points in front of camera i: along its optical axis region, 1..3 focal units away
        o, d = a.rays(i, [[a[i].width / 2, a[i].height / 2], [0, 0], [a[i].width - 1, a[i].height - 1]])
        scale = np.linalg.norm(a.centers - a.centers.mean(0), axis=1).mean() or 1.0
        X = np.concatenate([o + d * s * scale for s in (0.5, 1.0, 1.5)])
        ua, _ = a.project(X, i)
        ub, _ = b.project(X, i)
        if not np.allclose(ua, ub, atol=tol_px, rtol=0):
            return False
    return True


# ------------------------------------------------------------------ exporters
def _exportable(c: Camera, fmt: str):
    if not c.metric:
        raise DataError(f"camera '{c.name}': a bare-P camera cannot be written as {fmt} (needs K [R|t])")
    if abs(c.K[0, 1]) > 1e-9 * abs(c.K[0, 0]):
        raise DataError(f"camera '{c.name}': skew {c.K[0, 1]:.4g} cannot be written as {fmt}")


def save_colmap(cams: Cameras, folder) -> None:
    """Write COLMAP text (cameras.txt, images.txt, empty points3D.txt): PINHOLE, or OPENCV / FULL_OPENCV
    with distortion. Image names are camera names (+ .png when they have no extension)."""
    from scipy.spatial.transform import Rotation

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    cl = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    il = ["# Image list with two lines of data per image:", "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
          "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
    for i, c in enumerate(cams, 1):
        _exportable(c, "COLMAP")
        fx, fy, cx, cy = c.K[0, 0], c.K[1, 1], c.K[0, 2] + 0.5, c.K[1, 2] + 0.5
        k1, k2, p1, p2, k3 = c.dist
        if k3 != 0:
            model, params = "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0, 0, 0]
        elif c.has_distortion:
            model, params = "OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2]
        else:
            model, params = "PINHOLE", [fx, fy, cx, cy]
        cl.append(f"{i} {model} {c.width} {c.height} " + " ".join(repr(float(p)) for p in params))
        qx, qy, qz, qw = Rotation.from_matrix(c.Rt[:, :3]).as_quat()
        name = c.name if Path(c.name).suffix else c.name + ".png"
        il.append(f"{i} " + " ".join(repr(float(v)) for v in (qw, qx, qy, qz, *c.Rt[:, 3])) + f" {i} {name}")
        il.append("")
    (folder / "cameras.txt").write_text("\n".join(cl) + "\n")
    (folder / "images.txt").write_text("\n".join(il) + "\n")
    (folder / "points3D.txt").write_text("# 3D point list (empty)\n")


def save_nerf(cams: Cameras, path) -> None:
    """Write a transforms.json with per-frame intrinsics (fl_x, fl_y, cx, cy, w, h, k1 k2 p1 p2 k3) and
    camera-to-world matrices in OpenGL axes; file_path = camera name."""
    frames = []
    for c in cams:
        _exportable(c, "transforms.json")
        R, t = c.Rt[:, :3], c.Rt[:, 3]
        T = np.eye(4)
        T[:3, :3] = R.T @ np.diag([1.0, -1.0, -1.0])
        T[:3, 3] = -R.T @ t
        k1, k2, p1, p2, k3 = (float(v) for v in c.dist)
        frames.append({"file_path": c.name, "w": c.width, "h": c.height, "fl_x": float(c.K[0, 0]), "fl_y": float(c.K[1, 1]),
                       "cx": float(c.K[0, 2] + 0.5), "cy": float(c.K[1, 2] + 0.5), "k1": k1, "k2": k2, "p1": p1, "p2": p2,
                       "k3": k3, "transform_matrix": T.tolist()})
    doc = {"camera_model": "OPENCV", "frames": frames}
    if len({(f["fl_x"], f["w"]) for f in frames}) == 1:
        doc["camera_angle_x"] = float(2 * np.arctan(0.5 * frames[0]["w"] / frames[0]["fl_x"]))
    Path(path).write_text(json.dumps(doc, indent=1))


def save_opencv(cams: Cameras, folder, pose: bool = True) -> None:
    """One OpenCV FileStorage YAML per camera, ``<name>.yml`` (camera_matrix, distortion_coefficients, R, T,
    image_width, image_height), as read_opencv reads it; ``pose`` False: intrinsics only (no R, T)."""
    import cv2

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for c in cams:
        _exportable(c, "OpenCV YAML")
        fs = cv2.FileStorage(str(folder / f"{c.name}.yml"), cv2.FILE_STORAGE_WRITE)
        try:
            fs.write("image_width", c.width)
            fs.write("image_height", c.height)
            fs.write("camera_matrix", c.K)
            fs.write("distortion_coefficients", c.dist.reshape(1, 5))
            if pose:
                fs.write("R", c.Rt[:, :3])
                fs.write("T", c.Rt[:, 3].reshape(3, 1))
        finally:
            fs.release()


def save_toml(cams: Cameras, path, error: float = 0.0) -> None:
    """Pose2Sim / anipose calibration TOML (rotation vector and translation world -> camera, the file's length
    unit = the cameras'; ``error``: the calibration's reprojection RMS in pixels, written in [metadata])."""
    import cv2

    def arr(v):
        return "[ " + ", ".join(repr(float(x)) for x in np.ravel(v)) + "]"

    out = []
    for c in cams:
        _exportable(c, "TOML")
        key = re.sub(r"[^A-Za-z0-9_-]", "_", c.name)
        rows = ", ".join(arr(r) for r in c.K)
        out += [f"[{key}]", f'name = "{c.name}"', f"size = {arr([c.width, c.height])}", f"matrix = [ {rows}]",
                f"distortions = {arr(c.dist if c.dist[4] != 0 else c.dist[:4])}",
                f"rotation = {arr(cv2.Rodrigues(c.Rt[:, :3])[0])}", f"translation = {arr(c.Rt[:, 3])}",
                "fisheye = false", ""]
    out += ["[metadata]", "adjusted = false", f"error = {float(error)!r}", ""]
    Path(path).write_text("\n".join(out))
