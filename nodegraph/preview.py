"""Small PNG previews of cached node outputs for the run report: the port type draws its value.

    preview("Masks", cache_dir / "masks", Path("masks.png"), companions={"Images": cache_dir / "images"})

The type named in the cache entry loads the value with its own ``load(folder)`` and draws it with its
``preview(value, size, companions)``; the PNG is at most ``size`` pixels wide. ``companions`` (type name ->
folder of a sibling output) lets a type combine values (masks over the images of the same frame, 3-D views
oriented by the cameras). This module holds the drawing helpers the engine's own types use (tables, arrays,
files) and that stage packages may reuse (matplotlib figures, text, PNG writing).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import DataError
from .types import type_named

MAX_WIDTH = 640


def preview(type_name: str, folder: Path, out_png: Path, size: int = 480, companions: dict | None = None) -> Path | None:
    """Draw the value stored in ``folder`` (a cache output port folder of type ``type_name``) to ``out_png``.

    Returns the PNG path, or None when the value has nothing to draw (an empty table, an empty mesh).
    Raises DataError naming the folder when the value cannot be read or drawn.
    """
    size = int(min(max(size, 64), MAX_WIDTH))
    folder, out_png = Path(folder), Path(out_png)
    dtype = type_named(type_name)
    if dtype is None:
        raise DataError(f"{folder}: no preview for data type '{type_name}' (its stage package is not installed here)")
    companions = {k: Path(v) for k, v in (companions or {}).items() if v is not None and Path(v).is_dir()}
    try:
        value = dtype.load(folder)
    except DataError:
        raise
    except Exception as exc:
        raise DataError(f"{folder}: cannot read {type_name} for a preview ({type(exc).__name__}: {exc})") from None
    out_png.parent.mkdir(parents=True, exist_ok=True)
    img = dtype.preview(value, size, companions)
    if img is None:
        return None
    write_png(out_png, img)
    return out_png


def load_companion(type_name: str, companions: dict):
    """The value of a companion output of type ``type_name``, or None (absent or unreadable)."""
    folder = companions.get(type_name)
    dtype = type_named(type_name)
    if folder is None or dtype is None:
        return None
    try:
        return dtype.load(folder)
    except Exception:  # a companion only decorates the preview; an unreadable one is left out
        return None


# ---------------------------------------------------------------- tables, arrays, files
def numeric_series(table: dict, prefix: str = "") -> tuple[dict, dict]:
    """(scalars, lists): numeric leaves of a (nested) table by dotted key; lists only when all-numeric."""
    scalars, lists = {}, {}
    for k, v in table.items():
        key = f"{prefix}{k}"
        if isinstance(v, bool):
            scalars[key] = float(v)
        elif isinstance(v, (int, float)):
            scalars[key] = float(v)
        elif isinstance(v, dict):
            s, l = numeric_series(v, key + ".")
            scalars.update(s)
            lists.update(l)
        elif isinstance(v, list) and v and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
            lists[key] = [float(x) for x in v]
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):  # records, e.g. one per view
            for field_name in v[0]:
                column = [x.get(field_name) for x in v]
                if all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in column):
                    lists[f"{key}.{field_name}"] = [float(c) for c in column]
    return scalars, lists


def record_labels(table: dict, key: str) -> list[str] | None:
    """The 'name' of each record behind a ``numeric_series`` list key like 'views.iou', if they have one."""
    node = table
    for part in key.split(".")[:-1]:
        node = node.get(part) if isinstance(node, dict) else None
    if isinstance(node, list) and all(isinstance(x, dict) and "name" in x for x in node):
        return [str(x["name"]) for x in node]
    return None


def draw_table(value, size):
    """Bar charts of the table's numeric lists (e.g. per-view IoU), else of its numeric scalars."""
    scalars, lists = numeric_series(value)
    panels = list(lists.items())[:3] or ([("values", list(scalars.values()))] if scalars else [])
    if not panels:
        return None
    fig, canvas = figure(size, 160 * len(panels) + 30)
    for k, (name, vals) in enumerate(panels):
        ax = fig.add_subplot(len(panels), 1, k + 1)
        ax.bar(range(len(vals)), vals, color="#4a7fc0")
        ax.set_title(name, fontsize=8)
        ax.tick_params(labelsize=6)
        labels = record_labels(value, name) if name != "values" else None
        if labels and len(labels) <= 40:
            ax.set_xticks(range(len(vals)), labels, rotation=90, fontsize=5)
        if name == "values":
            ax.set_xticks(range(len(vals)), list(scalars), rotation=30, ha="right", fontsize=6)
    fig.tight_layout()
    return render_figure(fig, canvas)


def draw_array(value, size):
    a = np.asarray(value)
    if a.size == 0:
        return text_image([f"empty array {a.shape}"], size)
    if not np.issubdtype(a.dtype, np.number) and a.dtype != bool:
        return text_image([f"array {a.shape} {a.dtype}"], size)
    a = a.astype(np.float64)
    fig, canvas = figure(size, int(size * 0.5))
    ax = fig.add_subplot(1, 1, 1)
    if a.ndim <= 1:
        ax.plot(a.ravel(), marker="." if a.size <= 64 else None)
    else:
        while a.ndim > 2:
            a = a.max(axis=-1)
        ax.imshow(a, cmap="viridis", aspect="auto")
    ax.set_title(f"array {np.asarray(value).shape} {np.asarray(value).dtype}", fontsize=8)
    ax.tick_params(labelsize=6)
    fig.tight_layout()
    return render_figure(fig, canvas)


def draw_files(value, size):
    lines = [f"{name}  ({len(data):,} bytes)" for name, data in sorted(value.items())] or ["(no files)"]
    if len(lines) > 24:
        lines = lines[:23] + [f"... and {len(lines) - 23} more"]
    return text_image(lines, size)


# ---------------------------------------------------------------- drawing helpers
def figure(width: int, height: int):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    dpi = 100
    fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi)
    return fig, FigureCanvasAgg(fig)


def render_figure(fig, canvas) -> np.ndarray:
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[:, :, :3].copy()


def text_image(lines: list[str], width: int) -> np.ndarray:
    import cv2

    img = np.full((16 * len(lines) + 8, width, 3), 250, np.uint8)
    for i, line in enumerate(lines):
        cv2.putText(img, line, (6, 16 * i + 16), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (20, 20, 20), 1, cv2.LINE_AA)
    return img


def write_png(path: Path, rgb: np.ndarray):
    import cv2

    if rgb.shape[1] > MAX_WIDTH:
        h = int(rgb.shape[0] * MAX_WIDTH / rgb.shape[1])
        rgb = cv2.resize(rgb, (MAX_WIDTH, max(h, 1)), interpolation=cv2.INTER_AREA)
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[:, :, ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 6]):
        raise DataError(f"{path}: could not write preview PNG")
