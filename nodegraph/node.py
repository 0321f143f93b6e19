"""Node declarations and the node registry.

A node is a class: its ports, parameters and kernels are declared once, and validation, the cache key,
``describe`` and the docs are all generated from that declaration. ``run`` does the work:

    class Hull(Node):
        "Volumetric visual hull: voxels whose projection falls inside every silhouette."
        type_name = "hull"
        version = 1
        inputs = {"masks": Masks, "cameras": CameraSet}
        outputs = {"volume": Volume}
        params = {"resolution": Param(int, 128, range=(8, 1024), doc="voxels along the longest side")}
        kernels = [source("hull.cl")]     # paths: kernels.source names a file in kernels/

        def run(self, masks, cameras, *, resolution):
            return {"volume": ...}

``per = "frame"`` (default): one work item per frame; inputs are that frame's artifacts.
``per = "sequence"``: one work item for the whole frame range; each per-frame input arrives as a list
(in frame order) and ``self.frames`` holds the frame numbers.
``uses_frame = True``: the frame number is part of the work (sources, per-frame file patterns); it is
passed to ``run`` as ``frame=`` and is part of the cache key.
``publishes = True``: the node's ``Files`` outputs are copied into the run's output folder, and its ``Table``
outputs are written there as JSON per frame and CSV per node (OUT/tables/NODE/FRAME.json, OUT/tables/NODE.csv).
``summary = ("key", ...)``: Table keys printed in one line per node after a run (mean, and min/max over frames).
``self.progress(done, total, what)`` in run(): how far a long item has come, shown on the command line's bar.
``checkpoint = True``: the node's outputs are always stored in the cache (a costly source such as a renderer),
even when the nodes that read them run in the same process (nodegraph/plan.py says what is kept).

Node types are found through the ``volcap.nodes`` entry-point group: each entry point names a module or
a package, and every module of a package is imported (the built-in stages are one such package, plugins
register theirs the same way). The implementation fingerprint in the cache key is computed from the node's
module and what it imports (nodegraph.fingerprint); ``kernels`` lists the OpenCL source files (paths).
"""
from __future__ import annotations

import importlib
import inspect
import logging
import pkgutil
import reprlib
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any, ClassVar

from .errors import VolcapError
from .fingerprint import ENTRY_POINT_GROUP
from .types import DataType, describe_type




_repr = reprlib.Repr()
_repr.maxstring, _repr.maxother, _repr.maxlist, _repr.maxdict, _repr.maxlevel = 80, 80, 8, 8, 3


def show(value) -> str:
    """A value for a message: repr with long strings, long lists and deep nesting cut short (never expands
    an alias bomb; repr escapes control characters)."""
    return _repr.repr(value)


class _Required:
    def __repr__(self):
        return "required"


REQUIRED: Any = _Required()


class InPath(str):
    """Param type for an input file or folder: resolved against the graph file's folder and hashed by
    content in the cache key (so a project can move)."""


class OutPath(str):
    """Param type for an output file pattern (relative to the run's output folder)."""


@dataclass
class Param:
    type: type
    default: Any = REQUIRED
    doc: str = ""
    range: tuple | None = None          # inclusive (lo, hi); None on either side = open (type=list: each item's)
    choices: tuple | None = None
    item: type | None = None            # for type=list: the element type
    length: int | None = None           # for type=list: exact length

    def describe_type(self) -> str:
        if self.type is list:
            inner = self.item.__name__ if self.item else "any"
            return f"list[{inner}]" + (f" (length {self.length})" if self.length else "")
        return {InPath: "path", OutPath: "output path"}.get(self.type, self.type.__name__)

    def coerce(self, value: Any) -> Any:
        """Return the value converted to the declared type, or raise ValueError with a user message."""
        if value is None:
            if self.default is None:
                return None
            raise ValueError("must not be null")
        if self.type is list:
            if not isinstance(value, (list, tuple)):
                raise ValueError(f"expects a list, got {show(value)}")
            if self.length is not None and len(value) != self.length:
                raise ValueError(f"expects a list of {self.length} items, got {len(value)}")
            if self.item is not None:
                value = [_coerce_scalar(self.item, v) for v in value]
            if self.range is not None:
                for i, v in enumerate(value):
                    self._in_range(v, f"item {i + 1} ")
            return list(value)
        value = _coerce_scalar(self.type, value)
        if self.choices is not None and value not in self.choices:
            raise ValueError(f"must be one of {', '.join(map(str, self.choices))}; got {show(value)}")
        if self.range is not None:
            self._in_range(value)
        return value

    def _in_range(self, value, what: str = "") -> None:
        lo, hi = self.range
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise ValueError(f"{what}must be in [{'' if lo is None else lo}, {'' if hi is None else hi}]; got {show(value)}")


