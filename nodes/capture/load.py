"""The `capture` source node: one frame of a calibrated multi-camera capture from a dataset folder.

File patterns are relative to the dataset folder and are expanded per camera with
    {cam}   camera index (0-based)      {cam1}  camera index + 1       {name}  camera name
    {frame} frame number
A pattern may contain '*': the matching files, sorted, are the frames (frame N = the N-th file). A video
file (.avi, .mp4, .mov, .mkv) holds the frames itself: frame N is its N-th frame. Without '*', {frame} or a
video, the data is static and only frame 0 exists. The background (clean plate) is always frame 0 of its
pattern. Masks: "alpha" takes the images' alpha channel; else grey images thresholded at mask_threshold
(the maximum over colour channels). With several cameras every images, masks and background pattern needs a
camera field ({cam}, {cam1}, {name}; {image} and {nerf_path} where they apply): one without would give every
camera the same file, and is refused ('*' means frames, never cameras).

Known dataset layouts are detected automatically: layouts.yaml beside this file lists them (a marker file
pattern that identifies the folder, then the patterns); an unknown folder is read with ``load_cameras`` and
an image folder (images/, image/ or the folder itself) whose files are paired with the cameras:
  - by name (file stem = camera name), else
  - by the number in their names: the one run of digits that tells the names apart on each side
    (image_7.jpg <-> viff007_matrix), never by text order (image_10 sorts before image_2);
  - every image needs its camera (an image left over is an error); a calibration with more cameras than
    images is used for the cameras named by the images (the others are left out, with a warning);
  - anything else (duplicate numbers, several varying numbers, no numbers) is refused: give patterns.
The pairing is logged (the item log), and a warning says when it was made from numbers. Masks come from
a masks/ or mask/ folder beside the images (same names), or the masks pattern; patterns there may also use
{image}, the stem of the camera's image file. One pattern given on such a folder is completed the same way:
calibration= alone reads that calibration and pairs the images as above; images= alone expands the pattern
per camera of the calibration found in the folder, masks from masks/ or mask/ beside the images.

With patterns, files that match a pattern but belong to no camera of the calibration (a calibration file
missing) are an error, not a camera fewer. Only regular files are read (a FIFO or a device never is).
"""
from __future__ import annotations

import glob
import json
import logging
import os
import re
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

from functools import lru_cache

from nodegraph import DataError, NodeError
from nodes.common.calibration import IMAGE_EXTS, MissingImageSize, camera_names, load_cameras
from nodes.common.cameras import Cameras
from nodes.common.types import ImageSet, MaskSet

VIDEO_EXTS = (".avi", ".mp4", ".mov", ".mkv")
PATTERN_KEYS = ("calibration", "images", "masks", "background")
WORLD_KEYS = ("up", "units", "floor")     # the layout's world frame (world.py): up axis, metres per unit, floor height


LOG = logging.getLogger("volcap.capture")


