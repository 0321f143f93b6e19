"""The track.export node: a tracked mesh sequence as USD / glTF / Draco files (writers in formats.py)."""
from __future__ import annotations

from nodegraph import Files, Input, Node, NodeError, Output, Param, Table
from nodes.common.types import FPS_PARAM, Mesh, MeshSequence, sequence_segments

from . import formats as exporters


class Export(Node):
    """A tracked mesh sequence as files a pipeline reads: USD with time-sampled points (one mesh per segment,
    visible during its frames), glTF with morph-target animation per segment, Draco (connectivity once per
    segment, positions per frame, vertex order kept); ``sizes`` compares its storage with the per-frame
    reconstructions (binary PLY, raw, Draco per frame) when those are connected."""

    type_name = "track.export"
    version = 1
    per = "sequence"
    publishes = True
    inputs = {
        "sequence": Input(MeshSequence, doc="tracked meshes (track)"),
        "meshes": Input(Mesh, optional=True, doc="the per-frame reconstructions, for the storage comparison"),
    }
    outputs = {"files": Files, "sizes": Output(Table, "bytes of each export and of the per-frame meshes")}
    params = {
        "name": Param(str, "dynamic_mesh", doc="file name stem (USD/glTF), folder name (Draco frames)"),
        "formats": Param(list, ["usd", "gltf", "draco"], item=str, doc="any of usd, gltf, draco"),
        "fps": FPS_PARAM,
        "draco_bits": Param(int, 14, range=(1, 30), doc="Draco position quantisation bits"),
    }

    def run(self, sequence, meshes=None, *, name, formats: list, fps, draco_bits):
        unknown = sorted(set(formats) - {"usd", "gltf", "draco"})
        if unknown:
            raise NodeError(f"track.export: unknown formats {unknown}; use usd, gltf, draco")
        if not sequence:
            raise NodeError("track.export: the sequence is empty")
        files = {}
        if "usd" in formats:
            files[f"{name}.usdc"] = exporters.usd_bytes(sequence, fps)
        if "gltf" in formats:
            files[f"{name}.glb"] = exporters.gltf_bytes(sequence, fps)
        if "draco" in formats:
            for k, data in exporters.draco_sequence(sequence, draco_bits).items():
                files[f"{name}_draco/{k}"] = data
        sizes = exporters.sizes(sequence, meshes, None, draco_bits)
        sizes["files"] = {k: len(v) for k, v in files.items() if not k.endswith(".drc")}
        if "draco" in formats:
            sizes["dynamic_draco_bytes"] = int(sum(len(v) for k, v in files.items() if k.endswith(".drc")))
        sizes["segments_frames"] = [b - a for a, b in sequence_segments(sequence)]
        return {"files": files, "sizes": sizes}

