"""The stages' data and port types: images, masks, cameras, volumes, meshes, skeletons, boxes.

Values are plain classes (ImageSet, MaskSet, VoxelGrid, SkeletonData; cameras: nodes.common.cameras;
meshes: trimesh.Trimesh; boxes: (2, 3) arrays). Port types (nodegraph.DataType) give each its on-disk form
in the cache and its preview in the report: images/masks as raw .npy per camera (soft alpha as .alpha.npy,
8-bit alpha as .alpha8.npy),
cameras as JSON, volumes as .npz, meshes as PLY, textured meshes as GLB, skeletons as JSON (+ .npy weights),
boxes as JSON.
"""
from __future__ import annotations

import json
import math
import os
import re
import threading
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

from nodegraph import DataError, DataType, Param

from . import previews
from .cameras import Cameras, unique_names
from .viewlayers import NONE, ViewLayers


def write_exr(path: Path, arr: np.ndarray, channel: str = "A"):
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {channel: np.ascontiguousarray(arr, dtype=np.float32)}) as f:
        f.write(str(path))


def read_exr(path: Path, channel: str = "A") -> np.ndarray:
    import OpenEXR

    try:
        with OpenEXR.File(str(path)) as f:
            return np.array(f.channels()[channel].pixels, dtype=np.float32)
    except Exception as exc:  # OpenEXR raises plain exceptions for corrupt files
        raise DataError(f"{path}: unreadable EXR ({exc})") from None


# ---------------------------------------------------------------- values
class _Lazy:
    """A per-camera set whose arrays may be produced on first use: a node can hand over a value whose costly
    host form (a read-back from the OpenCL device, a despill) is only computed when a reader or the cache asks
    for it. ``produce()`` returns the arrays; ``ready`` says whether they exist yet."""

    def __init__(self, produce, names):
        self._produce = produce
        self.names = list(names)
        unique_names(self.names, "camera")

    @property
    def ready(self) -> bool:
        return self._produce is None

    def _materialise(self):
        if self._produce is not None:
            produce, self._produce = self._produce, None
            self._set(*produce())

    def materialise(self):
        """Produce the arrays now (the engine does before keeping them, to time making apart from writing)."""
        self._materialise()


class _PasteBlock:
    """The last block ``_pasted`` filled in this process, kept for the next frame of the same image sizes: when
    nothing holds any of its images any more, the next frame's windows are pasted into it and only what the last
    frame's windows wrote outside the new ones is zeroed again, instead of a new zeroed block per frame (24 HD
    views: ~150 MB whose pages are faulted in afresh, 24 ms a frame and on a VM that hands freed memory back to its
    host 300 ms now and then; reused: ~7 ms). A process keeps one such block (150 MB for 24 HD views) once it has
    read windowed images, until its image sizes change.

    Each frame's images are views of one array over the block (``frame``, made from a memoryview of it: NumPy ties
    every view of it, and every view of those, to that array): the block is free when that array is gone, which a
    weak reference tells without counting references."""

    lock = threading.Lock()
    last: "_PasteBlock | None" = None

    def __init__(self, shapes: list[tuple]):
        self.shapes = shapes
        sizes = [math.prod(sh) for sh in shapes]
        self.starts = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
        self.block = np.zeros(int(self.starts[-1]), np.uint8)
        self.windows = [(0, 0, 0, 0)] * len(shapes)    # what the last frame wrote, per image
        self.frame: "weakref.ref | None" = None          # the last frame's array over the block

    def images(self) -> list[np.ndarray]:
        """(H, W, 3) views of a new array over the block, whose life ``free`` watches."""
        frame = np.frombuffer(memoryview(self.block), np.uint8)
        self.frame = weakref.ref(frame)
        return [frame[a:b].reshape(sh) for a, b, sh in zip(self.starts[:-1], self.starts[1:], self.shapes)]

    def free(self) -> bool:
        """Whether nothing holds the last frame's images (or any view of them: a texture's packed buffer)."""
        return self.frame is None or self.frame() is None


def _clear_outside(im: np.ndarray, old, new):
    """Zero the pixels of box ``old`` (x0, y0, x1, y1) that box ``new`` does not cover."""
    ox0, oy0, ox1, oy1 = old
    nx0, ny0, nx1, ny1 = new
    if nx0 >= ox1 or nx1 <= ox0 or ny0 >= oy1 or ny1 <= oy0 or nx1 <= nx0 or ny1 <= ny0:
        im[oy0:oy1, ox0:ox1] = 0              # disjoint (or nothing new): all of the old box
        return
    im[oy0:ny0, ox0:ox1] = 0                  # the rows above and below the new box
    im[ny1:oy1, ox0:ox1] = 0
    y0, y1 = max(oy0, ny0), min(oy1, ny1)     # beside it, on the rows they share
    im[y0:y1, ox0:nx0] = 0
    im[y0:y1, nx1:ox1] = 0


def _pasted(crops, shapes, windows) -> list[np.ndarray]:
    """Whole images from their windows' pixels: the windowed ones in one zeroed block (untouched pages cost nothing
    until read; a texture takes the block as it is; the last frame's block again when nothing holds it,
    ``_PasteBlock``), read-only; a camera without a window is its crop itself."""
    sizes = [tuple(int(x) for x in sh) for sh, w in zip(shapes, windows) if w is not None]
    boxes = [tuple(int(x) for x in w) for w in windows if w is not None]
    with _PasteBlock.lock:
        pb = _PasteBlock.last
        if pb is not None and pb.shapes == sizes and pb.free():
            blank = pb.images()
            for im, old, new in zip(blank, pb.windows, boxes):
                _clear_outside(im, old, new)
        else:
            pb = _PasteBlock.last = _PasteBlock(sizes)
            blank = pb.images()
        pb.windows = boxes
        blank = iter(blank)
        images = []
        for a, w in zip(crops, windows):
            if w is None:
                images.append(a)
                continue
            x0, y0, x1, y1 = w
            im = next(blank)
            im[y0:y1, x0:x1] = a
            im.flags.writeable = False            # as the memory-mapped images are
            images.append(im)
        if images and pb.frame is not None and pb.frame() is not None:
            pb.frame().flags.writeable = False     # a reader's view of the whole block (one_block) is read-only too
    return images


def one_block(arrays) -> np.ndarray | None:
    """The bytes of uint8 ``arrays`` as one 1-D array, without a copy, where they lie one after the other in one
    block of memory (``_pasted``'s, ``_PasteBlock``); None where they do not."""
    def root(a):
        while isinstance(a.base, np.ndarray):
            a = a.base
        return a

    if not arrays:
        return None
    first = root(arrays[0])
    if first.dtype != np.uint8 or first.ndim != 1 or not first.flags.c_contiguous:
        return None
    start = at = arrays[0].__array_interface__["data"][0]
    for a in arrays:
        if (not isinstance(a, np.ndarray) or a.dtype != np.uint8 or not a.flags.c_contiguous or root(a) is not first
                or a.__array_interface__["data"][0] != at):
            return None
        at += a.nbytes
    off = start - first.__array_interface__["data"][0]
    return first[off:off + (at - start)]