def natural_key(name: str) -> list:
    """Sort key reading runs of digits as numbers: 2.png before 10.png."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", str(name))]


def _regular(paths) -> list[Path]:
    """The regular files among ``paths`` (links followed), in natural order: a FIFO or device is never read."""
    return sorted((Path(p) for p in paths if Path(p).is_file()), key=lambda p: natural_key(str(p)))


@lru_cache(maxsize=None)
def layouts() -> list[dict]:
    """The known dataset layouts (layouts.yaml beside this module), in detection order."""
    import yaml

    doc = yaml.safe_load((Path(__file__).with_name("layouts.yaml")).read_text())
    for entry in doc:
        unknown = set(entry) - {"name", "marker", *PATTERN_KEYS, *WORLD_KEYS}
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
        files = [str(f) for f in _regular(glob.glob(str(root / rel)))]
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




OPEN_VIDEOS = 64     # video readers kept open per process (the least recently used closed first; ~18 MiB each)
FORWARD = 64         # a frame at most this many frames after a reader's position is reached by decoding on


class _VideoReader:
    """An open video (one decoding thread: 18 instead of 29 MiB per reader at 1080p, no threads left waiting, and
    as fast here, since frames are decoded one at a time) and the index of the frame it decodes next."""

    def __init__(self, path: Path):
        import cv2

        self.cap = cv2.VideoCapture(str(path), cv2.CAP_ANY, [cv2.CAP_PROP_N_THREADS, 1])
        if not self.cap.isOpened():
            raise DataError(f"{path}: unreadable video")
        self.count = int(self.cap.get(cv2.CAP_PROP_FRAME_COUNT))
        self.next = 0
        self.closed = False
        self.lock = threading.Lock()

    def close(self):
        with self.lock:
            self.closed = True
            self.cap.release()


_readers: "OrderedDict[tuple, _VideoReader]" = OrderedDict()
_readers_lock = threading.Lock()


def _video_reader(path: Path) -> _VideoReader:
    """This process's open reader of the file as it is now (path, size, mtime), opened when there is none (the
    file is opened, and the evicted readers closed, outside the lock of the table)."""
    try:
        st = os.stat(path)
    except OSError as exc:
        raise DataError(f"{path}: unreadable video ({exc.strerror})") from None
    key = (str(path), st.st_size, st.st_mtime_ns)
    with _readers_lock:
        reader = _readers.get(key)
        if reader is not None:
            _readers.move_to_end(key)
            return reader
    opened = _VideoReader(path)
    with _readers_lock:
        reader = _readers.setdefault(key, opened)         # another thread may have opened it meanwhile
        _readers.move_to_end(key)
        evicted = [_readers.popitem(last=False)[1] for _ in range(len(_readers) - OPEN_VIDEOS)]
    for old in evicted + ([opened] if reader is not opened else []):
        old.close()
    return reader


def video_frame(path: Path, frame: int) -> np.ndarray:
    """Frame ``frame`` of a video file as decoded (BGR). The video stays open in this process (up to OPEN_VIDEOS
    of them, per file version: path, size, mtime) and decodes on from where it stopped: a run's frames one after
    another cost one decode each. A seek (cv2's CAP_PROP_POS_FRAMES) decodes from the keyframe before the frame:
    opening and seeking per frame cost 2.8 ms more per frame of the position on pose2sim_single's videos (343 ms
    for frame 99 of a camera, 6.6 ms decoding on), so a minute of footage grew quadratically. A frame before the
    position, or more than FORWARD frames after it, is sought. (More videos per frame than OPEN_VIDEOS, e.g. 33
    cameras with image and mask videos, reopen and seek every frame again.)"""
    import cv2

    if frame < 0:
        raise DataError(f"{path}: frame {frame} out of range (frames count from 0)")
    while True:
        reader = _video_reader(path)
        with reader.lock:
            if reader.closed:                              # evicted by another thread meanwhile: open it again
                continue
            n = reader.count
            if n > 0 and frame >= n:
                raise DataError(f"{path}: frame {frame} out of range (the video has {n} frames)")
            if not 0 <= frame - reader.next <= FORWARD:
                reader.cap.set(cv2.CAP_PROP_POS_FRAMES, frame)
                reader.next = frame
            ok = True
            while ok and reader.next < frame:
                ok = reader.cap.grab()
                reader.next += 1
            if ok:
                ok, img = reader.cap.read()
            reader.next += 1
            if not ok:
                reader.next = -FORWARD - 1            # the position is unknown: the next frame is sought
                raise DataError(f"{path}: frame {frame} could not be decoded")
            return img


def video_fps(path: Path) -> float | None:
    """The frame rate a video file states (None when it states none)."""
    import cv2

    try:
        reader = _video_reader(path)
        with reader.lock:
            fps = 0.0 if reader.closed else float(reader.cap.get(cv2.CAP_PROP_FPS))
    except DataError:
        return None
    return fps if fps > 0 else None


def read_image(path: Path, frame: int | None = None) -> np.ndarray:
    """An image file, or frame ``frame`` of a video, as uint8 (H, W, 3) RGB or (H, W, 4) RGBA or (H, W) grey."""
    import cv2

    if frame is not None:
        img = video_frame(path, frame)
    else:
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise DataError(f"{path}: unreadable or corrupt image")
    if img.dtype != np.uint8:
        if img.dtype != np.uint16:
            raise DataError(f"{path}: {img.dtype} images are not supported (8 or 16 bit)")
        img = (img >> 8).astype(np.uint8)
    if img.ndim == 3 and img.shape[2] in (3, 4):       # cv2's swap: the bytes of img[..., ::-1] (of [2, 1, 0, 3]), 4x faster
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB if img.shape[2] == 3 else cv2.COLOR_BGRA2RGBA)
    return np.ascontiguousarray(img)


def _rgb(img: np.ndarray) -> np.ndarray:
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2)
    return np.ascontiguousarray(img[:, :, :3])


def _mask(img: np.ndarray, threshold: int) -> np.ndarray:
    grey = img if img.ndim == 2 else img[:, :, :3].max(axis=2)
    return (grey > threshold).view(np.uint8) * np.uint8(255)      # np.where(.., 255, 0).astype(np.uint8)'s bytes


# ------------------------------------------------------------------ layout detection
def detect_layout(root: Path) -> dict:
    """Patterns for a dataset folder: a known layout, or a generic one (calibration + images by name/order)."""
    for layout in layouts():
        if glob.glob(str(root / layout["marker"])):
            return {k: v for k, v in layout.items() if k in PATTERN_KEYS}
    return {}


def layout_world(root: Path) -> dict:
    """The world keys (up, units, floor) of the known layout of a dataset folder ({} for an unknown one)."""
    for layout in layouts():
        if glob.glob(str(Path(root) / layout["marker"])):
            return {k: v for k, v in layout.items() if k in WORLD_KEYS}
    return {}


def world_of(path, images, masks, background, calibration, mask_threshold, up, units, origin, origin_frame,
             loaded: dict | None = None, log=None):
    """(WorldFrame, report) of a capture folder, from its frame ``origin_frame`` (``loaded``: that frame when
    the caller has it); memoised per process, as every frame of a sequence asks the same."""
    key = (str(path), images, masks, background, calibration, mask_threshold, up, units, origin, origin_frame)
    hit = _WORLDS.get(key)
    if hit is None:
        from .world import find_world

        ref = loaded or load_capture(path, origin_frame, images, masks, background, calibration, mask_threshold, log=LOG)
        ms = ref["masks"]
        hit = find_world(ref["cameras"], None if ms is None else ms.masks, layout_world(Path(path)), up=up,
                         units=units, origin=origin, node="capture", log=log)
        _WORLDS[key] = hit
    elif log:
        for w in hit[1]["warnings"]:
            log.warning("capture: world frame: %s", w)
    return hit


_WORLDS: dict = {}


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


def _digits(names: list[str]) -> list[int] | None:
    """Per name, the number that tells the names apart: all names hold the same count of digit runs and
    exactly one run varies between them (a single name: its only run). None when there is no such number."""
    runs = [[int(x) for x in re.findall(r"\d+", n)] for n in names]
    if not runs or len({len(r) for r in runs}) != 1 or not runs[0]:
        return None
    if len(runs) == 1:
        return runs[0] if len(runs[0]) == 1 else None
    varying = [j for j in range(len(runs[0])) if len({r[j] for r in runs}) > 1]
    return [r[varying[0]] for r in runs] if len(varying) == 1 else None


def _list(items, n: int = 6) -> str:
    items = list(items)
    return ", ".join(map(str, items[:n])) + (f" and {len(items) - n} more" if len(items) > n else "")


def _relative_name(f: Path, folder: Path) -> str:
    """The file's path below ``folder`` without its extension ("cam0/0001"), as a COLMAP camera is named."""
    try:
        return f.relative_to(folder).with_suffix("").as_posix()
    except ValueError:
        return f.stem


