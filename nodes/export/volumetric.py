"""The deliverable: a textured volumetric video, one animated textured asset per tracked segment.

Input: the tracked sequence (constant connectivity per segment) and, per frame, its textured mesh painted
with the segment's one atlas (``texture`` with ``reference: tracked.keyframe``): the textured mesh keeps the
tracked faces in order and splits vertices at UV seams, so the seam split of the segment's first frame maps
every textured vertex to its tracked vertex and every frame's positions come over by index.

Per segment ``NAME_SSSS``:
    NAME_SSSS.glb           the split mesh (POSITION, NORMAL, TEXCOORD_0), the first frame's atlas embedded,
                            one morph target per later frame (POSITION and NORMAL displacements), a STEP
                            animation over the segment's frames at ``fps`` that holds its last frame for one
                            frame period (loops cleanly); extras: fps, frames, the atlas video beside it
    NAME_SSSS.mp4           the atlas per frame as video (H.264, yuv420p, PyAV), frame k = the segment's k-th
    NAME_tex/FFFFF.png      the atlas per frame, lossless
and for the whole take:
    NAME.usdc               one stage: per segment a mesh with time-sampled points (and extent), visibility
                            during its frames, ``st`` UVs, a UsdPreviewSurface whose texture file is
                            time-sampled per frame (NAME_tex/FFFFF.png); upAxis Z, metres, timeCodesPerSecond
                            = fps, time code = frame number.
"""
from __future__ import annotations

import io
import os

import numpy as np

from nodegraph import NodeError
from nodes.common.gltf import GltfBuilder, png_bytes, texture_image, texture_uv
from nodes.common.meshops import smooth_vertex_normals
from nodes.common.types import sequence_segments
from nodes.common.views import map_views


def seam_split(faces, textured, frame: int) -> np.ndarray:
    """(V_split,) tracked vertex of each textured vertex, from a textured mesh with the same faces in order."""
    tf = np.asarray(textured.faces)
    if tf.shape != np.asarray(faces).shape:
        raise NodeError(f"frame {frame}: the textured mesh has {len(tf)} faces, the tracked mesh {len(faces)}: "
                        "texture the tracked frame (track.frame's mesh)")
    src = np.full(len(textured.vertices), -1, np.int64)
    src[tf.ravel()] = np.asarray(faces, np.int64).ravel()
    if (src < 0).any():
        raise NodeError(f"frame {frame}: the textured mesh has vertices no face uses")
    again = np.full(len(textured.vertices), -1, np.int64)
    again[tf.ravel()[::-1]] = np.asarray(faces, np.int64).ravel()[::-1]
    if not np.array_equal(src, again):
        raise NodeError(f"frame {frame}: a textured vertex stands for two tracked vertices: its faces are not the "
                        "tracked faces in order")
    return src


def _segment(meshes, textured, frames, a: int, c: int):
    """(src, uv (V, 2) trimesh UVs, atlases [(H, W, 3) uint8 per frame]) of segment frames a..c-1."""
    faces = np.asarray(meshes[a].faces)
    first = textured[a]
    src = seam_split(faces, first, frames[a])
    uv = np.asarray(first.visual.uv, np.float64) if getattr(first.visual, "uv", None) is not None else None
    atlases = []
    for k in range(a, c):
        t = textured[k]
        img = texture_image(t)
        if uv is None or img is None:
            raise NodeError(f"frame {frames[k]}: the textured mesh has no UVs or no texture")
        if not np.array_equal(np.asarray(t.faces), np.asarray(first.faces)) or \
                not np.allclose(np.asarray(t.visual.uv), uv, atol=1e-6):
            raise NodeError(f"frame {frames[k]}: another UV layout than frame {frames[a]} of its segment: give "
                            "texture the segment's keyframe as reference (track.frame's keyframe)")
        if atlases and img.shape != atlases[0].shape:
            raise NodeError(f"frame {frames[k]}: atlas {img.shape[1]}x{img.shape[0]} differs from its segment's")
        atlases.append(img)
    return src, uv, atlases


def segment_glb(points, faces, src, uv, atlas, frames, fps: float, video: str | None) -> bytes:
    """One segment as a GLB: the seam-split mesh of its first frame, morph targets for the others. ``atlas``:
    the first frame's atlas, (H, W, 3) uint8 or its PNG bytes (``png_bytes``, when the caller has them)."""
    split = [np.asarray(p, np.float64)[src] for p in points]
    normals = [smooth_vertex_normals(p, faces) for p in split]
    b = GltfBuilder("volcap export.volumetric")
    targets = [{"POSITION": p - split[0], "NORMAL": n - normals[0]} for p, n in zip(split[1:], normals[1:])]
    m = b.mesh(split[0], faces, normals=normals[0], uv=texture_uv(uv), targets=targets, name="capture")
    png = atlas if isinstance(atlas, bytes) else png_bytes(atlas)
    b.set_material(m, b.texture_material(png, name="atlas"))
    node = b.node("capture", mesh=m)
    n = len(points)
    if targets:
        times = list(np.arange(n) / fps) + [n / fps]
        weights = np.zeros((n + 1, n - 1), np.float32)
        rows = np.arange(1, n)
        weights[rows, rows - 1] = 1.0
        weights[n] = weights[n - 1]                       # the last frame held for one frame period
        b.animate(node, "weights", times, weights, "STEP", animation="volumetric")
    return b.glb(extras={"fps": fps, "frames": [int(f) for f in frames], "duration": n / fps,
                         **({"texture_video": video} if video else {})})