class ImageSet(_Lazy):
    """One frame of a capture: an RGB uint8 image (H, W, 3) per camera, in camera order.
    ``ImageSet(images, names)``, or ``ImageSet.lazy(produce, names)`` (``produce() -> images`` or
    ``(images, windows)``).

    ``windows``: per camera (x0, y0, x1, y1) or None, the producer's promise that the image is black (0) outside
    that box (a key's despilled images: nothing is sampled far from the matte). The cache then stores the boxes'
    pixels only (24 HD views of the synthetic figure: ~30 % of the bytes to write, hash and read back).
    ``ImageSet.cropped(crops, shapes, windows, names)`` holds such images as their windows' pixels alone (``crops``:
    per camera the (y1 - y0, x1 - x0, 3) box, or the whole image where its window is None); the whole images are
    made (in one block, ``_PasteBlock``) only when a reader asks for ``images``: a key whose despilled images go to the cache
    alone (a texture after tracking reads them in another unit) writes no 149 MB block of 24 HD frames. A lazy
    set's ``produce()`` may return ``("crops", crops, shapes, windows)``."""

    def __init__(self, images: list[np.ndarray], names: list[str] | None = None, windows=None):
        super().__init__(None, names or [f"cam{i:03d}" for i in range(len(images))])
        self._set(images, windows)

    @classmethod
    def lazy(cls, produce, names: list[str]) -> "ImageSet":
        s = cls([], names)

        def made():
            out = produce()
            return out if isinstance(out, tuple) else (out,)
        s._produce = made
        return s

    @classmethod
    def cropped(cls, crops, shapes, windows, names: list[str]) -> "ImageSet":
        s = cls([], names)
        s._set("crops", crops, shapes, windows)
        return s

    def _set(self, images, windows=None, *crops_form):
        if isinstance(images, str) and images == "crops":   # ("crops", crops, shapes, windows): see the class
            crops, (shapes, windows) = windows, crops_form
            self._images, self._crops, self._shapes = None, list(crops), [tuple(x) for x in shapes]
            self._windows = [None if w is None else list(w) for w in windows]
            return
        self._images = list(images)
        self._windows = None if windows is None else list(windows)
        self._crops = self._shapes = None
        if CHECK_PROMISES and self._windows is not None and all(
                w is None or _is_box(w, im.shape[1], im.shape[0]) for im, w in zip(self._images, self._windows)):
            problem = _outside(self._images, self._windows)
            if problem:
                raise AssertionError(f"ImageSet.windows: {problem}")

    @property
    def windows(self) -> list | None:
        self._materialise()
        return self._windows

    @property
    def crops(self) -> tuple[list[np.ndarray], list[tuple]] | None:
        """(crops, shapes) where the set holds its windowed images as their windows' pixels, else None."""
        self._materialise()
        return None if self._crops is None else (self._crops, self._shapes)

    @property
    def images(self) -> list[np.ndarray]:
        self._materialise()
        if self._images is None:      # windows' pixels pasted into one zeroed block (as the cache's reader does)
            self._images = _pasted(self._crops, self._shapes, self._windows)
        return self._images

    def __len__(self):
        return len(self.names)


class MaskSet(_Lazy):
    """Silhouettes per camera: binary uint8 masks (0 / 255) and optional soft alpha (float32 0..1).

    ``alpha8``: the soft alpha as 8-bit levels (uint8 0..255) where the producer made it so (the keys): ``alpha``
    is then ``alpha8 / 255`` in float32, computed when first read, and the cache stores the levels (a quarter of
    the bytes; the same float32 values come back). It may be given as a function returning the list, called when
    ``alpha8`` or ``alpha`` is first read (Masks.load: a reader of the masks alone makes no whole-frame levels).
    ``device``: the same silhouettes already on the OpenCL device (nodes.common.silhouettes.SilhouetteBits),
    when the producer made them there; a reader that can use them (the hull) then needs no host masks at all.
    ``MaskSet.lazy(produce, names, device=...)`` defers the host masks (``produce() -> (masks, alpha)`` or
    ``(masks, None, alpha8)``); ``make_device`` (a function returning the SilhouetteBits) defers the device's too,
    until a reader asks for ``device``."""

    def __init__(self, masks: list[np.ndarray], alpha: list[np.ndarray] | None = None, names: list[str] | None = None,
                 device=None, alpha8=None, boxes: list | None = None):
        super().__init__(None, names or [f"cam{i:03d}" for i in range(len(masks))])
        self._set(masks, alpha, alpha8, boxes)
        self._device, self._make_device = device, None

    @classmethod
    def lazy(cls, produce, names: list[str], device=None, make_device=None) -> "MaskSet":
        s = cls([], None, names, device)
        s._produce = produce
        s._make_device = make_device
        return s

    def _set(self, masks, alpha, alpha8=None, boxes=None):
        if alpha is not None and alpha8 is not None:
            raise ValueError("MaskSet: give alpha or alpha8, not both")
        self._masks, self._alpha = list(masks), (list(alpha) if alpha is not None else None)
        # alpha8 may come as a function making the levels when first read (Masks.load: a reader of the masks alone,
        # the texture, then makes no whole-frame levels: 24 HD planes of fresh memory a frame)
        self._alpha8_make = alpha8 if callable(alpha8) else None
        self._alpha8 = list(alpha8) if alpha8 is not None and not callable(alpha8) else None
        self._boxes = None if boxes is None else [None if b is None else tuple(b) for b in boxes]
        if CHECK_PROMISES and self._boxes is not None and all(
                b is None or _is_box(b, m.shape[1], m.shape[0]) for m, b in zip(self._masks, self._boxes)):
            for planes in (self._masks, self._alpha8, self._alpha):     # (levels still to be made: pasted in
                                                                          # their stored box, 0 outside it)
                problem = None if planes is None else _outside(planes, self._boxes)
                if problem:
                    raise AssertionError(f"MaskSet.boxes: {problem}")

    @property
    def boxes(self) -> list | None:
        """Per camera (x0, y0, x1, y1) or None: the producer's promise that the mask and its alpha are 0 (every bit:
        no -0.0) outside that box (a key's alpha window, the clean-up's working box), so readers look at the box alone: the cache's
        writer finds each plane's non-zero box there, not in the whole HD frame. None: not known."""
        self._materialise()
        return self._boxes

    @property
    def device(self):
        if self._make_device is not None:
            make, self._make_device = self._make_device, None
            self._device = make()
        return self._device

    @device.setter
    def device(self, value):
        self._device, self._make_device = value, None

    @property
    def masks(self) -> list[np.ndarray]:
        self._materialise()
        return self._masks

    def _levels(self):
        make = self._alpha8_make
        if make is not None:            # made first, then the maker dropped: a reader racing in meanwhile makes them
            levels = list(make())       # too (the same arrays' values) instead of reading None
            self._alpha8, self._alpha8_make = levels, None
        return self._alpha8

    @property
    def alpha(self) -> list[np.ndarray] | None:
        self._materialise()
        if self._alpha is None and self._levels() is not None:
            self._alpha = [np.divide(a, np.float32(255), dtype=np.float32) for a in self._alpha8]
        return self._alpha

    @property
    def alpha8(self) -> list[np.ndarray] | None:
        """The soft alpha's 8-bit levels when the set was made from them, else None (read ``alpha``)."""
        self._materialise()
        return self._levels()

    def __len__(self):
        return len(self.names)


class PlateMixture:
    """Per camera a per-pixel Gaussian mixture of the background (capture.background): ``mean`` (K, H, W, 3) uint8 and
    ``sigma`` (K, H, W, 3) float16 per channel, components by weight, slots that are no background repeating the
    first; ``weight`` (K, H, W) float32 (0 on those slots)."""

    def __init__(self, mean: list[np.ndarray], sigma: list[np.ndarray], weight: list[np.ndarray], names: list[str]):
        self.mean, self.sigma, self.weight, self.names = list(mean), list(sigma), list(weight), list(names)

    def __len__(self):
        return len(self.names)