def pair_files(names: list[str], files: list[Path], folder: Path, what: str = "image", partner: str = "camera",
               log=None) -> tuple[list[int], list[Path]]:
    """Pair ``files`` with ``names`` (cameras): by name (file stem), else by the number in the names (see
    the module docstring). Returns (index into names, file) pairs in the order of ``names``; DataError for an
    ambiguous pairing or a file without a partner."""
    log = log or LOG
    stems = [f.stem for f in files]
    index = {n: i for i, n in enumerate(names)}
    by_name = [index.get(_relative_name(f, folder), index.get(s)) for f, s in zip(files, stems)]
    if any(b is not None for b in by_name):
        stray = [f.name for f, b in zip(files, by_name) if b is None]
        if stray:
            named = {b for b in by_name if b is not None}
            missing = [f"{i} '{n}'" for i, n in enumerate(names) if i not in named]
            first = (f"no {what} named after {partner}(s) {_list(missing)} (the other {partner}s' {what}s are there by "
                     "name); ") if missing else ""
            raise DataError(f"{folder}: {first}{what}(s) {_list(stray)} have no {partner} (not named after one of the "
                            f"{len(names)} {partner}s: {_list(names, 4)}); is a calibration file missing?")
        idx, how = by_name, "by name"
    else:
        cn, fn = _digits(names), _digits(stems)
        if cn is None or fn is None or len(set(cn)) != len(cn) or len(set(fn)) != len(fn):
            raise DataError(f"{folder}: cannot tell which {what} belongs to which {partner}: no {what} is named after a "
                            f"{partner} ({_list(names, 3)}), and the numbers in the names do not identify them one to one "
                            f"({what}s {_list([f.name for f in files], 3)}); give patterns with {{name}}, {{cam}} or "
                            "{cam1} (images=, calibration=)")
        pos = {n: i for i, n in enumerate(cn)}
        stray = [f.name for f, n in zip(files, fn) if n not in pos]
        if stray:
            raise DataError(f"{folder}: {what}(s) {_list(stray)} have no {partner}: their numbers name none of the "
                            f"{len(names)} {partner}s ({names[0]} .. {names[-1]}); is a calibration file missing?")
        idx, how = [pos[n] for n in fn], "by the number in their names"
    if len(set(idx)) != len(idx):
        raise DataError(f"{folder}: several {what}s pair with the same {partner}")
    order = sorted(range(len(files)), key=lambda j: idx[j])
    keep, paired = [idx[j] for j in order], [files[j] for j in order]
    pairs = [f"{f.name} -> {names[i]}" for i, f in zip(keep, paired)]
    log.info("paired %d %ss with %ss %s: %s", len(pairs), what, partner, how, "; ".join(pairs))
    if how != "by name":
        shown = pairs if len(pairs) <= 4 else pairs[:3] + ["...", pairs[-1]]
        log.warning("%s: no %s is named after a %s: paired the %d %ss with %ss by the number in their names "
                    "(%s); give patterns to pair them otherwise", folder, what, partner, len(pairs), what, partner,
                    ", ".join(shown))
    unused = [n for i, n in enumerate(names) if i not in set(keep)]
    if unused:
        log.warning("%s: %d of the %d %ss have no %s and are left out: %s", folder, len(unused), len(names), partner,
                    what, _list(unused, 10))
    return keep, paired