# libx264's settings beside ``crf``: preset veryfast with tune psnr (no adaptive quantisation, no psycho-visual
# optimisation: the atlas is judged by its PSNR), subpixel refinement 4 (veryfast's 2 costs bits), diamond motion
# search, no weighted prediction (unused on an atlas: the same bytes less its analysis), no 8x8 inter partitions
# (20-30 % of the encoder's time for 1-7 % of the bytes). Against the former preset medium on the demo (12 frames,
# 25 fps; encoder CPU time on the 2-core EPYC, load ~6): the 1024² atlas at crf 18 1.60 -> 0.59 s, 39.01 dB mean
# (was 38.95), worst frame 38.68 (38.52), 5 % more bytes; at crf 28 (the stream's full rung) 0.91 -> 0.49 s,
# 35.60 dB (35.74), worst 35.05 (35.23), 1 % more; the 512² quarter rung 0.32 -> 0.12 s, 32.10 dB (31.80), 28 % more.
X264_OPTIONS = {"preset": "veryfast", "tune": "psnr", "x264-params": "subme=4:me=dia:weightp=0:partitions=i8x8,i4x4"}


def atlas_video(atlases, fps: float, crf: int = 18) -> bytes:
    """The atlases as an H.264 MP4 (yuv420p: even sizes), one frame each at ``fps`` (libx264: ``X264_OPTIONS``)."""
    try:
        import av
    except ImportError:
        raise NodeError("export.volumetric: the video needs PyAV (pip install av); leave 'video' out of formats") from None
    from fractions import Fraction

    buf = io.BytesIO()
    h, w = atlases[0].shape[:2]
    with av.open(buf, "w", format="mp4") as out:
        stream = out.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
        stream.width, stream.height = w + w % 2, h + h % 2
        stream.pix_fmt = "yuv420p"
        stream.options = {"crf": str(crf), **X264_OPTIONS}
        for img in atlases:
            if w % 2 or h % 2:
                img = np.pad(img, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
            for packet in stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(img), format="rgb24")):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    return buf.getvalue()


def read_video(data: bytes) -> list[np.ndarray]:
    """The frames of a video file's bytes as (H, W, 3) uint8 RGB (for checks and the stream reader)."""
    import av

    with av.open(io.BytesIO(data)) as f:
        return [fr.to_ndarray(format="rgb24") for fr in f.decode(video=0)]


def volumetric_files(meshes, textured, frames, name: str, fps: float, formats, crf: int) -> tuple[dict, dict]:
    """(files, report) of the deliverable (module docstring)."""
    from nodes.common.usd import UsdStage

    if len(textured) != len(meshes):
        raise NodeError(f"export.volumetric: {len(textured)} textured meshes for {len(meshes)} tracked frames")
    files, report = {}, {"segments": []}
    stage = UsdStage(fps=fps, frames=(int(frames[0]), int(frames[-1]))) if "usd" in formats else None
    if stage is not None:
        stage.group("/Capture")
    for s, (a, c) in enumerate(sequence_segments(meshes)):
        src, uv, atlases = _segment(meshes, textured, frames, a, c)
        faces = np.asarray(textured[a].faces)
        stem = f"{name}_{s:04d}"
        tex_names = [f"{name}_tex/{int(frames[k]):05d}.png" for k in range(a, c)]
        # zlib frees the GIL: the PNGs on every core of the machine, not this worker's share: the node runs last,
        # after every frame's texture, when the other workers have nothing left (pose2sim at -j 2: one core idle for
        # the 35 s of this node before)
        files.update(zip(tex_names, map_views(png_bytes, atlases, count=os.cpu_count())))
        video = f"{stem}.mp4" if "video" in formats else None
        if video:
            files[video] = atlas_video(atlases, fps, crf)
        if "gltf" in formats:
            files[f"{stem}.glb"] = segment_glb([meshes[k].vertices for k in range(a, c)], faces, src, uv,
                                               files[tex_names[0]], frames[a:c], fps, video)   # its PNG, once
        if stage is not None:
            geom = stage.mesh(f"/Capture/{stem}", faces, uv=uv)
            for k in range(a, c):
                stage.points_at(geom, np.asarray(meshes[k].vertices, np.float64)[src], int(frames[k]))
            keys = {int(frames[a]): True}
            if a > 0:
                keys = {int(frames[0]): False, **keys}
            if c < len(meshes):
                keys[int(frames[c])] = False
            stage.visibility(geom, keys)
            stage.material(geom, f"/Capture/{stem}_material",
                           texture={int(frames[k]): tn for k, tn in zip(range(a, c), tex_names)})
        report["segments"].append({"name": stem, "first_frame": int(frames[a]), "last_frame": int(frames[c - 1]),
                                   "vertices": int(len(src)), "tracked_vertices": int(len(meshes[a].vertices)),
                                   "faces": int(len(faces)), "atlas": list(atlases[0].shape[1::-1])})
    if stage is not None:
        files[f"{name}.usdc"] = stage.save(f"{name}.usdc")
    report["files"] = {k: len(v) for k, v in files.items() if not k.startswith(f"{name}_tex/")}
    report["atlas_frames_bytes"] = int(sum(len(v) for k, v in files.items() if k.startswith(f"{name}_tex/")))
    return files, report