def _coerce_scalar(t: type, v: Any) -> Any:
    if t is bool:
        if isinstance(v, bool):
            return v
        raise ValueError(f"expects true or false, got {show(v)}")
    if t is int:
        if isinstance(v, bool) or not isinstance(v, int):
            raise ValueError(f"expects an integer, got {show(v)}")
        return v
    if t is float:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ValueError(f"expects a number, got {show(v)}")
        if v != v:  # NaN passes every range check and never equals itself
            raise ValueError("expects a number, got nan")
        if abs(v) == float("inf"):
            raise ValueError(f"expects a finite number, got {show(v)}")
        return float(v)
    if t in (str, InPath, OutPath):
        if not isinstance(v, str):
            raise ValueError(f"expects a string, got {show(v)}")
        if "\x00" in v:
            raise ValueError(f"contains a NUL character: {show(v)}")
        return t(v) if t is not str else v
    if isinstance(v, t):
        return v
    raise ValueError(f"expects {t.__name__}, got {show(v)}")


@dataclass
class Input:
    type: type[DataType]
    optional: bool = False
    doc: str = ""


@dataclass
class Output:
    type: type[DataType]
    doc: str = ""
    optional: bool = False  # the node may return None (e.g. a dataset without masks)


_REGISTRY: dict[str, type["Node"]] = {}