@dataclass
class VoxelGrid:
    """A regular voxel grid over an axis-aligned box. ``occupancy[i, j, k]`` is the voxel whose centre is
    bbox_min + (i + 0.5, j + 0.5, k + 0.5) * voxel_size. uint8 (0/1) or float32 (soft, 0..1)."""

    occupancy: np.ndarray
    bbox_min: np.ndarray
    bbox_max: np.ndarray
    colors: np.ndarray | None = None  # (nx, ny, nz, 3) uint8, optional

    def __post_init__(self):
        self.bbox_min = np.asarray(self.bbox_min, dtype=np.float64).reshape(3)
        self.bbox_max = np.asarray(self.bbox_max, dtype=np.float64).reshape(3)

    @property
    def voxel_size(self) -> np.ndarray:
        return (self.bbox_max - self.bbox_min) / np.array(self.occupancy.shape[:3])

    def centers(self) -> np.ndarray:
        """World coordinates of all voxel centres, (nx, ny, nz, 3)."""
        axes = [self.bbox_min[a] + (np.arange(n) + 0.5) * self.voxel_size[a] for a, n in enumerate(self.occupancy.shape[:3])]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)


@dataclass
class SkeletonData:
    """A joint tree: joint positions (J, 3), parent index per joint (-1 for the root), optional LBS
    weights (V, J) for a mesh's vertices, and optionally its motion over frames: ``rotations`` (F, J, 3, 3)
    and ``translations`` (F, J, 3) take the rest pose (``joints``, the mesh the weights belong to) to each
    frame, x -> R x + t per joint's bone (the skinning matrices); ``frames`` their frame numbers."""

    joints: np.ndarray
    parents: list[int]
    names: list[str] = field(default_factory=list)
    weights: np.ndarray | None = None
    rotations: np.ndarray | None = None
    translations: np.ndarray | None = None
    frames: list[int] | None = None

    def problem(self) -> str | None:
        """What is inconsistent (shapes, parents that do not form a tree), or None."""
        j = len(self.parents)
        joints = np.asarray(self.joints)
        if joints.shape != (j, 3):
            return f"joints have shape {joints.shape}, expected ({j}, 3) for {j} parents"
        if self.names and len(self.names) != j:
            return f"{len(self.names)} names for {j} joints"
        if sum(1 for p in self.parents if p < 0) != 1 and j:
            return "a skeleton needs exactly one root (parent -1)"
        for i, p in enumerate(self.parents):
            seen, q = {i}, p
            while q >= 0:
                if q >= j or q in seen:
                    return f"joint {i}: parent chain is not a tree (parent {q})"
                seen.add(q)
                q = self.parents[q]
        if self.weights is not None and (np.ndim(self.weights) != 2 or np.shape(self.weights)[1] != j):
            return f"weights have shape {np.shape(self.weights)}, expected (vertices, {j})"
        if (self.rotations is None) != (self.translations is None):
            return "rotations and translations come together"
        if self.rotations is not None:
            f = np.shape(self.rotations)[0]
            if np.shape(self.rotations) != (f, j, 3, 3) or np.shape(self.translations) != (f, j, 3):
                return f"motion shapes {np.shape(self.rotations)} / {np.shape(self.translations)} do not fit {j} joints"
            if self.frames is not None and len(self.frames) != f:
                return f"{len(self.frames)} frame numbers for {f} frames of motion"
        return None


# ---------------------------------------------------------------- types
def _save_array(path: Path, arr: np.ndarray):
    np.save(path, np.ascontiguousarray(arr), allow_pickle=False)


def _load_array(path: Path, mapped: bool = True) -> np.ndarray:
    """A stored array, memory-mapped read-only: no read until used, and half the page-fault cost of a private
    (copy-on-write) map (24 HD images: 17 vs 36-44 ms). A node must not edit its inputs in place anyway (a
    frame unit hands the same value to every consumer); one that tries gets numpy's read-only error. ``mapped``
    False: read whole into memory, writable (values that bindings take as buffers: MeshSequence)."""
    try:
        if mapped:
            return _map_array(path)
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: unreadable array ({exc})") from None


# the header np.save writes: "{'descr': '<f4', 'fortran_order': False, 'shape': (1080, 1920, 3), }" (padded)
_NPY_HEADER = re.compile(r"\{'descr': '([<>|=][a-zA-Z]\d*)', 'fortran_order': (False|True), 'shape': \(((?:\d+, )*(?:\d+,?)?)\), \}")


def _map_array(path: Path) -> np.ndarray:
    """np.load(path, mmap_mode="r") as a plain read-only array over an mmap of the file, its header read directly
    when it is the one np.save writes (np.memmap resolves the path through every folder above it, np.load re-opens
    the file and parses the header as a Python literal: 0.3 ms an array, 24 HD images 7.5 ms a frame; this: 0.05
    ms an array). Any other header goes through NumPy's own reader; object arrays are refused as np.load refuses
    them (nothing is unpickled)."""
    import mmap

    with open(path, "rb") as f:
        version = np.lib.format.read_magic(f)
        if version not in ((1, 0), (2, 0)):
            return np.load(path, mmap_mode="r", allow_pickle=False)
        size = int.from_bytes(f.read(2 if version == (1, 0) else 4), "little")
        m = _NPY_HEADER.fullmatch(f.read(size).decode("latin1").rstrip())
        try:
            dtype = None if m is None else np.dtype(m.group(1))
        except TypeError:                                   # not a type code NumPy knows: its reader says so
            dtype = None
        if dtype is None or dtype.itemsize == 0:
            return np.load(path, mmap_mode="r", allow_pickle=False)
        if dtype.hasobject:
            raise ValueError("an object array (Python objects are not read from the cache)")
        shape = tuple(int(x) for x in m.group(3).split(",") if x.strip())
        offset = f.tell()
        count = math.prod(shape)
        held = os.fstat(f.fileno()).st_size - offset
        if count * dtype.itemsize > held:
            raise ValueError(f"the header promises {count * dtype.itemsize} bytes of data, the file holds {held}")
        if count == 0:
            out = np.zeros(shape, dtype)
            out.flags.writeable = False
            return out
        mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    return np.frombuffer(mm, dtype, count=count, offset=offset).reshape(shape, order="F" if m.group(2) == "True" else "C")


def _mask_of_levels(levels: np.ndarray, hint=None) -> np.ndarray:
    """The binary mask (0 / 255) of 8-bit alpha levels: alpha >= 128, as the keys make it (cv2.threshold: one pass);
    ``hint``: a box (x0, y0, x1, y1) the levels are 0 outside of, thresholded alone."""
    import cv2

    levels = np.asarray(levels, np.uint8)
    if hint is None:
        return cv2.threshold(levels, 127, 255, cv2.THRESH_BINARY)[1]
    out = np.zeros(levels.shape, np.uint8)
    x0, y0, x1, y1 = (int(v) for v in hint)
    if x1 > x0 and y1 > y0:
        out[y0:y1, x0:x1] = cv2.threshold(np.ascontiguousarray(levels[y0:y1, x0:x1]), 127, 255, cv2.THRESH_BINARY)[1]
    return out


