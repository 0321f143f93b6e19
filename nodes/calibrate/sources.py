"""Board images (or videos) of each camera, found by a pattern, and their detections.

Patterns are relative to the folder, '/'-separated:
    {name}   the camera's name (required when there are several cameras)
    {shot}   extrinsics only: the part of a file name that is the same instant in every camera
    *        any characters but '/' (intrinsic images: every match is one view)
A match that is a video (.mp4 .mov .avi .mkv) gives every ``every``-th frame as a view; for the extrinsics the
frame number is the shot (the videos must be synchronised).
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nodegraph.errors import NodeError

from .board import Board, detect
from .bundle import View

VIDEO_EXTS = (".mp4", ".mov", ".avi", ".mkv", ".m4v")


@dataclass
class Source:
    name: str        # camera
    shot: str        # "" for intrinsic images (each its own shot)
    path: Path


def _regex(pattern: str) -> re.Pattern:
    out, i = [], 0
    for m in re.finditer(r"\{name\}|\{shot\}|\*|\?", pattern):
        out.append(re.escape(pattern[i:m.start()]))
        tok = m.group()
        out.append({"{name}": r"(?P<name>[^/]+?)", "{shot}": r"(?P<shot>[^/]+?)", "*": r"[^/]*", "?": r"[^/]"}[tok])
        i = m.end()
    out.append(re.escape(pattern[i:]))
    return re.compile("".join(out) + r"\Z")


def find(root: Path, pattern: str, what: str, names: list[str] | None) -> list[Source]:
    """Files under ``root`` matching ``pattern`` (``what``: 'intrinsics' or 'extrinsics'), camera and shot read
    from the path. ``names`` (when given) limits and orders the cameras."""
    if pattern.count("{name}") > 1 or pattern.count("{shot}") > 1:
        raise NodeError(f"calibrate: {what} pattern '{pattern}': {{name}} and {{shot}} may appear once each")
    if what == "intrinsics" and "{shot}" in pattern:
        raise NodeError(f"calibrate: intrinsics pattern '{pattern}': {{shot}} belongs to the extrinsics (shared shots)")
    if "{name}" not in pattern and names and len(names) > 1:
        raise NodeError(f"calibrate: {what} pattern '{pattern}' has no {{name}} field: every camera would get the same "
                        f"files; write where the camera's name is, e.g. '{what}/{{name}}/*.png'")
    rx = _regex(pattern)
    glob = re.sub(r"\{name\}|\{shot\}", "*", pattern)
    out = []
    for p in sorted(root.glob(glob)):
        if not p.is_file():
            continue
        m = rx.match(p.relative_to(root).as_posix())
        if not m:
            continue
        name = m.groupdict().get("name") or (names[0] if names else "cam")
        shot = m.groupdict().get("shot") or ""
        if names and name not in names:
            continue
        if what == "extrinsics" and not shot and p.suffix.lower() not in VIDEO_EXTS:
            raise NodeError(f"calibrate: extrinsics pattern '{pattern}': needs {{shot}} (the part of the file name "
                            f"that is the same instant in every camera), or videos")
        out.append(Source(name, shot, p))
    return out


def _frames(path: Path, every: int):
    """(index, grey image) of a still, or of every ``every``-th frame of a video."""
    import cv2

    if path.suffix.lower() in VIDEO_EXTS:
        cap = cv2.VideoCapture(str(path))
        if not cap.isOpened():
            raise NodeError(f"calibrate: {path}: cannot open the video")
        k = 0
        try:
            while True:
                ok = cap.grab()
                if not ok:
                    break
                if k % every == 0:
                    ok, img = cap.retrieve()
                    if ok:
                        yield k, cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
                k += 1
        finally:
            cap.release()
        return
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise NodeError(f"calibrate: {path}: not an image OpenCV can read")
    yield None, img


def detect_all(sources: list[Source], names: list[str], board: Board, every: int, shared: bool,
               sizes: dict[str, tuple[int, int]], root: Path, log=None) -> tuple[list[View], dict]:
    """Detect the board in every source; fills ``sizes`` (name -> (w, h)) and refuses a camera whose images
    differ in size. Returns the views and per-camera counts (found, looked at)."""
    views, counts = [], {}
    for s in sources:
        cam = names.index(s.name)
        for k, gray in _frames(s.path, every):
            h, w = gray.shape
            if sizes.setdefault(s.name, (w, h)) != (w, h):
                raise NodeError(f"calibrate: camera '{s.name}': {s.path.relative_to(root)} is {w}x{h}, its other images "
                                f"are {sizes[s.name][0]}x{sizes[s.name][1]}")
            got = detect(gray, board)
            found, seen = counts.get(s.name, (0, 0))
            counts[s.name] = (found + (got is not None), seen + 1)
            if got is None:
                continue
            ids, uv = got if board.charuco else (np.arange(board.cols * board.rows), got)
            src = s.path.relative_to(root).as_posix() + ("" if k is None else f"#{k}")
            shot = (s.shot if k is None else f"{s.shot}f{k:06d}") if shared else f"{s.name}/{src}"
            views.append(View(cam, ("shared:" + shot) if shared else shot, uv, src, shared, ids))
    return views, counts