def _generic(root: Path, frame: int, masks: str, background: str, log, calibration: str = "") -> tuple:
    """Unknown folder: calibration found by load_cameras (or the ``calibration`` pattern), images in images/ or
    image/ (or the folder), paired with the cameras (pair_files); masks from masks/ or mask/ beside them, or
    the masks pattern."""
    calib = root
    if calibration:
        hits = [Path(h) for h in sorted(glob.glob(str(root / calibration)))] if "*" in calibration else [root / calibration]
        if len(hits) != 1 or not hits[0].exists():
            raise DataError(f"{root}: calibration pattern '{calibration}' matches {len(hits) if '*' in calibration else 0} "
                            "files (one is needed)")
        calib = hits[0]
    img_dir = next((d for d in (root / "images", root / "image") if d.is_dir()), root)
    files = _regular(p for p in img_dir.iterdir() if p.suffix.lower() in IMAGE_EXTS)
    if not files:  # one folder per camera (COLMAP names them by the relative path: cam0/0001)
        files = _regular(sorted(p for p in img_dir.glob("*/*") if p.suffix.lower() in IMAGE_EXTS))
    if not files:
        raise DataError(f"{root}: unknown dataset layout and no images found (give the images= pattern)")
    if frame != 0:
        raise DataError(f"{root}: frame {frame} out of range (a folder of images is a single frame; use patterns for sequences)")
    try:
        cams = load_cameras(calib)
    except MissingImageSize:
        names = camera_names(calib)
        keep, files = pair_files(names, files, img_dir, log=log)
        sizes = {names[i]: _size(f) for i, f in zip(keep, files)}
        some = next(iter(sizes.values()))
        cams = load_cameras(calib, image_sizes={n: sizes.get(n, some) for n in names})
    else:
        keep, files = pair_files(cams.names, files, img_dir, log=log)
    if len(keep) < len(cams):
        cams = Cameras([cams[i] for i in keep])
    extra = {c.name: {"image": f.stem} for c, f in zip(cams, files)}
    _check_camera_fields(root, {"masks": masks, "background": background}, len(cams))
    mask_files = None
    if masks and masks != "alpha":
        mask_files = [_expand(root, masks, i, c.name, frame, extra) for i, c in zip(keep, cams)]
    elif not masks:
        mask_files = _masks_beside(img_dir, files, log)
    bg = None
    if background:
        bg = ImageSet([_rgb(read_image(*_expand(root, background, i, c.name, 0, extra))) for i, c in zip(keep, cams)],
                      cams.names)
    mask_imgs = [read_image(p, f) for p, f in mask_files] if mask_files else None
    return cams, files, mask_imgs, [p for p, _ in mask_files] if mask_files else None, bg, (list(keep), extra)