def bounding_rect(flags: np.ndarray, hint=None) -> tuple[int, int, int, int]:
    """cv2.boundingRect of an 8-bit image (x, y, w, h of its non-zero pixels; all 0 when none), looked for inside
    the box ``hint`` (x0, y0, x1, y1) alone when given: the promise that nothing outside it is non-zero."""
    import cv2

    if hint is None:
        return cv2.boundingRect(np.ascontiguousarray(flags))
    x0, y0, x1, y1 = (int(v) for v in hint)
    if x1 <= x0 or y1 <= y0:
        return (0, 0, 0, 0)
    x, y, w, h = cv2.boundingRect(np.ascontiguousarray(flags[y0:y1, x0:x1]))
    return (x + x0, y + y0, w, h) if w and h else (0, 0, 0, 0)


def _is_box(b, width: int, height: int) -> bool:
    """(x0, y0, x1, y1) of whole numbers with 0 <= x0 <= x1 <= width, 0 <= y0 <= y1 <= height."""
    return (isinstance(b, (list, tuple)) and len(b) == 4 and all(isinstance(v, (int, np.integer)) for v in b)
            and 0 <= b[0] <= b[2] <= width and 0 <= b[1] <= b[3] <= height)


def _boxes_problem(boxes, planes, what: str, of: str) -> str | None:
    """A type check's message for ``boxes`` (one per plane, or None) that are not boxes of whole numbers inside their
    planes (``_is_box``), or None."""
    if boxes is None:
        return None
    if len(boxes) != len(planes):
        return f"{len(boxes)} {what}es for {len(planes)} {of}s" if what == "box" else f"{len(boxes)} {what}s for {len(planes)} {of}s"
    for i, (b, a) in enumerate(zip(boxes, planes)):
        if b is not None and not _is_box(b, a.shape[1], a.shape[0]):
            return f"{of} {i}: {what} {b} is not a box (x0, y0, x1, y1) of whole numbers inside its {a.shape[1]}x{a.shape[0]}"
    return None


def _outside(planes, boxes) -> str | None:
    """Where a promised box is broken: the first plane with a bit set outside its box (-0.0 counts), or None."""
    for i, (a, b) in enumerate(zip(planes, boxes)):
        if b is None or a is None:
            continue
        flags = np.asarray(a).view(np.uint8).reshape(np.shape(a)[0], np.shape(a)[1], -1).any(axis=2)
        x0, y0, x1, y1 = b
        flags[y0:y1, x0:x1] = False
        if flags.any():
            return f"plane {i} is not 0 outside its box {list(b)}"
    return None


CHECK_PROMISES = os.environ.get("VOLCAP_CHECK_PROMISES") == "1"   # the tests set it: every box promise is verified


def _nonzero_box(a: np.ndarray, hint=None) -> tuple[np.ndarray, list]:
    """(the box of ``a``'s non-zero pixels cut out of it, [height, width, x0, y0, x1, y1]); ``a`` (H, W) of any
    dtype (a float alpha's box: its pixels != 0, and any -0.0); ``hint``: a box nothing outside of is non-zero."""
    a = np.asarray(a)
    if a.dtype == np.uint8:
        flags = a
    else:                           # a float's -0.0 is inside the box too: every bit comes back
        flags = np.ascontiguousarray((a != 0) | np.signbit(a) if a.dtype.kind == "f" else a != 0).view(np.uint8)
    x, y, w, h = bounding_rect(flags, hint)   # an 8-bit image: the box of its non-zero pixels
    return a[y:y + h, x:x + w], [int(a.shape[0]), int(a.shape[1]), x, y, x + w, y + h]


def _is_mask_of_levels(mask, cut: np.ndarray, box, hint=None) -> bool:
    """Whether ``mask`` is ``_mask_of_levels`` of the levels whose non-zero box ``box`` holds ``cut`` (0 outside
    it): its own non-zero pixels inside that box, and there the threshold of the cut. (The two boxes, not two
    whole images: an HD frame's 24 views 53-70 -> a few ms.)"""
    import cv2

    h, w, x0, y0, x1, y1 = box
    m = np.asarray(mask)
    if m.shape != (h, w):
        return False
    if m.dtype != np.uint8:          # the whole images
        full = np.zeros((h, w), np.uint8)
        full[y0:y1, x0:x1] = cut
        return bool(np.array_equal(m, _mask_of_levels(full)))
    mx, my, mw, mh = bounding_rect(m, hint)
    if cut.size == 0:                # no level above 0: the mask must be empty too
        return not (mw and mh)
    if mw and mh and not (x0 <= mx and y0 <= my and mx + mw <= x1 and my + mh <= y1):
        return False
    return bool(np.array_equal(m[y0:y1, x0:x1], _mask_of_levels(cut)))


def _paste(a: np.ndarray, box, path: Path) -> np.ndarray:
    """The (height, width) array, 0 outside the box [height, width, x0, y0, x1, y1] that ``a`` fills."""
    h, w, x0, y0, x1, y1 = box
    if a.shape != (y1 - y0, x1 - x0) or not (0 <= x0 <= x1 <= w and 0 <= y0 <= y1 <= h):
        raise DataError(f"{path}: {a.shape} does not fill its box {box[2:]} of {w}x{h}")
    out = np.zeros((h, w), a.dtype)       # untouched pages cost nothing until read
    out[y0:y1, x0:x1] = a
    out.flags.writeable = False
    return out


class Images(DataType):
    """Stored as one raw .npy per camera (read by memory map: loading a frame of 24 HD images costs nothing
    until a kernel reads it; see bench/formats.py for PNG and compressed forms measured against it)."""

    name = "Images"
    kept_by_default = False  # large: passed in memory within a frame unless kept

    @classmethod
    def check(cls, v):
        if not isinstance(v, ImageSet):
            return f"expected an ImageSet, got {type(v).__name__}"
        if not v.ready:
            return None  # produced later by its own node's code, checked when it is
        if v.crops is not None:   # windows' pixels: checked as they are (the whole images are not made for it)
            crops, shapes = v.crops
            if not (len(crops) == len(shapes) == len(v.windows) == len(v.names)):
                return f"{len(crops)} crops, {len(shapes)} shapes and {len(v.windows)} windows for {len(v.names)} names"
            for i, (c, sh, w) in enumerate(zip(crops, shapes, v.windows)):
                if len(sh) != 3 or sh[2] != 3 or not (w is None or _is_box(w, sh[1], sh[0])):
                    return f"image {i}: window {w} is not a box (x0, y0, x1, y1) inside its {tuple(sh)}"
                want = tuple(sh) if w is None else (w[3] - w[1], w[2] - w[0], 3)
                if not (isinstance(c, np.ndarray) and c.dtype == np.uint8 and c.shape == want):
                    return f"image {i}: its pixels {getattr(c, 'shape', None)} do not fill window {w} of {tuple(sh)}"
            return None
        for i, im in enumerate(v.images):
            if not (isinstance(im, np.ndarray) and im.dtype == np.uint8 and im.ndim == 3 and im.shape[2] == 3):
                return f"image {i} must be an (H, W, 3) uint8 array"
        if len(v.images) != len(v.names):
            return f"{len(v.images)} images but {len(v.names)} names"
        return _boxes_problem(v.windows, v.images, "window", "image")

    @classmethod
    def save(cls, v: ImageSet, folder: Path):
        windows = v.windows
        held = v.crops
        if held is not None:   # the windows' pixels as they are: the same files as cut from the whole images
            crops, shapes = held
        else:
            crops = [im if not windows or windows[i] is None else im[windows[i][1]:windows[i][3], windows[i][0]:windows[i][2]]
                     for i, im in enumerate(v.images)]
            shapes = [im.shape for im in v.images]
        for i, c in enumerate(crops):   # files by position: any camera name (a path, a dot) is a name
            _save_array(folder / f"{i:04d}.npy", c)
        (folder / "names.json").write_text(json.dumps(v.names))
        if windows:   # the images' sizes and the boxes whose pixels were stored (black outside them)
            (folder / "windows.json").write_text(json.dumps({"shapes": [list(x) for x in shapes],
                                                             "windows": [None if w is None else [int(x) for x in w]
                                                                         for w in windows]}))

    @classmethod
    def load(cls, folder: Path) -> ImageSet:
        names = json.loads((folder / "names.json").read_text())
        arrays = [_load_array(folder / f"{i:04d}.npy") for i in range(len(names))]
        if not (folder / "windows.json").is_file():
            return ImageSet(arrays, names)
        doc = json.loads((folder / "windows.json").read_text())
        for i, (a, shape, w) in enumerate(zip(arrays, doc["shapes"], doc["windows"])):
            if w is None:
                continue
            x0, y0, x1, y1 = w
            if a.shape != (y1 - y0, x1 - x0, 3) or not (0 <= x0 <= x1 <= shape[1] and 0 <= y0 <= y1 <= shape[0]):
                raise DataError(f"{folder / f'{i:04d}.npy'}: {a.shape} does not fill its window {w} of {shape}")
        return ImageSet(_pasted(arrays, doc["shapes"], doc["windows"]), names, doc["windows"])

    @classmethod
    def preview(cls, value, size, companions):
        return previews.draw_images(value, size, companions)


