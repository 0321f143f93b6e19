"""volcap node-graph engine: typed nodes, YAML graphs, a cached per-frame scheduler.

The engine knows no domain: port types, nodes and OpenCL sources come from the packages registered in the
``volcap.nodes`` entry-point group (the built-in stages are the package ``nodes``)."""
from .errors import DataError, GraphError, NodeError, VolcapError
from .node import REQUIRED, InPath, Input, Node, OutPath, Output, Param, node_class, registry
from .types import Array, DataType, Files, Table

__all__ = [
    "Array", "DataError", "DataType", "Files", "GraphError", "InPath", "Input", "Node", "NodeError", "OutPath",
    "Output", "Param", "REQUIRED", "Table", "VolcapError", "node_class", "registry",
]