def _masks_beside(img_dir: Path, files: list[Path], log) -> list | None:
    """(mask file, None) per image file from a masks/ or mask/ folder beside ``img_dir`` (paired by name), None
    when there is none; a DataError when only some images have their mask."""
    mask_dir = next((d for d in (img_dir.parent / "masks", img_dir.parent / "mask") if d.is_dir() and d != img_dir), None)
    if mask_dir is None:
        return None
    exts = IMAGE_EXTS + (".pbm", ".pgm")
    found = _regular(p for p in mask_dir.iterdir() if p.suffix.lower() in exts) or \
        _regular(p for p in mask_dir.glob("*/*") if p.suffix.lower() in exts)
    if not found:
        return None
    stems = [_relative_name(f, img_dir) for f in files]
    mk, mf = pair_files(stems, found, mask_dir, what="mask", partner="image", log=log)
    if len(mk) != len(stems):
        raise DataError(f"{mask_dir}: masks for {len(mk)} of the {len(stems)} images (missing: "
                        f"{_list(s for i, s in enumerate(stems) if i not in set(mk))}); give the masks pattern")
    return [(f, None) for f in mf]


def _size(path: Path) -> tuple[int, int]:
    img = read_image(path)
    return img.shape[1], img.shape[0]


# ------------------------------------------------------------------ loading
def load_capture(path, frame: int = 0, images: str = "", masks: str = "", background: str = "",
                 calibration: str = "", mask_threshold: int = 127, log=None, plates: int = 0) -> dict:
    """One frame of a capture: {"images": ImageSet, "masks": MaskSet | None, "cameras": Cameras,
    "background": ImageSet | None}. Empty patterns are auto-detected (see the module docstring). ``log``
    (the node's logger) receives the image-camera pairing and warnings about it. ``plates`` > 0: also
    "plates", up to that many frames of the background pattern (a video, '*' or {frame}) spread over all it
    holds, as a list of ImageSet, and "plate_frames", their frame numbers."""
    log = log or LOG
    root = Path(path)
    if not root.is_dir():
        raise DataError(f"capture folder {root} not found")
    if frame < 0:
        raise DataError(f"frame {frame} out of range (frames start at 0)")
    layout = detect_layout(root)
    given = {k: v for k, v in dict(images=images, masks=masks, background=background, calibration=calibration).items() if v}
    if not layout and "images" not in given:  # the images are found and paired with the cameras
        cams, files, mask_imgs, mask_files, bg, (keep, extra) = _generic(root, frame, masks, background, log, calibration)
        imgs = [read_image(f) for f in files]
        out = _assemble(cams, imgs, files, mask_imgs, bg, mask_threshold, masks or ("files" if mask_imgs else ""),
                        mask_files, log)
        if plates:
            out["plates"], out["plate_frames"] = _plates(root, background, list(zip(keep, cams.names)), extra, plates,
                                                         log)
        return out
    pat = {**layout, **given}
    if not layout and "calibration" not in pat:  # images given: the calibration is found as for the folder alone
        pat["calibration"] = "."
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
            _check_camera_fields(root, pat, len(calib))
            cams, raw, img_files = _per_folder_cameras(root, calib, pat["images"], frame, extra)
        else:
            cams = load_cameras(calib)
            raw = None
    except MissingImageSize:  # names first (they expand the patterns), then the sizes from those images
        names = camera_names(calib)
        _check_camera_fields(root, pat, len(names))
        img_files = [_expand(root, pat["images"], i, n, frame, extra) for i, n in enumerate(names)]
        raw = [read_image(p, f) for p, f in img_files]
        cams = load_cameras(calib, image_sizes=[(im.shape[1], im.shape[0]) for im in raw])
    _check_camera_fields(root, pat, len(cams))
    _check_camera_count(root, pat["images"], cams)
    for kind in ("images", "masks", "background"):
        if pat.get(kind) and pat[kind] != "alpha" and not extra:
            _check_unclaimed(root, pat[kind], cams, kind)
    if raw is None:
        img_files = [_expand(root, pat["images"], i, c.name, frame, extra) for i, c in enumerate(cams)]
        raw = [read_image(p, f) for p, f in img_files]
    bg = None
    if pat.get("background"):
        bg = ImageSet([_rgb(read_image(*_expand(root, pat["background"], i, c.name, 0, extra))) for i, c in enumerate(cams)],
                      cams.names)
    mask_imgs = mask_files = None
    found = None
    if pat.get("masks") and pat["masks"] != "alpha":
        found = [_expand(root, pat["masks"], i, c.name, frame, extra) for i, c in enumerate(cams)]
    elif not layout and "masks" not in pat and len({p.parent for p, f in img_files if f is None}) == 1 \
            and all(f is None for _, f in img_files):  # images= on an unknown folder: masks/ beside them, as without
        found = _masks_beside(img_files[0][0].parent, [p for p, _ in img_files], log)
    if found:
        mask_files = [p for p, _ in found]
        mask_imgs = [read_image(p, f) for p, f in found]
    out = _assemble(cams, raw, [p for p, _ in img_files], mask_imgs, bg, mask_threshold, pat.get("masks", ""), mask_files,
                    log)
    if plates:
        out["plates"], out["plate_frames"] = _plates(root, pat.get("background", ""), list(enumerate(cams.names)),
                                                     extra, plates, log)
    videos = sorted({p for p, f in img_files if f is not None})
    rates = sorted({r for r in (video_fps(p) for p in videos) if r})
    out["fps"] = rates[0] if len(rates) == 1 else None
    if len(rates) > 1:
        log.warning("capture: the cameras' videos state different frame rates %s: give the exports' fps", rates)
    return out