class Masks(DataType):
    """Stored as one raw .npy per camera (uint8), and the soft alpha as .alpha.npy (float32), or as .alpha8.npy
    (uint8 levels) when the set carries ``alpha8``; masks that are exactly the levels' alpha >= 128 (the keys'
    and key.cleanup's) are then not stored but made from the levels when loaded (the same masks, half the
    bytes to write and hash). Each stored plane holds only the box of its non-zero pixels (its box in
    names.json; zeros around it when loaded)."""

    name = "Masks"
    kept_by_default = False  # large: passed in memory within a frame unless kept

    @classmethod
    def check(cls, v):
        if not isinstance(v, MaskSet):
            return f"expected a MaskSet, got {type(v).__name__}"
        if not v.ready:
            return None  # produced later by its own node's code, checked when it is
        for i, m in enumerate(v.masks):
            if not (isinstance(m, np.ndarray) and m.dtype == np.uint8 and m.ndim == 2):
                return f"mask {i} must be an (H, W) uint8 array"
        if len(v.masks) != len(v.names):
            return f"{len(v.masks)} masks but {len(v.names)} names"
        if v.alpha8 is not None:
            if len(v.alpha8) != len(v.masks):
                return "alpha8 must have one image per mask"
            for i, (a, m) in enumerate(zip(v.alpha8, v.masks)):
                if not (isinstance(a, np.ndarray) and a.dtype == np.uint8 and a.shape == m.shape):
                    return f"alpha8 {i} must be a uint8 array the shape of its mask"
        elif v.alpha is not None:
            if len(v.alpha) != len(v.masks):
                return "alpha must have one image per mask"
            for i, (a, m) in enumerate(zip(v.alpha, v.masks)):
                if np.shape(a) != m.shape:
                    return f"alpha {i} must be an array the shape of its mask {m.shape}, got {np.shape(a)}"
        return _boxes_problem(v.boxes, v.masks, "box", "mask")

    @classmethod
    def save(cls, v: MaskSet, folder: Path):
        levels = v.alpha8   # 8-bit alpha stays 8-bit on disk: (H, W) uint8 per camera, .alpha8.npy
        hints = v.boxes or [None] * len(v.masks)   # where the producer says the planes are 0 outside: looked at alone
        # every plane is stored as the box of its non-zero pixels (0 outside it): the same arrays come back. A person's
        # masks and float alpha after key.consensus (pose2sim_single, 4 x 1080p): 41.6 -> 8.0 MB per frame to write and hash
        cuts = None if levels is None else [_nonzero_box(np.asarray(a, np.uint8), h) for a, h in zip(levels, hints)]
        # masks that are the levels' alpha >= 128 (the keys' and their clean-up's) are not stored: read back from them
        derived = cuts is not None and all(_is_mask_of_levels(m, cut, box, h)
                                           for m, (cut, box), h in zip(v.masks, cuts, hints))
        boxes = {"mask_boxes": [], "alpha8_boxes": [], "alpha_boxes": []}

        def put(name, kind, a, hint):
            cut, box = _nonzero_box(a, hint)
            _save_array(folder / name, cut)
            boxes[kind].append(box)

        for i, m in enumerate(v.masks):
            if not derived:
                put(f"{i:04d}.npy", "mask_boxes", m, hints[i])
            if cuts is not None:
                a, box = cuts[i]
                _save_array(folder / f"{i:04d}.alpha8.npy", a)
                boxes["alpha8_boxes"].append(box)
            elif v.alpha is not None:
                put(f"{i:04d}.alpha.npy", "alpha_boxes", np.asarray(v.alpha[i], np.float32), hints[i])
        has = levels is not None or v.alpha is not None
        (folder / "names.json").write_text(json.dumps({"names": v.names, "alpha": has, "alpha8": levels is not None,
                                                       "masks_from_alpha8": derived,
                                                       **{k: b for k, b in boxes.items() if b}}))

    @classmethod
    def load(cls, folder: Path) -> MaskSet:
        meta = json.loads((folder / "names.json").read_text())
        names = meta["names"]

        def read(name, kind, i):   # entries written before planes were boxed hold whole images
            a = _load_array(folder / name)
            return _paste(a, meta[kind][i], folder / name) if kind in meta else a

        def boxes(*kinds):   # per camera the union of its stored planes' boxes (the set is 0 outside it), or None
            stored = [meta[k] for k in kinds if k in meta]
            if not stored or len(stored) < len(kinds):
                return None
            out = []
            for i in range(len(names)):
                bs = [(b[2], b[3], b[4], b[5]) for b in (k[i] for k in stored) if b[4] > b[2] and b[5] > b[3]]
                out.append((min(b[0] for b in bs), min(b[1] for b in bs), max(b[2] for b in bs), max(b[3] for b in bs))
                           if bs else (0, 0, 0, 0))
            return out

        if meta.get("alpha8"):
            derived = meta.get("masks_from_alpha8")
            box = boxes("alpha8_boxes") if derived else boxes("alpha8_boxes", "mask_boxes")
            if derived and "alpha8_boxes" in meta:   # each mask the threshold of its stored levels' box, pasted (read-
                crops = []                           # only, as stored planes are); the whole levels when read
                for i in range(len(names)):          # (the crops mapped: read, they cost 3 ms more a frame)
                    path = folder / f"{i:04d}.alpha8.npy"
                    c = _load_array(path)
                    _, _, x0, y0, x1, y1 = meta["alpha8_boxes"][i]
                    if c.shape != (y1 - y0, x1 - x0):
                        raise DataError(f"{path}: {c.shape} does not fill its box {meta['alpha8_boxes'][i][2:]}")
                    crops.append(c)
                masks = [_paste(_mask_of_levels(c) if c.size else c, meta["alpha8_boxes"][i],
                                folder / f"{i:04d}.alpha8.npy") for i, c in enumerate(crops)]
                return MaskSet(masks, None, names, boxes=box, alpha8=lambda: [
                    _paste(c, meta["alpha8_boxes"][i], folder / f"{i:04d}.alpha8.npy") for i, c in enumerate(crops)])
            levels = [read(f"{i:04d}.alpha8.npy", "alpha8_boxes", i) for i in range(len(names))]
            masks = [_mask_of_levels(a, None if box is None else box[i]) if derived
                     else read(f"{i:04d}.npy", "mask_boxes", i) for i, a in enumerate(levels)]
            return MaskSet(masks, None, names, alpha8=levels, boxes=box)
        masks = [read(f"{i:04d}.npy", "mask_boxes", i) for i in range(len(names))]
        alpha = [read(f"{i:04d}.alpha.npy", "alpha_boxes", i) for i in range(len(names))] if meta["alpha"] else None
        return MaskSet(masks, alpha, names, boxes=boxes("mask_boxes", "alpha_boxes") if meta["alpha"] else boxes("mask_boxes"))

    @classmethod
    def preview(cls, value, size, companions):
        return previews.draw_masks(value, size, companions)


