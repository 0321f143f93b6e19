"""volcap node-graph engine: typed nodes, YAML graphs, a cached per-frame scheduler.

The engine knows no domain: port types, nodes and OpenCL sources come from the packages registered in the
``volcap.nodes`` entry-point group (the built-in stages are the package ``nodes``). Names are imported on
first use (``from nodegraph import Node``), so the command line starts without loading what it does not need.
"""
from __future__ import annotations

import importlib

from .errors import DataError, GraphError, NodeError, VolcapError

_LAZY = {
    "REQUIRED": "node", "InPath": "node", "Input": "node", "Node": "node", "OutPath": "node", "Output": "node",
    "Param": "node", "node_class": "node", "registry": "node",
    "Array": "types", "DataType": "types", "Files": "types", "Table": "types",
    "clrt": None,
}

__all__ = ["DataError", "GraphError", "NodeError", "VolcapError", *_LAZY]


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'nodegraph' has no attribute {name!r}")
    module = _LAZY[name]
    if module is None:
        return importlib.import_module(f".{name}", __name__)
    return getattr(importlib.import_module(f".{module}", __name__), name)
