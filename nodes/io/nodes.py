"""Input nodes: meshes from disk (work in mesh.py)."""
from __future__ import annotations

from nodegraph import InPath, Node, Param
from nodes.common.types import Mesh

from .mesh import load_mesh


class LoadMesh(Node):
    """A triangle mesh from a file (PLY, OBJ, STL, OFF, GLB/GLTF), e.g. a reference for eval.surface."""

    type_name = "load.mesh"
    version = 1
    outputs = {"mesh": Mesh}
    params = {"path": Param(InPath, doc="mesh file (.ply .obj .stl .off .glb .gltf)")}

    def run(self, *, path):
        mesh = load_mesh(path)
        self.log.info("%s: %d vertices, %d faces", path, len(mesh.vertices), len(mesh.faces))
        return {"mesh": mesh}