class CameraSet(DataType):
    name = "Cameras"

    @classmethod
    def check(cls, v):
        return None if isinstance(v, Cameras) else f"expected Cameras, got {type(v).__name__}"

    @classmethod
    def save(cls, v: Cameras, folder: Path):
        (folder / "cameras.json").write_text(v.to_json())

    @classmethod
    def load(cls, folder: Path) -> Cameras:
        return Cameras.from_json((folder / "cameras.json").read_text())

    @classmethod
    def preview(cls, value, size, companions):
        return previews.draw_cameras(value, size, companions)


class Volume(DataType):
    name = "Volume"
    kept_by_default = False  # large: passed in memory within a frame unless kept

    @classmethod
    def check(cls, v):
        if not isinstance(v, VoxelGrid):
            return f"expected a VoxelGrid, got {type(v).__name__}"
        if v.occupancy.ndim != 3:
            return "occupancy must be a 3-D array"
        return None

    @classmethod
    def save(cls, v: VoxelGrid, folder: Path):
        arrays = {"occupancy": v.occupancy, "bbox_min": v.bbox_min, "bbox_max": v.bbox_max}
        if v.colors is not None:
            arrays["colors"] = v.colors
        np.savez(folder / "volume.npz", **arrays)

    @classmethod
    def load(cls, folder: Path) -> VoxelGrid:
        with np.load(folder / "volume.npz") as z:
            return VoxelGrid(z["occupancy"], z["bbox_min"], z["bbox_max"], z["colors"] if "colors" in z else None)

    @classmethod
    def preview(cls, value, size, companions):
        return previews.draw_volume(value, size, companions)


def nonfinite_vertices(mesh) -> str | None:
    """What is wrong when a mesh has vertices that are not finite (NaN, infinite): nothing downstream can use them
    (texture.transfer's closest-point kernels read outside their buffers from a NaN vertex), so the node that made
    them fails, named, instead of its readers."""
    v = np.asarray(mesh.vertices)
    ok = np.isfinite(v)
    if ok.all():
        return None
    rows = np.flatnonzero(~ok.all(axis=1))
    return f"{len(rows)} of its {len(v)} vertices are not finite (NaN or infinite; the first: vertex {rows[0]})"


_PLY_HEADER = ("ply\nformat binary_little_endian 1.0\nelement vertex {nv}\nproperty float x\nproperty float y\n"
               "property float z\nelement face {nf}\nproperty list uchar int vertex_indices\nend_header\n")
_PLY_FACE = np.dtype([("n", "u1"), ("v", "<i4", (3,))])                   # packed: 13 bytes a face
_PLY_PLAIN = re.compile("(\\d{1,19})".join(re.escape(part) for part in re.split(r"\{n[vf]\}", _PLY_HEADER)).encode())


def _write_plain_ply(path: Path, vertices, faces):
    """Binary PLY of float32 vertices and triangles (the file trimesh writes for a plain mesh, less its comment and
    the vertex normals it adds when they are cached, which its reader ignores)."""
    v = np.ascontiguousarray(vertices, "<f4").reshape(-1, 3)
    f = np.empty(len(faces), _PLY_FACE)
    f["n"] = 3
    f["v"] = faces
    with open(path, "wb") as out:
        out.write(_PLY_HEADER.format(nv=len(v), nf=len(f)).encode())
        out.write(v.tobytes())
        out.write(f.tobytes())


def _read_plain_ply(path: Path):
    """(vertices float64 (V, 3), faces int64 (F, 3)) of a file ``_write_plain_ply`` wrote; None for any other
    PLY (trimesh reads those), or when the sizes do not add up or a face is not a triangle."""
    data = path.read_bytes()
    m = _PLY_PLAIN.match(data)
    if m is None:
        return None
    nv, nf = int(m.group(1)), int(m.group(2))
    a = m.end()
    if len(data) != a + 12 * nv + _PLY_FACE.itemsize * nf:
        return None
    f = np.frombuffer(data, _PLY_FACE, nf, a + 12 * nv)
    if nf and not np.all(f["n"] == 3):
        return None
    v = np.frombuffer(data, "<f4", 3 * nv, a).reshape(nv, 3).astype(np.float64)
    return v, f["v"].astype(np.int64)


class Mesh(DataType):
    """A triangle mesh (trimesh.Trimesh), stored as binary PLY (vertex order preserved)."""

    name = "Mesh"
    filename: ClassVar[str] = "mesh.ply"
    kept_by_default = False  # large: passed in memory within a frame unless kept

    @classmethod
    def check(cls, v):
        import trimesh

        if not isinstance(v, trimesh.Trimesh):
            return f"expected a trimesh.Trimesh, got {type(v).__name__}"
        return nonfinite_vertices(v)

    @classmethod
    def canonical(cls, v):
        """PLY (trimesh) and GLB store float32 vertices and no metadata: a reader in the same unit gets the mesh
        so too. A copy when that changes it: the node's object may be part of another value (a sequence's frame)."""
        points = np.asarray(v.vertices)
        if points.dtype == np.float64 and np.array_equal(points, points.astype(np.float32)) and not v.metadata:
            return v
        out = v.copy()
        out.vertices = points.astype(np.float32).astype(np.float64)
        out.metadata.clear()
        return out

    @classmethod
    def save(cls, v, folder: Path):
        if getattr(v.visual, "kind", None) is None:     # a plain mesh: written directly (trimesh's writer: 1.4-2x the time)
            _write_plain_ply(folder / cls.filename, v.vertices, v.faces)
        else:                                           # vertex or face colours: trimesh writes them
            v.export(folder / cls.filename)

    @classmethod
    def load(cls, folder: Path):
        import trimesh

        path = folder / cls.filename
        plain = _read_plain_ply(path)
        if plain is not None:
            return trimesh.Trimesh(*plain, process=False)
        mesh = trimesh.load(path, process=False, force="mesh")
        mesh.metadata.clear()  # what the loader notes (file name, units, glTF node) is not part of the value
        return mesh

    @classmethod
    def preview(cls, value, size, companions):
        return previews.draw_mesh(value, size, companions)


