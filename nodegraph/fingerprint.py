"""Implementation fingerprints: what a node's results depend on besides its inputs and parameters.

The fingerprint of a node class hashes
  - the source of every module in the import closure of the node's module, within the project's own
    packages (the top-level packages registered in the ``volcap.nodes`` entry-point group, and the node's
    own): import statements are read from the source (those inside functions too), so no list of modules
    is kept by hand and a change anywhere the node reaches (a calibration reader, the camera model) moves it;
  - the data files beside those modules (files other than Python in the same folder, e.g. a table of
    dataset layouts read at run time);
  - its OpenCL sources (``Node.kernels``, paths) and every header they ``#include "NAME"`` (searched beside
    the including file), recursively.
Modules are named by their dotted names and files by their names relative to their package, never by
absolute path, so a project that moves keeps its cache. The engine itself is not part of it: the form of
cache entries is versioned by hashing.KEY_SCHEMA. A module that only draws (report previews) and cannot change
what a node computes says so with a top-level ``__fingerprint__ = False``: it and what only it imports are left
out, so editing a drawing does not invalidate every cache entry.
"""
from __future__ import annotations

import ast
import hashlib
import importlib.util
import json
import os
import re
from functools import lru_cache
from importlib import metadata
from pathlib import Path

from .hashing import digest

ENTRY_POINT_GROUP = "volcap.nodes"
_INCLUDE = re.compile(r'^\s*#\s*include\s+"([^"]+)"', re.M)
_NOT_RESULTS = re.compile(r"^__fingerprint__\s*=\s*False\b", re.M)


@lru_cache(maxsize=None)
def project_packages() -> frozenset[str]:
    """Top-level package names of the node packages registered in the entry-point group."""
    return frozenset(ep.value.split(":")[0].split(".")[0] for ep in metadata.entry_points(group=ENTRY_POINT_GROUP))


def _module_file(name: str) -> tuple[Path | None, bool]:
    """(source file, is_package) of module ``name``, or (None, False) when it is not a module."""
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, AttributeError, ValueError):  # an attribute, not a module ("a.b.func")
        return None, False
    if spec is None or not spec.origin or not spec.origin.endswith(".py"):
        return None, False
    return Path(spec.origin), spec.submodule_search_locations is not None


_PARSED: dict[str, list[str]] = {}   # (module, content hash) -> imported names: parsing is the slow part
_STORE: Path | None = None


def remember_in(path: Path | None):
    """Keep the parsed import lists in ``path`` (a JSON file, e.g. in the cache folder) across processes: a
    module whose text did not change is not parsed again."""
    global _STORE
    _STORE = path
    if path is not None and path.is_file():
        try:
            _PARSED.update(json.loads(path.read_text()))
        except (OSError, ValueError):
            pass


def save_parsed():
    if _STORE is not None:
        try:
            tmp = _STORE.with_suffix(".tmp")
            tmp.write_text(json.dumps(_PARSED))
            os.replace(tmp, _STORE)
        except OSError:
            pass


def imported_names(source: str, module: str, is_package: bool) -> set[str]:
    """Dotted names a module's source imports (absolute; parents included; ``from a import b`` gives a and
    a.b, which may be an attribute rather than a module)."""
    memo = f"{module}:{int(is_package)}:{hashlib.sha1(source.encode()).hexdigest()}"
    if memo in _PARSED:
        return set(_PARSED[memo])
    names = _imported_names(source, module, is_package)
    _PARSED[memo] = sorted(names)
    return names


def _imported_names(source: str, module: str, is_package: bool) -> set[str]:
    names: set[str] = set()
    package = module if is_package else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            bases = [a.name for a in node.names]
            subs: list[str] = []
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                anchor = ".".join(parts[: len(parts) - node.level + 1])
                base = f"{anchor}.{node.module}" if node.module else anchor
            else:
                base = node.module or ""
            bases = [base]
            subs = [f"{base}.{a.name}" for a in node.names if a.name != "*"]
        else:
            continue
        for name in bases + subs:
            parts = name.split(".")
            names.update(".".join(parts[: i + 1]) for i in range(len(parts)))
    return names


def module_closure(module: str, roots: frozenset[str] | None = None) -> dict[str, Path]:
    """Module name -> source file for ``module`` and everything it imports, transitively, within the top-level
    packages ``roots`` (default: the project's packages and the module's own)."""
    roots = (roots if roots is not None else project_packages()) | {module.split(".")[0]}
    found: dict[str, Path] = {}
    todo = [module]
    while todo:
        name = todo.pop()
        if name in found or name.split(".")[0] not in roots:
            continue
        path, is_pkg = _module_file(name)
        if path is None:
            continue
        source = path.read_text()
        if _NOT_RESULTS.search(source):
            continue
        found[name] = path
        parent = name.rpartition(".")[0]
        if parent:
            todo.append(parent)  # importing a.b.c runs a/__init__.py and a/b/__init__.py
        todo.extend(imported_names(source, name, is_pkg) - found.keys())
    return found


def data_files(modules: dict[str, Path]) -> dict[str, Path]:
    """'package/file' -> path of the non-Python files beside the given modules."""
    out = {}
    for name, path in modules.items():
        pkg = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for f in sorted(path.parent.iterdir()):
            if f.is_file() and f.suffix not in (".py", ".pyc") and not f.name.startswith("."):
                out[f"{pkg}/{f.name}"] = f
    return out


def kernel_files(kernels) -> dict[str, Path]:
    """Name -> path of the OpenCL sources and the headers they include, recursively."""
    out: dict[str, Path] = {}
    todo = [Path(k) for k in kernels]
    while todo:
        p = todo.pop()
        if p.name in out:
            continue
        out[p.name] = p
        todo += [p.parent / inc for inc in _INCLUDE.findall(p.read_text())]
    return out


def implementation_sources(cls) -> dict[str, str]:
    """The texts that make up a node's implementation, keyed 'py:module', 'data:package/file', 'cl:file'."""
    modules = module_closure(cls.__module__)
    out = {f"py:{m}": p.read_text() for m, p in modules.items()}
    out.update({f"data:{k}": p.read_bytes().hex() for k, p in data_files(modules).items()})
    out.update({f"cl:{k}": p.read_text() for k, p in kernel_files(cls.kernels).items()})
    return out


@lru_cache(maxsize=None)
def implementation_fingerprint(cls) -> str:
    return digest(implementation_sources(cls))[:16]