def _frame_count(root: Path, pattern: str, cam: int, name: str, extra: dict) -> int:
    """How many frames a per-camera pattern holds: a video's frame count, the files '*' matches, the {frame}
    files that exist from 0 on, or 1 for a single file."""
    import cv2

    path, index = _expand(root, pattern, cam, name, 0, extra)
    if index is not None:
        cap = cv2.VideoCapture(str(path))
        try:
            n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) if cap.isOpened() else 0
        finally:
            cap.release()
        if n <= 0:
            raise DataError(f"{path}: unreadable video, or it states no frame count")
        return n
    rel = pattern.format(cam=cam, cam1=cam + 1, name=name, frame=0, **extra.get(name, {}))
    if "*" in rel:
        return len(_regular(glob.glob(str(root / rel))))
    if "{frame" not in pattern:
        return 1
    n = 1
    while n < 1_000_000 and (root / pattern.format(cam=cam, cam1=cam + 1, name=name, frame=n,
                                                   **extra.get(name, {}))).is_file():
        n += 1
    return n


def _plates(root: Path, pattern: str, cams: list[tuple[int, str]], extra: dict, count: int, log=None):
    """Up to ``count`` frames of every camera's background ``pattern``, spread evenly over the frames the
    shortest camera holds: (list of ImageSet, frame numbers). Videos are decoded once, front to back."""
    import cv2

    if not pattern:
        raise NodeError(f"{root}: no background pattern: give one (a video, '*' or {{frame}} of the empty stage)")
    total = min(_frame_count(root, pattern, i, n, extra) for i, n in cams)
    pick = sorted(set(np.linspace(0, total - 1, min(count, total)).round().astype(int).tolist()))
    per_cam = []
    for i, name in cams:
        path, index = _expand(root, pattern, i, name, 0, extra)
        if index is None:
            per_cam.append([_rgb(read_image(*_expand(root, pattern, i, name, f, extra))) for f in pick])
            continue
        cap, got, want, f = cv2.VideoCapture(str(path)), [], set(pick), 0
        try:
            while f <= pick[-1]:
                ok = cap.grab()
                if not ok:  # AVI headers often state a frame or two more than the stream holds
                    if not got:
                        raise DataError(f"{path}: frame {f} could not be decoded ({total} stated)")
                    (log or LOG).warning("capture: %s states %d frames, decodes %d: the plate frames stop there",
                                         path, total, f)
                    break
                if f in want:
                    ok, img = cap.retrieve()
                    if not ok:
                        raise DataError(f"{path}: frame {f} could not be decoded")
                    got.append(cv2.cvtColor(img, cv2.COLOR_BGR2RGB) if img.ndim == 3 else _rgb(img))
                f += 1
        finally:
            cap.release()
        per_cam.append(got)
    names = [n for _, n in cams]
    pick = pick[:min(len(g) for g in per_cam)]
    return [ImageSet([per_cam[c][k] for c in range(len(cams))], names) for k in range(len(pick))], pick


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


