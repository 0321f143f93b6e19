"""volcap node-graph engine: typed nodes, YAML graphs, a cached per-frame scheduler."""
from .errors import DataError, GraphError, NodeError, VolcapError
from .node import REQUIRED, InPath, Input, Node, OutPath, Output, Param, node_class, registry
from .types import (Array, Bounds, CameraSet, DataType, Files, Images, ImageSet, Masks, MaskSet, Mesh, MeshSequence,
                    Skeleton, SkeletonData, Table, TexturedMesh, Volume, VoxelGrid)

__all__ = [
    "Array", "Bounds", "CameraSet", "DataError", "DataType", "Files", "GraphError", "Images", "ImageSet", "InPath", "Input",
    "Masks", "MaskSet", "Mesh", "MeshSequence", "Node", "NodeError", "OutPath", "Output", "Param", "REQUIRED",
    "Skeleton", "SkeletonData", "Table", "TexturedMesh", "VolcapError", "Volume", "VoxelGrid", "node_class",
    "registry",
]
