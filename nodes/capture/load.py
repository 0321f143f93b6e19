"""The `capture` source node: one frame of a calibrated multi-camera capture from a dataset folder.

File patterns are relative to the dataset folder and are expanded per camera with
    {cam}   camera index (0-based)      {cam1}  camera index + 1       {name}  camera name
    {frame} frame number
A pattern may contain '*': the matching files, sorted, are the frames (frame N = the N-th file). A video
file (.avi, .mp4, .mov, .mkv) holds the frames itself: frame N is its N-th frame. Without '*', {frame} or a
video, the data is static and only frame 0 exists. The background (clean plate) is always frame 0 of its
pattern. Masks: "alpha" takes the images' alpha channel; else grey images thresholded at mask_threshold
(the maximum over colour channels).

Known dataset layouts are detected automatically: layouts.yaml beside this file lists them (a marker file
pattern that identifies the folder, then the patterns); an unknown folder is read with ``load_cameras`` and
an image folder whose files match the cameras by name or by order.
"""
from __future__ import annotations

import glob
import json
import re
from pathlib import Path

import numpy as np

from functools import lru_cache

from nodegraph import DataError, NodeError
from nodes.common.calibration import IMAGE_EXTS, MissingImageSize, load_cameras
from nodes.common.cameras import Cameras
from nodes.common.types import ImageSet, MaskSet

VIDEO_EXTS = (".avi", ".mp4", ".mov", ".mkv")
PATTERN_KEYS = ("calibration", "images", "masks", "background")


@lru_cache(maxsize=None)
def layouts() -> list[dict]:
    """The known dataset layouts (layouts.yaml beside this module), in detection order."""
    import yaml

    doc = yaml.safe_load((Path(__file__).with_name("layouts.yaml")).read_text())
    for entry in doc:
        unknown = set(entry) - {"name", "marker", *PATTERN_KEYS}
        if unknown or "marker" not in entry:
            raise DataError(f"layouts.yaml: layout {entry.get('name')!r} has unknown keys {sorted(unknown)} or no marker")
    return doc


# ------------------------------------------------------------------ files
def _expand(root: Path, pattern: str, cam: int, name: str, frame: int, extra: dict) -> tuple[Path, int | None]:
    """The file holding camera ``cam``'s frame ``frame``, and the frame index inside it (videos)."""
    try:
        rel = pattern.format(cam=cam, cam1=cam + 1, name=name, frame=frame, **extra.get(name, {}))
    except (KeyError, IndexError, ValueError) as exc:
        raise NodeError(f"pattern '{pattern}': cannot expand it ({exc}); use {{cam}}, {{cam1}}, {{name}}, {{frame}}") from None
    if Path(rel).suffix.lower() in VIDEO_EXTS:
        p = root / rel
        if not p.is_file():
            raise DataError(f"camera {cam} '{name}': video {p} not found (pattern '{pattern}')")
        return p, frame
    if "*" in rel:
        files = sorted(glob.glob(str(root / rel)))
        if not files:
            raise DataError(f"camera {cam} '{name}': no file matches {root / rel} (pattern '{pattern}')")
        if frame >= len(files):
            raise DataError(f"camera {cam} '{name}': frame {frame} out of range: {len(files)} frames match {rel}")
        return Path(files[frame]), None
    if frame != 0 and "{frame" not in pattern:
        raise DataError(f"frame {frame} out of range: '{pattern}' is a single frame (only frame 0 exists)")
    p = root / rel
    if not p.is_file():
        raise DataError(f"camera {cam} '{name}': file {p} not found (pattern '{pattern}')")
    return p, None


def read_image(path: Path, frame: int | None = None) -> np.ndarray:
    """An image file, or frame ``frame`` of a video, as uint8 (H, W, 3) RGB or (H, W, 4) RGBA or (H, W) grey."""
    import cv2

    if frame is not None:
        cap = cv2.VideoCapture(str(path))
        try:
            if not cap.isOpened():
                raise DataError(f"{path}: unreadable video")
            n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            if n > 0 and frame >= n:
                raise DataError(f"{path}: frame {frame} out of range (the video has {n} frames)")
            cap.set(cv2.CAP_PROP_POS_FRAMES, frame)
            ok, img = cap.read()
        finally:
            cap.release()
        if not ok:
            raise DataError(f"{path}: frame {frame} could not be decoded")
    else:
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise DataError(f"{path}: unreadable or corrupt image")
    if img.dtype != np.uint8:
        if img.dtype != np.uint16:
            raise DataError(f"{path}: {img.dtype} images are not supported (8 or 16 bit)")
        img = (img >> 8).astype(np.uint8)
    if img.ndim == 3 and img.shape[2] == 3:
        img = img[:, :, ::-1]
    elif img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, [2, 1, 0, 3]]
    return np.ascontiguousarray(img)


def _rgb(img: np.ndarray) -> np.ndarray:
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2)
    return np.ascontiguousarray(img[:, :, :3])


