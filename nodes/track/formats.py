"""Dynamic-mesh exports a production pipeline reads, from a tracked mesh sequence (one connectivity per segment):

    USD (usd-core)   one UsdGeom.Mesh per segment under /DynamicMesh: faces once, ``points`` (and ``extent``)
                     time-sampled at the frame numbers, ``visibility`` invisible outside the segment's frames;
                     binary crate (.usdc), up axis Z, metres, time codes per second = fps.
    glTF (pygltflib) one node + mesh per segment: its first frame as the base POSITION and NORMAL (smooth),
                     every later frame a morph target (POSITION and NORMAL displacements), an animation whose
                     STEP weights switch on one target per frame and whose STEP scale shows the node only during
                     its segment (.glb); every channel ends at the clip's end, n frames / fps (``clip_duration``):
                     the last frame is held for one frame period, so a looping viewer shows it like the others.
    Draco (DracoPy)  per segment its connectivity once (a mesh, vertex order preserved) and per frame its
                     positions only (a point cloud, vertex order preserved: vertex i stays the same surface point
                     within a segment), positions quantised to ``bits``.

``sizes`` compares the storage of the dynamic mesh with that of per-frame meshes (binary PLY / Draco).
"""
from __future__ import annotations

import numpy as np

from nodes.common.types import FPS, sequence_segments


def frame_numbers(meshes) -> list[int]:
    """The frame number of each mesh (metadata "frame"), else its index."""
    return [int(m.metadata.get("frame", i)) for i, m in enumerate(meshes)]


# ---------------------------------------------------------------- USD
def usd_bytes(meshes, fps: float = FPS) -> bytes:
    """The sequence as a binary USD layer (see the module docstring)."""
    from nodes.common.usd import UsdStage

    frames = frame_numbers(meshes)
    stage = UsdStage(fps=fps, frames=(frames[0], frames[-1]) if frames else None)
    stage.group("/DynamicMesh")
    for s, (a, b) in enumerate(sequence_segments(meshes)):
        prim = stage.mesh(f"/DynamicMesh/segment_{s:04d}", meshes[a].faces)
        prim.GetPrim().SetCustomDataByKey("keyframe", int(meshes[a].metadata.get("keyframe", frames[a])))
        for k in range(a, b):
            stage.points_at(prim, meshes[k].vertices, frames[k])
        keys = {frames[0]: False} if a > 0 else {}
        keys[frames[a]] = True
        if b < len(meshes):
            keys[frames[b]] = False
        stage.visibility(prim, keys)
    return stage.save("dynamic_mesh.usdc")


def usd_points(data: bytes, frame: int) -> np.ndarray:
    """Points of the segment visible at ``frame`` in a layer written by ``usd_bytes`` (as a reader sees it)."""
    from pxr import Usd, UsdGeom

    from nodes.common.usd import opened

    with opened(data) as stage:
        for prim in stage.GetPrimAtPath("/DynamicMesh").GetChildren():
            mesh = UsdGeom.Mesh(prim)
            if mesh.ComputeVisibility(Usd.TimeCode(frame)) != UsdGeom.Tokens.invisible:
                return np.array(mesh.GetPointsAttr().Get(Usd.TimeCode(frame)), np.float32)
    raise KeyError(f"no segment is visible at frame {frame}")


# ---------------------------------------------------------------- glTF
def clip_duration(frames, fps: float) -> float:
    """Seconds of a clip of frames ``frames[0]..frames[-1]``: each frame lasts 1 / fps, the last one too, so a
    looping viewer shows every frame for one frame period (the clip's last key is at its end, n / fps)."""
    return (frames[-1] - frames[0] + 1) / fps if len(frames) else 0.0


def _held(times, values, end: float):
    """Key times and values with a last key at ``end`` repeating the last value (held to the clip's end)."""
    times, values = list(times), list(values)
    if times and times[-1] < end:
        times.append(end)
        values.append(values[-1])
    return np.asarray(times, np.float32), np.asarray(values, np.float32)


def gltf_bytes(meshes, fps: float = FPS) -> bytes:
    """The sequence as a binary glTF (.glb) with morph-target animation (see the module docstring)."""
    from nodes.common.gltf import GltfBuilder
    from nodes.common.meshops import smooth_vertex_normals

    frames = frame_numbers(meshes)
    b = GltfBuilder("volcap track.export")
    t0 = frames[0] if frames else 0
    end = clip_duration(frames, fps)
    for s, (a, c) in enumerate(sequence_segments(meshes)):
        base = np.asarray(meshes[a].vertices, np.float32)
        normals = [smooth_vertex_normals(meshes[k].vertices, meshes[a].faces).astype(np.float32) for k in range(a, c)]
        targets = [{"POSITION": np.asarray(meshes[k].vertices, np.float32) - base, "NORMAL": normals[k - a] - normals[0]}
                   for k in range(a + 1, c)]
        name = f"segment_{s:04d}"
        node = b.node(name, mesh=b.mesh(base, meshes[a].faces, normals=normals[0], targets=targets, name=name),
                      scale=[0.0, 0.0, 0.0] if a > 0 else None)
        times = [(frames[k] - t0) / fps for k in range(a, c)]
        if targets:
            weights = np.zeros((c - a, len(targets)), np.float32)
            weights[np.arange(1, c - a), np.arange(len(targets))] = 1.0
            b.animate(node, "weights", *_held(times, weights, end), "STEP", animation="dynamic_mesh")
        # shown only during its frames: STEP scale 0 -> 1 -> 0
        keys = [(0.0, 0.0)] if a > 0 else []
        keys.append((times[0], 1.0))
        if c < len(meshes):
            keys.append(((frames[c] - t0) / fps, 0.0))
        if len(keys) > 1:
            b.animate(node, "scale", *_held([k[0] for k in keys], [[k[1]] * 3 for k in keys], end), "STEP",
                      animation="dynamic_mesh")
    return b.glb(extras={"fps": fps, "duration": end, "frames": frames})