class Node:
    """Base class of all nodes (see the module docstring)."""

    type_name: ClassVar[str] = ""
    version: ClassVar[int] = 1
    per: ClassVar[str] = "frame"
    uses_frame: ClassVar[bool] = False
    publishes: ClassVar[bool] = False
    summary: ClassVar[tuple] = ()     # Table keys summarised after a run (see the module docstring)
    checkpoint: ClassVar[bool] = False
    inputs: ClassVar[dict] = {}
    outputs: ClassVar[dict] = {}
    params: ClassVar[dict] = {}
    kernels: ClassVar[list] = []   # OpenCL source files (paths); they and their #includes are fingerprinted

    # set by the worker before run()
    frame: int | None = None
    frames: list[int] = []
    log: logging.Logger = logging.getLogger("volcap.node")
    _progress = None   # callable(done, total, what) or None

    def progress(self, done: int, total: int, what: str = "") -> None:
        """Say how far a long run has come (a sequence node's frames, a solver's iterations): the command line's
        bar shows it beside the item (``skin 7/15 iterations``). Cheap: call it as often as is natural."""
        if self._progress is not None:
            self._progress(int(done), int(total), str(what))

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        cls.inputs = {k: v if isinstance(v, Input) else Input(v) for k, v in cls.__dict__.get("inputs", cls.inputs).items()}
        cls.outputs = {k: v if isinstance(v, Output) else Output(v) for k, v in cls.__dict__.get("outputs", cls.outputs).items()}
        if cls.per not in ("frame", "sequence"):
            raise TypeError(f"{cls.__name__}.per must be 'frame' or 'sequence'")
        if cls.__dict__.get("type_name"):
            other = _REGISTRY.get(cls.type_name)
            if other is not None and (other.__module__, other.__qualname__) != (cls.__module__, cls.__qualname__):
                raise TypeError(f"node type '{cls.type_name}' is defined twice: {other.__module__} and {cls.__module__}")
            _REGISTRY[cls.type_name] = cls

    @classmethod
    def doc(cls) -> str:
        return inspect.getdoc(cls) or ""

    def run(self, **kwargs) -> dict:  # pragma: no cover - abstract
        raise NotImplementedError

    @classmethod
    def source_file(cls) -> str:
        """The file declaring the node, relative to the folder holding its top-level package (the project:
        ``nodes/hull/nodes.py``), or absolute when that cannot be told."""
        import sys

        try:
            path = Path(inspect.getsourcefile(cls)).resolve()
            top = sys.modules[cls.__module__.split(".")[0]]
            root = Path(top.__file__).resolve().parent
            if hasattr(top, "__path__"):   # a package: the project is the folder above it
                root = root.parent
            return path.relative_to(root).as_posix()
        except (TypeError, ValueError, KeyError, AttributeError):
            return str(inspect.getsourcefile(cls) or "?")

    @classmethod
    def describe(cls) -> str:
        """Human-readable description generated from the declaration (used by ``describe NODE``)."""
        lines = [f"{cls.type_name} (version {cls.version}, per {cls.per})",
                 f"  module {cls.__module__} ({cls.source_file()})", ""]
        lines += ["  " + ln for ln in cls.doc().splitlines()] + [""]
        lines.append("inputs:" if cls.inputs else "inputs: none")
        for name, inp in cls.inputs.items():
            opt = " (optional)" if inp.optional else ""
            lines.append(f"  {name}: {describe_type(inp.type)}{opt}  {inp.doc}".rstrip())
        lines.append("outputs:")
        for name, out in cls.outputs.items():
            lines.append(f"  {name}: {describe_type(out.type)}  {out.doc}".rstrip())
        lines.append("params:" if cls.params else "params: none")
        for name, p in cls.params.items():
            extra = []
            if p.range:
                extra.append(f"{'each item in' if p.type is list else 'range'} {list(p.range)}")
            if p.choices:
                extra.append("one of " + ", ".join(map(str, p.choices)))
            default = "required" if p.default is REQUIRED else repr(p.default)
            lines.append(f"  {name}: {p.describe_type()} = {default}" + (f" ({'; '.join(extra)})" if extra else "") + (f"  {p.doc}" if p.doc else ""))
        if cls.kernels:
            lines.append("kernels: " + ", ".join(Path(k).name for k in cls.kernels))
        return "\n".join(lines)


def _import_all(package) -> list[str]:
    """Import every module below ``package`` (a module object); one problem string per failure."""
    problems = []
    for mod in pkgutil.walk_packages(package.__path__, prefix=package.__name__ + "."):
        try:
            importlib.import_module(mod.name)
        except Exception as exc:  # a broken node module must not hide the others
            problems.append(f"cannot import node module '{mod.name}': {type(exc).__name__}: {exc}")
    return problems


_discovered = False
_discovery_problems: list[str] = []


def registry() -> dict[str, type[Node]]:
    """All known node types, by type name (imports ``nodes`` and the entry points once)."""
    global _discovered
    if not _discovered:
        _discovered = True
        eps = metadata.entry_points(group=ENTRY_POINT_GROUP)
        if not eps:
            _discovery_problems.append(f"no node packages are registered in the '{ENTRY_POINT_GROUP}' entry-point group: "
                                       "install volcap (pip install -e . in the checkout, or ./setup.sh)")
        for ep in eps:
            try:
                mod = ep.load()
            except Exception as exc:
                _discovery_problems.append(f"cannot load node package '{ep.name}' ({ep.value}): {type(exc).__name__}: {exc}")
                continue
            if hasattr(mod, "__path__"):
                _discovery_problems.extend(_import_all(mod))
        for p in _discovery_problems:
            logging.getLogger("volcap").warning(p)
    return dict(_REGISTRY)


def discovery_problems() -> list[str]:
    registry()
    return list(_discovery_problems)


def node_class(type_name: str, module: str | None = None) -> type[Node]:
    """Look a node class up, importing ``module`` first (work items carry it, so workers find plugins)."""
    if type_name not in _REGISTRY and module:
        importlib.import_module(module)
    if type_name not in _REGISTRY:
        registry()
    try:
        return _REGISTRY[type_name]
    except KeyError:
        raise VolcapError(f"unknown node type '{type_name}'") from None