def _mask(img: np.ndarray, threshold: int) -> np.ndarray:
    grey = img if img.ndim == 2 else img[:, :, :3].max(axis=2)
    return np.where(grey > threshold, 255, 0).astype(np.uint8)


# ------------------------------------------------------------------ layout detection
def detect_layout(root: Path) -> dict:
    """Patterns for a dataset folder: a known layout, or a generic one (calibration + images by name/order)."""
    for layout in layouts():
        if glob.glob(str(root / layout["marker"])):
            return {k: v for k, v in layout.items() if k in PATTERN_KEYS}
    return {}


def _nerf_transforms(root: Path, calibration: str) -> Path:
    """The transforms file whose images all exist (nerf_lego ships a full file and a subset)."""
    cands = sorted(glob.glob(str(root / calibration)))
    good = []
    for c in cands:
        frames = json.loads(Path(c).read_text()).get("frames", [])
        if frames and all(any((root / (f["file_path"] + e)).is_file() for e in ("",) + IMAGE_EXTS) for f in frames):
            good.append(Path(c))
    if len(good) != 1:
        raise DataError(f"{root}: {len(good)} of the transforms files {[Path(c).name for c in cands]} have all their images; "
                        "give calibration= explicitly")
    return good[0]


def _generic(root: Path, frame: int):
    """Unknown folder: calibration found by load_cameras, images in images/ (or the folder) by name or order."""
    img_dir = root / "images" if (root / "images").is_dir() else root
    files = sorted(p for p in img_dir.iterdir() if p.suffix.lower() in IMAGE_EXTS)
    if not files:
        raise DataError(f"{root}: unknown dataset layout and no images found (give the images= pattern)")
    if frame != 0:
        raise DataError(f"{root}: frame {frame} out of range (a folder of images is a single frame; use patterns for sequences)")
    try:
        cams = load_cameras(root)
    except MissingImageSize:
        cams = load_cameras(root, image_sizes=[_size(f) for f in files])
    by_stem = {f.stem: f for f in files}
    missing = [f"{i} '{c.name}'" for i, c in enumerate(cams) if c.name not in by_stem]
    if not missing:
        files = [by_stem[c.name] for c in cams]
    elif len(missing) < len(cams):      # some files are named after cameras: matching by order would mix them up
        raise DataError(f"{img_dir}: no image named after camera(s) {', '.join(missing)} (the other cameras' images "
                        "are there by name)")
    elif len(files) != len(cams):
        raise DataError(f"{img_dir}: {len(files)} images but the calibration has {len(cams)} cameras, and their names do not match")
    return cams, files


def _size(path: Path) -> tuple[int, int]:
    img = read_image(path)
    return img.shape[1], img.shape[0]


# ------------------------------------------------------------------ loading
def load_capture(path, frame: int = 0, images: str = "", masks: str = "", background: str = "",
                 calibration: str = "", mask_threshold: int = 127) -> dict:
    """One frame of a capture: {"images": ImageSet, "masks": MaskSet | None, "cameras": Cameras,
    "background": ImageSet | None}. Empty patterns are auto-detected (see the module docstring)."""
    root = Path(path)
    if not root.is_dir():
        raise DataError(f"capture folder {root} not found")
    if frame < 0:
        raise DataError(f"frame {frame} out of range (frames start at 0)")
    layout = detect_layout(root)
    given = {k: v for k, v in dict(images=images, masks=masks, background=background, calibration=calibration).items() if v}
    if not layout and "images" not in given:
        cams, files = _generic(root, frame)
        imgs = [read_image(f) for f in files]
        return _assemble(cams, imgs, [f for f in files], None, None, mask_threshold, masks or "")
    pat = {**layout, **given}
    if "calibration" not in pat or "images" not in pat:
        raise NodeError(f"{root}: unknown dataset layout: give both the calibration and images patterns")
    calib = root / pat["calibration"]
    extra = {}
    if "{nerf_path}" in pat["images"]:
        calib = _nerf_transforms(root, pat["calibration"])
        frames = json.loads(calib.read_text())["frames"]
        extra = {Path(f["file_path"]).name: {"nerf_path": f["file_path"].lstrip("./") + ".png"} for f in frames}
    elif "*" in pat["calibration"]:
        hits = sorted(glob.glob(str(calib)))
        if not hits or (len(hits) > 1 and len({Path(h).parent for h in hits}) != len(hits)):
            raise DataError(f"{root}: calibration pattern '{pat['calibration']}' matches {len(hits)} files")
        calib = Path(hits[0]) if len(hits) == 1 else [Path(h) for h in hits]

    # cameras first (their names expand the patterns); sizes from the images when the calibration has none
    try:
        if isinstance(calib, list):
            cams, raw, img_files = _per_folder_cameras(root, calib, pat["images"], frame, extra)
        else:
            cams = load_cameras(calib)
            raw = None
    except MissingImageSize:
        probe = load_cameras(calib, image_sizes=(1, 1))
        img_files = [_expand(root, pat["images"], i, c.name, frame, extra) for i, c in enumerate(probe)]
        raw = [read_image(p, f) for p, f in img_files]
        cams = load_cameras(calib, image_sizes=[(im.shape[1], im.shape[0]) for im in raw])
    _check_camera_count(root, pat["images"], cams)
    if raw is None:
        img_files = [_expand(root, pat["images"], i, c.name, frame, extra) for i, c in enumerate(cams)]
        raw = [read_image(p, f) for p, f in img_files]
    bg = None
    if pat.get("background"):
        bg = ImageSet([_rgb(read_image(*_expand(root, pat["background"], i, c.name, 0, extra))) for i, c in enumerate(cams)],
                      cams.names)
    mask_imgs = mask_files = None
    if pat.get("masks") and pat["masks"] != "alpha":
        found = [_expand(root, pat["masks"], i, c.name, frame, extra) for i, c in enumerate(cams)]
        mask_files = [p for p, _ in found]
        mask_imgs = [read_image(p, f) for p, f in found]
    out = _assemble(cams, raw, [p for p, _ in img_files], mask_imgs, bg, mask_threshold, pat.get("masks", ""), mask_files)
    return out