CAMERA_FIELDS = ("cam", "cam1", "name", "image", "nerf_path")  # the fields that differ from camera to camera


def _fields(pattern: str) -> set[str] | None:
    """The field names of a pattern ({cam:03d} -> cam), None when it does not parse (``_expand`` says why)."""
    import string

    try:
        return {re.split(r"[.\[]", f)[0] for _, f, _, _ in string.Formatter().parse(pattern) if f is not None}
    except ValueError:
        return None


def _camera_field_example(root: Path, pattern: str) -> str:
    """``pattern`` with a camera field where the file names it matches hold their number: images/*.jpg
    matching image_0.jpg, image_1.jpg, ... -> images/image_{cam}.jpg ({cam1} when they count from 1)."""
    anywhere = re.sub(r"\{[^}]*\}", "*", pattern)
    files = _regular(glob.glob(str(root / anywhere)))[:10_000]
    if files:
        rel = Path(files[0].relative_to(root).as_posix())
        runs = list(re.finditer(r"\d+", rel.name))
        if runs:
            nums = _digits([f.stem for f in files])
            d = runs[-1].group()
            field = "{cam1}" if nums and min(nums) == 1 else f"{{cam:0{len(d)}d}}" if len(d) > 1 and d[0] == "0" else "{cam}"
            name = rel.name[:runs[-1].start()] + field + rel.name[runs[-1].end():]
            return (rel.parent / name).as_posix()
    if "*" in pattern:
        return pattern.replace("*", "{cam}", 1)
    stem, dot, ext = pattern.rpartition(".")
    return f"{stem}_{{cam}}.{ext}" if dot else pattern + "_{cam}"