def gltf_frame(data: bytes, index: int) -> np.ndarray:
    """Positions of the ``index``-th frame (0-based over the whole sequence) as a reader evaluates the .glb:
    at that frame's time (extras: frames, fps), the node whose STEP scale is not 0, its base plus its morph
    targets weighted by the STEP weights; in the world frame."""
    import pygltflib as G

    from nodes.common.gltf import read_accessor, world_points

    g = G.GLTF2.load_from_bytes(data)
    blob = g.binary_blob()
    read = lambda i: read_accessor(g, blob, i)  # noqa: E731

    frames = g.extras["frames"]
    fps = g.extras["fps"]
    anim = g.animations[0] if g.animations else None
    t = (frames[index] - frames[0]) / fps
    for node_i in g.scenes[0].nodes:
        node = g.nodes[node_i]
        scale = np.array(node.scale or [1.0, 1.0, 1.0])
        weights = None
        for ch in anim.channels if anim else []:
            if ch.target.node != node_i:
                continue
            smp = anim.samplers[ch.sampler]
            keys, vals = read(smp.input), read(smp.output)
            k = int(np.searchsorted(keys, t + 1e-6) - 1)
            if ch.target.path == "scale":
                scale = vals[k] if k >= 0 else scale
            else:
                n_t = len(g.meshes[node.mesh].primitives[0].targets)
                weights = vals.reshape(len(keys), n_t)[max(k, 0)] if k >= 0 else np.zeros(n_t)
        if scale[0] == 0:
            continue
        prim = g.meshes[node.mesh].primitives[0]
        p = read(prim.attributes.POSITION).astype(np.float64)
        for w, tg in zip(weights if weights is not None else [], prim.targets or []):
            if w:
                p = p + w * read(tg["POSITION"])
        return world_points(p).astype(np.float32)
    raise KeyError(f"no node is visible at frame index {index} ({fps} fps)")


# ---------------------------------------------------------------- Draco and sizes
def draco_frames(meshes, bits: int = 14) -> list[bytes]:
    """One Draco mesh per frame (positions and faces), as per-frame reconstructions are stored."""
    import DracoPy

    return [DracoPy.encode(np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.uint32), quantization_bits=bits,
                           compression_level=7) for m in meshes]


def draco_sequence(meshes, bits: int = 14) -> dict[str, bytes]:
    """The dynamic mesh in Draco: per segment its connectivity once (``segment_NNNN.drc``: a mesh of its first
    frame, vertex order preserved) and per frame its positions only (``frame_NNNNN.drc``: a point cloud, vertex
    order preserved), so frame k's mesh is its points with its segment's faces."""
    import DracoPy

    frames = frame_numbers(meshes)
    out = {}
    for s, (a, b) in enumerate(sequence_segments(meshes)):
        out[f"segment_{s:04d}.drc"] = DracoPy.encode(np.asarray(meshes[a].vertices, np.float32),
                                                     np.asarray(meshes[a].faces, np.uint32), quantization_bits=bits,
                                                     compression_level=7, preserve_order=True)
        for k in range(a, b):
            out[f"frame_{frames[k]:05d}.drc"] = DracoPy.encode(np.asarray(meshes[k].vertices, np.float32),
                                                               quantization_bits=bits, compression_level=7,
                                                               preserve_order=True)
    return out


def ply_size(mesh) -> int:
    return len(mesh.export(file_type="ply"))


def sizes(dynamic, reconstructions=None, files: dict | None = None, bits: int = 14) -> dict:
    """Bytes of the dynamic mesh (raw: float32 points per frame + int32 faces once per segment; and each
    exported file) and, given the per-frame reconstructions, of those as binary PLY and as Draco."""
    segs = sequence_segments(dynamic)
    raw = sum(len(m.vertices) * 12 for m in dynamic) + sum(len(dynamic[a].faces) * 12 for a, _ in segs)
    out = {"frames": len(dynamic), "segments": len(segs), "dynamic_raw_bytes": int(raw),
           "dynamic_ply_per_frame_bytes": int(sum(ply_size(m) for m in dynamic))}
    for name, data in (files or {}).items():
        out.setdefault("files", {})[name] = len(data)
    if reconstructions is not None:
        rec_raw = sum(len(m.vertices) * 12 + len(m.faces) * 12 for m in reconstructions)
        out["reconstruction_raw_bytes"] = int(rec_raw)
        out["reconstruction_ply_bytes"] = int(sum(ply_size(m) for m in reconstructions))
        out["reconstruction_draco_bytes"] = int(sum(len(b) for b in draco_frames(reconstructions, bits)))
        out["dynamic_vs_reconstruction_raw"] = raw / max(1, rec_raw)
    return out