def _per_folder_cameras(root: Path, files: list[Path], images: str, frame: int, extra: dict):
    """One calibration file per camera folder (e.g. camCC/cam_par.txt): each holds one camera, named after
    its folder (the name inside the file may differ: the folder pairs a calibration with its images), its
    image size read from the camera's image of this frame. Returns (cameras, images, image files)."""
    from dataclasses import replace

    cams, raw, img_files = [], [], []
    for i, f in enumerate(files):
        name = f.parent.name
        img_files.append(_expand(root, images, i, name, frame, extra))
        raw.append(read_image(*img_files[-1]))
        one = load_cameras(f, image_sizes=(raw[-1].shape[1], raw[-1].shape[0]))
        if len(one) != 1:
            raise DataError(f"{f}: {len(one)} cameras in a per-camera calibration file (expected one)")
        cams.append(replace(one[0], name=name))
    return Cameras(cams), raw, img_files


def _check_camera_count(root: Path, pattern: str, cams: Cameras):
    """When images live in one folder per camera ({cam}/{cam1}/{name} in the first folder), the number of
    folders holding such files must match the number of cameras."""
    parts = Path(pattern).parts
    if len(parts) < 2 or not re.search(r"\{(cam|cam1|name)[:}]", parts[0]):
        return
    anywhere = re.sub(r"\{[^}]*\}", "*", pattern)
    found = {Path(p).relative_to(root).parts[0] for p in glob.glob(str(root / anywhere))}
    if len(found) != len(cams):
        raise DataError(f"{root}: {len(found)} camera folders hold '{anywhere}' but the calibration has {len(cams)} cameras")


def _assemble(cams: Cameras, raw: list, files: list, mask_imgs, bg, threshold: int, mask_mode: str,
              mask_files: list | None = None) -> dict:
    for i, (c, img, f) in enumerate(zip(cams, raw, files)):
        h, w = img.shape[:2]
        if (w, h) != (c.width, c.height):
            raise DataError(f"camera {i} '{c.name}': image {f} is {w}x{h} but the calibration is for {c.width}x{c.height}")
        if c.metric and not (0 <= c.K[0, 2] <= w and 0 <= c.K[1, 2] <= h):
            raise DataError(f"camera {i} '{c.name}': principal point ({c.K[0, 2]:.1f}, {c.K[1, 2]:.1f}) lies outside "
                            f"the {w}x{h} image {f}: image size and intrinsics do not match")
    images = ImageSet([_rgb(im) for im in raw], cams.names)
    masks = None
    if mask_mode == "alpha":
        for f, im in zip(files, raw):
            if not (im.ndim == 3 and im.shape[2] == 4):
                raise DataError(f"{f}: masks='alpha' but the image has no alpha channel")
        masks = MaskSet([_mask(im[:, :, 3], threshold) for im in raw], None, cams.names)
    elif mask_imgs is not None:
        for i, (m, im) in enumerate(zip(mask_imgs, raw)):
            if m.shape[:2] != im.shape[:2]:
                mf = f" {mask_files[i]}" if mask_files else ""
                raise DataError(f"camera {i} '{cams[i].name}': mask{mf} is {m.shape[1]}x{m.shape[0]} but the image "
                                f"{files[i]} is {im.shape[1]}x{im.shape[0]}")
        masks = MaskSet([_mask(m, threshold) for m in mask_imgs], None, cams.names)
    if bg is not None:
        for i, (b, im) in enumerate(zip(bg.images, raw)):
            if b.shape[:2] != im.shape[:2]:
                raise DataError(f"camera {i} '{cams[i].name}': background is {b.shape[1]}x{b.shape[0]} but the image is {im.shape[1]}x{im.shape[0]}")
    return {"images": images, "masks": masks, "cameras": cams, "background": bg}