def _check_camera_fields(root: Path, pat: dict, n: int):
    """A NodeError for an images, masks or background pattern without a camera field when there are several
    cameras: every camera would read the same file(s), and nothing downstream could tell."""
    if n < 2:
        return
    for kind in ("images", "masks", "background"):
        pattern = pat.get(kind)
        if not pattern or pattern == "alpha":
            continue
        fields = _fields(pattern)
        if fields is None or fields & set(CAMERA_FIELDS):
            continue
        star = " ('*' in a pattern means frames, not cameras)" if "*" in pattern else ""
        raise NodeError(f"param '{kind}': the pattern '{pattern}' has no camera field, so all {n} cameras would read "
                        "the same file; add {cam} (camera index from 0, e.g. {cam:03d}), {cam1} (from 1) or {name} "
                        f"(camera name){star}; e.g. '{_camera_field_example(root, pattern)}'")


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


def _check_unclaimed(root: Path, pattern: str, cams: Cameras, kind: str):
    """Files that match ``pattern`` for some camera name but for none of the calibration's cameras (its
    calibration file is missing, or the calibration is another set): a DataError naming them, not a camera
    dropped in silence."""
    if not re.search(r"\{(cam|cam1|name)[:}]", pattern) or re.search(r"\{(?!cam[:}]|cam1[:}]|name[:}]|frame[:}])", pattern):
        return
    anywhere = re.sub(r"\{[^}]*\}", "*", pattern)
    every = {Path(p) for p in glob.glob(str(root / anywhere)) if Path(p).is_file()}
    if len(every) > 100_000:
        return
    per_frame = re.sub(r"\{frame[^}]*\}", "*", pattern)
    claimed = set()
    for i, c in enumerate(cams):
        try:
            mine = per_frame.format(cam=i, cam1=i + 1, name=c.name)
        except (KeyError, IndexError, ValueError):
            return
        claimed.update(Path(p) for p in glob.glob(str(root / glob.escape(mine).replace("[*]", "*"))))
    stray = sorted((p for p in every - claimed), key=lambda p: natural_key(str(p)))
    if stray:
        rel = [p.relative_to(root).as_posix() for p in stray]
        raise DataError(f"{root}: {kind} file(s) {_list(rel, 4)} match the pattern '{pattern}' but no camera of the "
                        f"calibration ({len(cams)} cameras: {_list(cams.names, 4)}) claims them: is a calibration file "
                        f"missing? (or give a {kind} pattern that does not match them)")


PAD = 16  # a video encoder pads or crops each side to a multiple of 16 pixels


def _assemble(cams: Cameras, raw: list, files: list, mask_imgs, bg, threshold: int, mask_mode: str,
              mask_files: list | None = None, log=None) -> dict:
    cropped = list(cams)
    for i, (c, img, f) in enumerate(zip(cams, raw, files)):
        h, w = img.shape[:2]
        if (w, h) != (c.width, c.height):
            if not (0 <= c.width - w < PAD and 0 <= c.height - h < PAD):
                raise DataError(f"camera {i} '{c.name}': image {f} is {w}x{h} but the calibration is for "
                                f"{c.width}x{c.height}")
            # pose2sim's cam01/cam02: 1080 wide videos of a 1088 wide calibrated field of view
            (log or LOG).warning("capture: camera '%s': image %dx%d, calibration %dx%d: taken as the calibrated "
                                 "image less its last %d columns and %d rows (a video encoder's crop to a multiple "
                                 "of 8 or 16)", c.name, w, h, c.width, c.height, c.width - w, c.height - h)
            cropped[i] = c = c.cropped(0, 0, w, h)
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
    return {"images": images, "masks": masks, "cameras": Cameras(cropped) if cropped != list(cams) else cams, "background": bg}