class TexturedMesh(Mesh):
    """A mesh with UVs and a texture image (or with vertex colours), stored as raw arrays (mesh.npz: float32
    vertices, faces, float64 UVs and the uint8 texture, or RGBA vertex colours). Not a GLB: its PNG encoding
    took 0.23 s of a 1024² atlas's 0.7 s texturing per frame; the exports write the GLB."""

    name = "TexturedMesh"
    filename = "mesh.npz"

    @classmethod
    def save(cls, v, folder: Path):
        arrays = {"vertices": np.asarray(v.vertices, np.float32), "faces": np.asarray(v.faces, np.int32)}
        visual = v.visual
        if getattr(visual, "kind", None) == "texture" and visual.uv is not None:
            mat = visual.material
            image = getattr(mat, "baseColorTexture", None) or getattr(mat, "image", None)
            arrays["uv"] = np.asarray(visual.uv, np.float64)
            arrays["texture"] = np.asarray(image)
        elif getattr(visual, "kind", None) == "vertex":
            arrays["vertex_colors"] = np.asarray(visual.vertex_colors, np.uint8)
        np.savez(folder / cls.filename, **arrays)

    @classmethod
    def load(cls, folder: Path):
        import trimesh

        with np.load(folder / cls.filename) as z:
            a = {k: z[k] for k in z.files}
        vertices, faces = a["vertices"].astype(np.float64), a["faces"].astype(np.int64)
        if "texture" in a:
            from .gltf import textured_visual

            return trimesh.Trimesh(vertices, faces, visual=textured_visual(a["uv"], a["texture"]), process=False)
        if "vertex_colors" in a:
            return trimesh.Trimesh(vertices, faces, vertex_colors=a["vertex_colors"], process=False)
        return trimesh.Trimesh(vertices, faces, process=False)

    @classmethod
    def preview(cls, value, size, companions):
        return previews.draw_textured_mesh(value, size, companions)


class ViewTextures(DataType):
    """View-dependent layers of one frame (nodes.common.viewlayers.ViewLayers): ``layer_<k>.png`` (RGB, on the
    atlas of the frame's textured mesh), ``view_<k>.png`` (8-bit camera index per texel, 255 = none) and
    ``cameras.json`` (names and centres in the world frame, the blend width ``sigma`` in radians and the index
    that means none). A renderer blends as ``viewdep.layer_weights`` says."""

    name = "ViewTextures"

    @classmethod
    def check(cls, v):
        if not isinstance(v, ViewLayers):
            return f"expected ViewLayers, got {type(v).__name__}"
        return v.problem()

    @classmethod
    def save(cls, v: ViewLayers, folder: Path):
        import cv2

        for k in range(v.layers.shape[0]):
            cv2.imwrite(str(folder / f"layer_{k}.png"), np.ascontiguousarray(v.layers[k][:, :, ::-1]))
            cv2.imwrite(str(folder / f"view_{k}.png"), np.ascontiguousarray(v.texel_view[:, :, k]))
        (folder / "cameras.json").write_text(json.dumps({"names": list(v.names), "none": NONE, "sigma": float(v.sigma),
                                                         "layers": int(v.layers.shape[0]),
                                                         "centres": np.asarray(v.centres).tolist()}))

    @classmethod
    def load(cls, folder: Path) -> ViewLayers:
        import cv2

        doc = json.loads((folder / "cameras.json").read_text())
        K = len(list(folder.glob("layer_*.png")))
        layers = np.stack([cv2.imread(str(folder / f"layer_{k}.png"), cv2.IMREAD_COLOR)[:, :, ::-1] for k in range(K)])
        views_ = np.stack([cv2.imread(str(folder / f"view_{k}.png"), cv2.IMREAD_UNCHANGED) for k in range(K)], axis=-1)
        return ViewLayers(np.ascontiguousarray(layers), np.ascontiguousarray(views_),
                          np.asarray(doc["centres"], np.float64).reshape(-1, 3), list(doc["names"]), float(doc["sigma"]))

    @classmethod
    def preview(cls, value, size, companions):
        import cv2

        k = value.layers.shape[0]
        tile = max(16, size // max(1, int(np.ceil(np.sqrt(k)))))
        n = int(np.ceil(np.sqrt(k)))
        img = np.zeros((n * tile, n * tile, 3), np.uint8)
        for i in range(k):
            y, x = divmod(i, n)
            img[y * tile:(y + 1) * tile, x * tile:(x + 1) * tile] = cv2.resize(value.layers[i], (tile, tile),
                                                                               interpolation=cv2.INTER_AREA)
        return cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)


class Skeleton(DataType):
    name = "Skeleton"

    @classmethod
    def check(cls, v):
        if not isinstance(v, SkeletonData):
            return f"expected SkeletonData, got {type(v).__name__}"
        return v.problem()

    @classmethod
    def save(cls, v: SkeletonData, folder: Path):
        doc = {"joints": np.asarray(v.joints).tolist(), "parents": list(map(int, v.parents)), "names": v.names,
               "frames": None if v.frames is None else [int(f) for f in v.frames]}
        (folder / "skeleton.json").write_text(json.dumps(doc, indent=1))
        for name in ("weights", "rotations", "translations"):
            if getattr(v, name) is not None:
                np.save(folder / f"{name}.npy", np.asarray(getattr(v, name)))

    @classmethod
    def load(cls, folder: Path) -> SkeletonData:
        doc = json.loads((folder / "skeleton.json").read_text())
        arrays = {n: (np.load(folder / f"{n}.npy") if (folder / f"{n}.npy").exists() else None)
                  for n in ("weights", "rotations", "translations")}
        return SkeletonData(np.array(doc["joints"], dtype=np.float64).reshape(-1, 3), doc["parents"], doc["names"],
                            frames=doc.get("frames"), **arrays)

    @classmethod
    def preview(cls, value, size, companions):
        return previews.draw_skeleton(value, size, companions)


FPS = 25.0
"""The capture's frame rate (frames per second): the one default of every timed export (track.export, skeleton.export),
so a dynamic mesh and a rig referenced together keep the same clock (25: bench/e2e.py's reference rate)."""
FPS_PARAM = Param(float, FPS, range=(1.0, 1000.0),
                  doc="frames per second: USD timeCodesPerSecond / framesPerSecond, glTF key times (frame / fps)")


def sequence_segments(meshes) -> list[tuple[int, int]]:
    """Half-open ranges (start, stop) of consecutive meshes sharing one connectivity: the same
    ``metadata["segment"]`` where the meshes carry one (a tracked sequence), else the same vertex count and
    face array. A texture node computes one atlas per range; a dynamic mesh is a single range."""
    out: list[tuple[int, int]] = []
    for i, m in enumerate(meshes):
        if out:
            prev = meshes[i - 1]
            a, b = prev.metadata.get("segment"), m.metadata.get("segment")
            same = (a == b) if (a is not None and b is not None) else (
                len(prev.vertices) == len(m.vertices) and prev.faces.shape == m.faces.shape
                and bool(np.array_equal(prev.faces, m.faces)))
            if same:
                out[-1] = (out[-1][0], i + 1)
                continue
        out.append((i, i + 1))
    return out


