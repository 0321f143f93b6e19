"""Export nodes: write results where a production chain picks them up (the run's output folder).

They render their input to file bytes (cached like any output) and the scheduler publishes those bytes to
``--out``/PATH, atomically, on every run (cached or not). PATH may use {frame} and, for masks, {camera}.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from nodegraph import Files, Node, NodeError, OutPath, Param
from nodes.common.types import Masks, Mesh, Volume, write_exr

MESH_FORMATS = ("ply", "obj", "glb", "stl", "off")


def _format(pattern: str, **fields) -> str:
    try:
        return pattern.format(**fields)
    except (KeyError, IndexError, ValueError) as exc:
        raise NodeError(f"path pattern {pattern!r}: {exc!r}; available fields: {', '.join(fields)}") from None


class ExportMesh(Node):
    """Write a mesh per frame (PLY, OBJ, GLB, STL or OFF, chosen by the file suffix)."""

    type_name = "export.mesh"
    uses_frame = True
    publishes = True
    inputs = {"mesh": Mesh}
    outputs = {"files": Files}
    params = {"path": Param(OutPath, "mesh_{frame:04d}.ply", doc="output file pattern, relative to --out")}

    def run(self, mesh, *, path, frame):
        rel = _format(path, frame=frame)
        ext = Path(rel).suffix.lstrip(".").lower()
        if ext not in MESH_FORMATS:
            raise NodeError(f"path {path!r}: unknown mesh format '.{ext}' (use one of {', '.join(MESH_FORMATS)})")
        if ext == "glb":
            from nodes.common.gltf import mesh_glb

            return {"files": {rel: mesh_glb(mesh, "volcap export.mesh")}}
        return {"files": {rel: mesh.export(file_type=ext)}}


class ExportMasks(Node):
    """Write masks per camera as PNG (and the soft alpha as EXR when present)."""

    type_name = "export.masks"
    uses_frame = True
    publishes = True
    inputs = {"masks": Masks}
    outputs = {"files": Files}
    params = {
        "path": Param(OutPath, "masks/{camera}/{frame:04d}.png", doc="PNG pattern with {camera} and {frame}"),
        "alpha": Param(bool, True, doc="also write the soft alpha as EXR beside each PNG"),
    }

    def run(self, masks, *, path, alpha, frame):
        import cv2

        import tempfile

        
        files = {}
        for i, (name, m) in enumerate(zip(masks.names, masks.masks)):
            rel = _format(path, frame=frame, camera=name)
            ok, buf = cv2.imencode(".png", m)
            if not ok:
                raise NodeError(f"could not encode mask of camera {name}")
            files[rel] = buf.tobytes()
            if alpha and masks.alpha is not None:
                with tempfile.TemporaryDirectory() as d:
                    p = Path(d) / "a.exr"
                    write_exr(p, masks.alpha[i])
                    files[str(Path(rel).with_suffix(".exr"))] = p.read_bytes()
        return {"files": files}


class ExportVolume(Node):
    """Write a voxel volume as .npz (occupancy, bbox_min, bbox_max[, colors])."""

    type_name = "export.volume"
    uses_frame = True
    publishes = True
    inputs = {"volume": Volume}
    outputs = {"files": Files}
    params = {"path": Param(OutPath, "volume_{frame:04d}.npz", doc="output file pattern")}

    def run(self, volume, *, path, frame):
        import io

        buf = io.BytesIO()
        arrays = {"occupancy": volume.occupancy, "bbox_min": volume.bbox_min, "bbox_max": volume.bbox_max}
        if volume.colors is not None:
            arrays["colors"] = volume.colors
        np.savez_compressed(buf, **arrays)
        return {"files": {_format(path, frame=frame): buf.getvalue()}}
