"""The `load.mesh` source node: a triangle mesh from a file (PLY, OBJ, STL, OFF, GLB/GLTF), e.g. the ground
truth that eval.surface compares a result with. A scene of several meshes (GLB) is concatenated; a file
that is not a regular file, empty, not a mesh, without faces, or with non-finite vertices is refused with a
DataError naming it. glTF is +Y up: its points come back in the world frame (+Z up, nodes.common.gltf)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from nodegraph import DataError

FORMATS = ("ply", "obj", "stl", "off", "glb", "gltf")


def load_mesh(path):
    """The mesh in ``path`` as a trimesh.Trimesh (vertex order kept, nothing merged)."""
    import trimesh

    p = Path(path)
    if p.is_dir():
        raise DataError(f"{p}: is a folder, not a mesh file")
    if not p.is_file():
        raise DataError(f"{p}: not a regular file (missing, a FIFO or a device)")
    ext = p.suffix.lower().lstrip(".")
    if ext not in FORMATS:
        raise DataError(f"{p}: unknown mesh format '.{ext}' (read: {', '.join(FORMATS)})")
    if p.stat().st_size == 0:
        raise DataError(f"{p}: the file is empty")
    try:
        mesh = trimesh.load(p, file_type=ext, force="mesh", process=False)
    except Exception as exc:  # every reader fails its own way on garbage
        raise DataError(f"{p}: cannot be read as a {ext.upper()} mesh ({type(exc).__name__}: {str(exc)[:200]})") from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise DataError(f"{p}: holds no triangle mesh (a {type(mesh).__name__})")
    if len(mesh.faces) == 0:
        raise DataError(f"{p}: the mesh has no faces (a point cloud?)")
    v = np.asarray(mesh.vertices)
    if not np.all(np.isfinite(v)):
        raise DataError(f"{p}: vertices contain NaN or infinity")
    f = np.asarray(mesh.faces)
    if f.min() < 0 or f.max() >= len(v):
        raise DataError(f"{p}: faces index vertices outside 0..{len(v) - 1}")
    if ext in ("glb", "gltf"):
        from nodes.common.gltf import world_points

        mesh.vertices = world_points(mesh.vertices)
    return mesh