class MeshSequence(DataType):
    """Meshes over frames: a list of trimesh.Trimesh. A dynamic mesh (constant connectivity) is a sequence
    whose meshes all share one face array; a tracked sequence is a run of such segments, each mesh carrying
    ``metadata["segment"]`` (and "keyframe", "frame" when known; see ``sequence_segments``). Stored per
    segment: the float64 vertices of all its frames (segment_NNNN.npy, (frames, V, 3)), its faces
    (segment_NNNN.faces.npy, int32) and a PLY of its first frame (to look at: loading reads the arrays, so a frame's
    reader of a long take does not parse every segment's PLY: pose2sim's 13 segments cost each frame's
    ``track.frame`` 0.19 s); sequence.json lists the segments and frames. The arrays are read whole, not
    memory-mapped: writable (a read-only map, as images get, is refused by bindings that want writable buffers:
    fast_simplification in track.simplify), and no open file per segment held while the value lives (a take joined
    from many windows has hundreds of segments)."""

    name = "MeshSequence"

    @classmethod
    def check(cls, v):
        import trimesh

        if not (isinstance(v, list) and all(isinstance(m, trimesh.Trimesh) for m in v)):
            return "expected a list of trimesh.Trimesh"
        for i, m in enumerate(v):
            problem = nonfinite_vertices(m)
            if problem:
                return f"mesh {i} (frame {m.metadata.get('frame', i)}): {problem}"
        for start, stop in sequence_segments(v):
            for i in range(start + 1, stop):
                if len(v[i].vertices) != len(v[start].vertices) or not np.array_equal(v[i].faces, v[start].faces):
                    return f"meshes {start} and {i} are in one segment but do not share their faces"
        return None

    @classmethod
    def join(cls, parts):
        """Windows of a sequence (a windowed track) as one: frames in order, segments numbered on (a window's
        segment 0 follows the last window's last), the meshes new objects sharing their arrays."""
        import trimesh

        out, base = [], 0
        for part in parts:
            ids: dict = {}
            for m in part:
                c = trimesh.Trimesh(m.vertices, m.faces, process=False)
                c.metadata.update(m.metadata)
                if "segment" in m.metadata:
                    c.metadata["segment"] = base + ids.setdefault(m.metadata["segment"], len(ids))
                out.append(c)
            base += len(ids)
        return out

    @classmethod
    def save(cls, v, folder: Path):
        segments = []
        for s, (start, stop) in enumerate(sequence_segments(v)):
            v[start].export(folder / f"segment_{s:04d}.ply")
            # every segment's vertices exactly (the PLY holds float32 vertices) and its faces
            _save_array(folder / f"segment_{s:04d}.npy", np.stack([np.asarray(m.vertices, np.float64) for m in v[start:stop]]))
            _save_array(folder / f"segment_{s:04d}.faces.npy", np.asarray(v[start].faces, np.int32))
            segments.append({"start": start, "stop": stop, "segment": v[start].metadata.get("segment"),
                             "keyframe": v[start].metadata.get("keyframe")})
        frames = [m.metadata.get("frame") for m in v]
        doc = {"count": len(v), "segments": segments, "frames": frames if any(f is not None for f in frames) else None}
        (folder / "sequence.json").write_text(json.dumps(doc))

    @classmethod
    def load(cls, folder: Path):
        import trimesh

        doc = json.loads((folder / "sequence.json").read_text())
        out = []
        for s, seg in enumerate(doc["segments"]):
            stored = folder / f"segment_{s:04d}.faces.npy"
            if stored.is_file():
                faces = _load_array(stored).astype(np.int64)           # a copy: no map kept
            else:            # written before the faces were stored as an array
                faces = trimesh.load(folder / f"segment_{s:04d}.ply", process=False, force="mesh").faces
            n = seg["stop"] - seg["start"]
            points = _load_array(folder / f"segment_{s:04d}.npy", mapped=False)
            if points.shape[:1] != (n,) or points.ndim != 3 or points.shape[2] != 3:
                raise DataError(f"{folder}: segment {s} holds {points.shape} vertices for {n} frames")
            if faces.ndim != 2 or faces.shape[1] != 3 or (faces.size and not 0 <= faces.min() <= faces.max() < points.shape[1]):
                raise DataError(f"{folder}: segment {s}'s faces {faces.shape} do not index its {points.shape[1]} vertices")
            for k in range(n):
                m = trimesh.Trimesh(points[k], faces, process=False)
                for key in ("segment", "keyframe"):
                    if seg.get(key) is not None:
                        m.metadata[key] = seg[key]
                out.append(m)
        if len(out) != doc["count"]:
            raise DataError(f"{folder}: sequence.json says {doc['count']} meshes, the segments hold {len(out)}")
        for m, f in zip(out, doc.get("frames") or []):
            if f is not None:
                m.metadata["frame"] = f
        return out

    @classmethod
    def preview(cls, value, size, companions):
        return previews.draw_mesh_sequence(value, size, companions)


class PlateModel(DataType):
    """A background mixture per camera (PlateMixture), stored as .npy per camera (mean, sigma, weight)."""

    name = "PlateModel"

    @classmethod
    def check(cls, v):
        if not isinstance(v, PlateMixture):
            return f"expected a PlateMixture, got {type(v).__name__}"
        for i, (m, s, w) in enumerate(zip(v.mean, v.sigma, v.weight)):
            if not (m.dtype == np.uint8 and m.ndim == 4 and m.shape[-1] == 3 and s.shape == m.shape
                    and s.dtype == np.float16 and w.shape == m.shape[:3]):
                return f"camera {i}: mean (K, H, W, 3) uint8, sigma the same in float16, weight (K, H, W)"
        if not len(v.mean) == len(v.sigma) == len(v.weight) == len(v.names):
            return f"{len(v.mean)} means, {len(v.sigma)} sigmas, {len(v.weight)} weights, {len(v.names)} names"
        return None

    @classmethod
    def save(cls, v: PlateMixture, folder: Path):
        for i in range(len(v)):
            _save_array(folder / f"{i:04d}.mean.npy", v.mean[i])
            _save_array(folder / f"{i:04d}.sigma.npy", v.sigma[i])
            _save_array(folder / f"{i:04d}.weight.npy", np.asarray(v.weight[i], np.float32))
        (folder / "names.json").write_text(json.dumps(v.names))

    @classmethod
    def load(cls, folder: Path) -> PlateMixture:
        names = json.loads((folder / "names.json").read_text())
        return PlateMixture(*([_load_array(folder / f"{i:04d}.{part}.npy") for i in range(len(names))]
                              for part in ("mean", "sigma", "weight")), names)

    @classmethod
    def preview(cls, value, size, companions):
        return previews.contact_sheet([np.ascontiguousarray(m[0]) for m in value.mean], value.names, size)


class Bounds(DataType):
    """An axis-aligned box: float64 array [[xmin, ymin, zmin], [xmax, ymax, zmax]], stored as JSON."""

    name = "Bounds"

    @classmethod
    def check(cls, v):
        if not (isinstance(v, np.ndarray) and v.shape == (2, 3) and np.all(np.isfinite(v)) and np.all(v[1] > v[0])):
            return "expected a (2, 3) array [min, max] with max > min"
        return None

    @classmethod
    def save(cls, v, folder: Path):
        (folder / "bounds.json").write_text(json.dumps({"min": v[0].tolist(), "max": v[1].tolist()}))

    @classmethod
    def load(cls, folder: Path):
        d = json.loads((folder / "bounds.json").read_text())
        return np.array([d["min"], d["max"]], dtype=np.float64)

    @classmethod
    def preview(cls, value, size, companions):
        return previews.draw_bounds(value, size, companions)
