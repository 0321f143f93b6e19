"""Port types: the data that flows along graph edges, and its on-disk form in the cache.

Every type is a class with these class methods:
    check(value) -> None | str      what is wrong with a value a node returned (None when fine)
    save(value, folder)             write the value into an empty folder (files other tools read)
    load(folder) -> value           read it back
    preview(value, size, companions) -> RGB uint8 image or None   a picture for the run report
Type compatibility along an edge is subclassing: a TexturedMesh output may feed a Mesh input.

The engine defines the base class and the domain-free types (tables, arrays, files). Stage packages
define theirs (images, meshes, cameras ... in nodes.common.types); every subclass with a ``name``
registers itself, so the report finds a type by the name recorded in a cache entry.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

_TYPES: dict[str, type["DataType"]] = {}


class DataType:
    """Base of all port types. ``kept_by_default``: whether a value of this type is stored in the cache even
    when its consumers run in the same process (small values: yes; images, masks, volumes, meshes: no — see
    nodegraph/plan.py)."""

    name: ClassVar[str] = "Data"
    kept_by_default: ClassVar[bool] = True
    # join(values) -> value: a windowed sequence node's windows as one value, frames in order (graph key
    # ``window:``), for a type whose values are per-frame runs (a mesh sequence); None: the type cannot be joined
    join: ClassVar = None

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        if "name" in cls.__dict__:
            _TYPES[cls.name] = cls

    @classmethod
    def check(cls, value) -> str | None:
        return None

    @classmethod
    def canonical(cls, value):
        """The value as the cache gives it back: what a reader in the same unit is handed too, so that a result
        never depends on whether its input came from memory or from the cache (e.g. a mesh's vertices at the
        precision its file stores). Default: the value itself."""
        return value

    @classmethod
    def save(cls, value, folder: Path) -> None:
        raise NotImplementedError

    @classmethod
    def load(cls, folder: Path):
        raise NotImplementedError

    @classmethod
    def files(cls, folder: Path) -> list[Path]:
        return sorted(p for p in folder.rglob("*") if p.is_file())

    @classmethod
    def preview(cls, value, size: int, companions: dict) -> np.ndarray | None:
        """An RGB uint8 picture of ``value`` at most ``size`` pixels wide, or None (nothing to draw).
        ``companions``: type name -> folder of a sibling output of the same work item or frame (a drawer
        may combine values, e.g. masks over their images)."""
        return None


def type_named(name: str) -> type[DataType] | None:
    """The registered port type called ``name`` (types register when their module is imported)."""
    return _TYPES.get(name)


# ---------------------------------------------------------------- domain-free types
class Table(DataType):
    """Metrics and reports: a JSON-serialisable dict."""

    name = "Table"

    @classmethod
    def check(cls, v):
        if not isinstance(v, dict):
            return f"expected a dict, got {type(v).__name__}"
        try:
            json.dumps(v)
        except TypeError as exc:
            return f"not JSON-serialisable: {exc}"
        return None

    @classmethod
    def save(cls, v, folder: Path):
        (folder / "table.json").write_text(json.dumps(v, indent=1, sort_keys=True))

    @classmethod
    def load(cls, folder: Path):
        return json.loads((folder / "table.json").read_text())

    @classmethod
    def preview(cls, value, size, companions):
        from .preview import draw_table

        return draw_table(value, size)


class Array(DataType):
    """A plain NumPy array (.npy)."""

    name = "Array"

    @classmethod
    def check(cls, v):
        return None if isinstance(v, np.ndarray) else f"expected a numpy array, got {type(v).__name__}"

    @classmethod
    def save(cls, v, folder: Path):
        np.save(folder / "array.npy", v)

    @classmethod
    def load(cls, folder: Path):
        return np.load(folder / "array.npy")

    @classmethod
    def preview(cls, value, size, companions):
        from .preview import draw_array

        return draw_array(value, size)


class Files(DataType):
    """Named files produced for the user (exports): dict of relative path -> bytes. Nodes that declare
    ``publishes = True`` have these files copied into the run's output folder."""

    name = "Files"

    @classmethod
    def check(cls, v):
        if not (isinstance(v, dict) and all(isinstance(k, str) and isinstance(b, bytes) for k, b in v.items())):
            return "expected a dict of relative path -> bytes"
        for k in v:
            p = Path(k)
            if p.is_absolute() or ".." in p.parts:
                return f"file name {k!r} must be relative and stay inside the output folder"
        return None

    @classmethod
    def save(cls, v, folder: Path):
        for rel, data in v.items():
            p = folder / "files" / rel
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_bytes(data)

    @classmethod
    def load(cls, folder: Path):
        root = folder / "files"
        return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}

    @classmethod
    def preview(cls, value, size, companions):
        from .preview import draw_files

        return draw_files(value, size)


def compatible(src: type[DataType], dst: type[DataType]) -> bool:
    return issubclass(src, dst)


def describe_type(t: Any) -> str:
    return getattr(t, "name", str(t))
