"""Export nodes: write results where a production chain picks them up (the run's output folder).

They render their input to file bytes (cached like any output) and the scheduler publishes those bytes to
``--out``/PATH, atomically, on every run (cached or not). PATH may use {frame} and, for masks, {camera}.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from nodegraph import Files, Input, Node, NodeError, OutPath, Output, Param, Table
from nodes.common.types import FPS_PARAM, Masks, Mesh, MeshSequence, TexturedMesh, ViewTextures, Volume, write_exr

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


class ExportViews(Node):
    """Write a frame's view-dependent layers (texture ``layers`` > 0) into a folder beside its textured mesh:
    ``layer_<k>.png`` (RGB on the mesh's atlas), ``view_<k>.png`` (camera index per texel, 255 = none) and
    ``cameras.json`` (camera names, centres in the world frame, the blend width ``sigma``). A player blends the
    layers per fragment with w_k = exp(-(a_k / sigma)^2) / a_k over the angle a_k between the ray to the eye
    and the ray to layer k's camera, the atlas texture counting as a layer at angle sigma
    (nodes/texture/viewdep.py ``layer_weights``). With ``mesh`` (the same texture node's mesh) the folder is
    also a viewer: ``index.html`` (three.js, that blend in its fragment shader; serve the folder over http),
    ``mesh.bin`` (float32 positions in the world frame, UVs, uint32 faces) and ``base.png`` (the atlas)."""

    type_name = "export.views"
    uses_frame = True
    publishes = True
    inputs = {"views": ViewTextures,
              "mesh": Input(TexturedMesh, optional=True, doc="the frame's textured mesh (texture.mesh): adds the viewer")}
    outputs = {"files": Files}
    params = {"path": Param(OutPath, "views/{frame:04d}", doc="output folder pattern, relative to --out")}

    def run(self, views, mesh, *, path, frame):
        import tempfile

        rel = _format(path, frame=frame)
        with tempfile.TemporaryDirectory() as d:
            ViewTextures.save(views, Path(d))
            files = {str(Path(rel) / f.name): f.read_bytes() for f in sorted(Path(d).iterdir())}
        if mesh is not None:
            from .player import views_files

            files.update(viewer_mesh(mesh, views, rel))
            page, warning = views_files(rel)
            files.update(page)
            if warning:
                self.log.warning("export.views: %s", warning)
        return {"files": files}


def viewer_mesh(mesh, views, rel: str) -> dict[str, bytes]:
    """mesh.bin and base.png of the view-dependent viewer (player/views.js reads them)."""
    import json

    from nodes.common.gltf import png_bytes

    visual = getattr(mesh, "visual", None)
    image = getattr(getattr(visual, "material", None), "baseColorTexture", None)
    if getattr(visual, "kind", None) != "texture" or visual.uv is None or image is None:
        raise NodeError("input 'mesh' has no atlas texture: connect the texture node's mesh (mode 'atlas') that "
                        "made these layers")
    base = np.asarray(image.convert("RGB"))
    if base.shape[:2] != views.layers.shape[1:3]:
        raise NodeError(f"input 'mesh' has a {base.shape[1]}x{base.shape[0]} texture but the layers are "
                        f"{views.layers.shape[2]}x{views.layers.shape[1]}: connect the texture node's mesh that made them")
    v = np.ascontiguousarray(mesh.vertices, np.float32)
    uv = np.ascontiguousarray(visual.uv, np.float32)
    f = np.ascontiguousarray(mesh.faces, np.uint32)
    head = json.dumps({"vertices": len(v), "faces": len(f), "frame": "+Z up, metres"}).encode()
    head += b" " * (-(len(head) + 4) % 4)
    data = len(head).to_bytes(4, "little") + head + v.tobytes() + uv.tobytes() + f.tobytes()
    return {str(Path(rel) / "mesh.bin"): data, str(Path(rel) / "base.png"): png_bytes(base)}


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


def frame_numbers(node: Node, sequence) -> list[int]:
    """Each mesh's frame number (its metadata "frame", else the run's frame, else its index)."""
    fallback = list(node.frames) if len(node.frames) == len(sequence) else list(range(len(sequence)))
    return [int(m.metadata.get("frame", f)) for m, f in zip(sequence, fallback)]


class ExportVolumetric(Node):
    """The textured volumetric video: per tracked segment one GLB (morph targets, UVs, the atlas), an H.264 video
    of its atlas per frame, and one USD stage of the take (time-sampled points and texture files): see
    nodes/export/volumetric.py. Give it the tracked sequence and each frame's textured mesh painted with its
    segment's atlas (texture with reference: track.frame's keyframe)."""

    type_name = "export.volumetric"
    version = 1
    per = "sequence"
    publishes = True
    inputs = {
        "sequence": Input(MeshSequence, doc="tracked meshes (track)"),
        "textured": Input(TexturedMesh, doc="each frame's textured mesh (texture of track.frame's mesh, with its "
                          "keyframe as reference: one atlas per segment)"),
    }
    outputs = {"files": Files, "report": Output(Table, "per segment its frames, vertex and face counts, atlas size; "
                                                 "bytes per file")}
    params = {
        "name": Param(str, "volumetric", doc="file name stem"),
        "formats": Param(list, ["gltf", "usd", "video"], item=str, doc="any of gltf, usd, video (the atlas PNGs "
                         "are always written)"),
        "fps": FPS_PARAM,
        "crf": Param(int, 18, range=(0, 51), doc="H.264 constant rate factor of the atlas video (lower: better)"),
    }

    def run(self, sequence, textured, *, name, formats, fps, crf):
        from .volumetric import volumetric_files

        unknown = sorted(set(formats) - {"gltf", "usd", "video"})
        if unknown:
            raise NodeError(f"export.volumetric: unknown formats {unknown}; use gltf, usd, video")
        if not sequence:
            raise NodeError("export.volumetric: the sequence is empty")
        frames = frame_numbers(self, sequence)
        files, report = volumetric_files(list(sequence), list(textured), frames, name, fps, formats, crf)
        return {"files": files, "report": report}


class ExportStream(Node):
    """One rung of a streamable volumetric video (stream.py): per tracked segment Draco connectivity + UVs once,
    every frame's positions quantised and predicted from the previous frame (zlib), the atlas as H.264, and a
    manifest; ``read_stream`` decodes it. A ladder is several of these nodes (e.g. one after track.simplify with
    a smaller texture), writing NAME/RUNG/ side by side; the report measures the rung against its input."""

    type_name = "export.stream"
    version = 1
    per = "sequence"
    publishes = True
    inputs = {
        "sequence": Input(MeshSequence, doc="tracked meshes (track, or track.simplify for a lower rung)"),
        "textured": Input(TexturedMesh, doc="each frame's textured mesh on its segment's atlas (as export.volumetric)"),
    }
    outputs = {"files": Files, "report": Output(Table, "bytes, Mbit/s (at fps and at 30 fps), geometry error (mm) "
                                                 "and atlas PSNR (dB) of the decoded rung")}
    params = {
        "name": Param(str, "stream", doc="the ladder's folder"),
        "rung": Param(str, "full", doc="this rung's folder in it"),
        "fps": FPS_PARAM,
        "bits": Param(int, 12, range=(8, 24), doc="position quantisation bits over each segment's box (12: 0.15 mm "
                      "mean error over a 2 m box, bench/stream.py)"),
        "crf": Param(int, 28, range=(0, 51), doc="H.264 constant rate factor of the atlas video (28: 39 dB on the "
                     "demo's 2048^2 atlas, bench/stream.py)"),
    }

    def run(self, sequence, textured, *, name, rung, fps, bits, crf):
        from .stream import stream_files

        if not sequence:
            raise NodeError("export.stream: the sequence is empty")
        if not rung or "/" in rung or rung.startswith("."):
            raise NodeError(f"export.stream: rung must be a plain folder name, got {rung!r}")
        frames = frame_numbers(self, sequence)
        files, report = stream_files(list(sequence), list(textured), frames, name, rung, fps, bits, crf)
        return {"files": files, "report": report}


class ExportPlayer(Node):
    """The stream player (player.py): a web page on three.js beside the ladder NAME/ that the export.stream
    nodes write (their rungs listed in ``rungs``): play, scrub, pick a rung; offline from any static server."""

    type_name = "export.player"
    version = 1
    per = "sequence"
    publishes = True
    inputs = {"after": Input(Table, optional=True, doc="a stream node's report, so the player runs after it (unused)")}
    outputs = {"files": Files}
    params = {
        "name": Param(str, "stream", doc="the ladder's folder (export.stream's name)"),
        "rungs": Param(list, ["full"], item=str, doc="the rungs it offers, the first shown first"),
    }

    def run(self, after=None, *, name, rungs):
        from .player import player_files

        if not rungs or any(not r or "/" in r or r.startswith(".") for r in rungs):
            raise NodeError(f"export.player: rungs must be plain folder names, got {rungs}")
        files, warning = player_files(name, rungs)
        if warning:
            self.log.warning("export.player: %s", warning)
        return {"files": files}
