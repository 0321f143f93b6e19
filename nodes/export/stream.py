"""The stream package: one rung of a volumetric video ladder, small enough to stream (the deliverable's third form).

A rung ``NAME/RUNG/`` holds, per tracked segment ``seg_SSSS``:
    .drc    Draco mesh of the segment's first frame: its seam-split vertices (vertex order kept), faces, UVs
            (``tex_coord``) - the connectivity and the UV set, once
    .pos    every frame's positions, quantised to ``bits`` over the segment's box: frame 0 as is, each later
            frame's motion from the frame before less its breadth-first parent vertex's motion over the mesh
            (neighbours move alike: on the demo figure 5.9 -> 3.6 bits per coordinate), int8 with the few larger
            values listed apart, zlib (deflate: what a browser inflates natively; LZMA would be 9 % smaller)
            (header: JSON length, JSON {frames, vertices, box, bits, escapes}; payload: frame 0 as byte planes,
            int8 residuals, escape indices uint32 and values int32, the parent of each vertex int32 planes)
    .mp4    the atlas per frame, H.264 (PyAV)
and ``manifest.json``: fps, frame numbers, world frame (+Z up, metres), per segment its files, counts, box, bits
and atlas size. ``read_stream`` decodes a rung back to per-frame meshes and atlases (the Python reader; a
player does the same). A ladder is several rungs from several ``export.stream`` nodes (e.g. one fed by
``track.simplify`` and a smaller ``texture`` size), each writing its own folder beside the others.
"""
from __future__ import annotations

import json
import zlib
import struct
from pathlib import Path

import numpy as np

from nodegraph import NodeError
from nodes.common.types import sequence_segments

from .volumetric import _segment, atlas_video, read_video

FORMAT = "volcap-stream"
VERSION = 3   # 3: zlib, parents stored


def _planes(a: np.ndarray) -> bytes:
    """An integer array's bytes split into planes (all low bytes, then the next...): small values compress."""
    return a.view(np.uint8).reshape(a.size, a.itemsize).T.tobytes()


def _unplanes(data: bytes, dtype, count: int) -> np.ndarray:
    dtype = np.dtype(dtype)
    return np.frombuffer(data, np.uint8).reshape(dtype.itemsize, count).T.copy().view(dtype).ravel()


def _bfs_parents(faces, n: int) -> np.ndarray:
    """(n,) breadth-first parent of each vertex over a mesh's edge graph, -1 at each component's root (a forest:
    a seam-split mesh falls apart into its charts; roots the lowest index of each component). One search from a
    hub joined to every root: each component's vertices are met in the order of its own search, so every parent
    is the one a search from its root gives (2.5x faster than a search per chart: 39 on the demo figure)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import breadth_first_order, connected_components

    f = np.asarray(faces, np.int64).reshape(-1, 3)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    A = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    A = ((A + A.T) > 0).astype(np.int8).tocsr()
    _, labels = connected_components(A, directed=False)
    roots = np.unique(labels, return_index=True)[1]
    hub = sp.coo_matrix((np.ones(len(roots), np.int8), (np.full(len(roots), n), roots)), shape=(n + 1, n + 1))
    graph = (sp.block_diag([A, sp.csr_matrix((1, 1), dtype=np.int8)]) + hub + hub.T).tocsr()
    _, pred = breadth_first_order(graph, n, directed=False)
    parent = pred[:n].astype(np.int64)
    parent[roots] = -1
    return parent


def _levels(parent: np.ndarray) -> list[np.ndarray]:
    """Vertices by depth in a forest given by parent indices (-1 at roots)."""
    depth = np.full(len(parent), -1, np.int64)
    depth[parent < 0] = 0
    while (depth < 0).any():
        todo = np.flatnonzero(depth < 0)
        known = depth[parent[todo]] >= 0
        depth[todo[known]] = depth[parent[todo[known]]] + 1
    return [np.flatnonzero(depth == d) for d in range(int(depth.max()) + 1)]


def encode_positions(frames: np.ndarray, bits: int, faces) -> bytes:
    """(F, V, 3) positions as a .pos payload: frame 0 quantised over the box; each later frame's motion (the
    difference from the frame before, in quanta) less its breadth-first parent vertex's motion over the mesh
    (``faces``: the motion of neighbours is alike); int8 with the few larger values listed apart; zlib."""
    frames = np.asarray(frames, np.float64)
    lo, hi = frames.reshape(-1, 3).min(0), frames.reshape(-1, 3).max(0)
    span = np.where(hi > lo, hi - lo, 1.0)
    q = np.round((frames - lo) / span * (2 ** bits - 1)).astype(np.int64)
    first = q[0].astype(np.uint16 if bits <= 16 else np.uint32)
    parent = _bfs_parents(faces, frames.shape[1])
    motion = np.diff(q, axis=0)
    res = motion - np.where(parent[None, :, None] >= 0, motion[:, np.maximum(parent, 0)], 0)
    flat = res.ravel()
    big = np.flatnonzero(np.abs(flat) > 127)
    small = np.where(np.abs(flat) > 127, 0, flat).astype(np.int8)
    head = json.dumps({"frames": int(len(frames)), "vertices": int(frames.shape[1]), "first": first.dtype.name,
                       "box": [lo.tolist(), hi.tolist()], "bits": int(bits), "escapes": int(len(big)),
                       "prediction": "previous frame, then breadth-first parent"}).encode()
    body = (_planes(first) + small.tobytes() + big.astype(np.uint32).tobytes() + flat[big].astype(np.int32).tobytes()
            + _planes(parent.astype(np.int32)))
    return struct.pack("<I", len(head)) + head + zlib.compress(body, 9)


def decode_positions(data: bytes) -> np.ndarray:
    """The (F, V, 3) float64 positions of a .pos payload."""
    (n,) = struct.unpack("<I", data[:4])
    head = json.loads(data[4:4 + n])
    body = zlib.decompress(data[4 + n:])
    nf, nv = head["frames"], head["vertices"]
    at = nv * 3 * np.dtype(head["first"]).itemsize
    first = _unplanes(body[:at], head["first"], nv * 3).astype(np.int64).reshape(nv, 3)
    count = (nf - 1) * nv * 3
    flat = np.frombuffer(body[at:at + count], np.int8).astype(np.int64)
    k = head["escapes"]
    idx = np.frombuffer(body[at + count:at + count + 4 * k], np.uint32)
    flat[idx] = np.frombuffer(body[at + count + 4 * k:at + count + 8 * k], np.int32)
    motion = flat.reshape(nf - 1, nv, 3)
    parent = _unplanes(body[at + count + 8 * k:], np.int32, nv).astype(np.int64)
    for level in _levels(parent)[1:]:                     # add each parent's motion, root to leaves
        motion[:, level] += motion[:, parent[level]]
    q = np.cumsum(np.concatenate([first[None], motion]), axis=0)
    lo, hi = np.array(head["box"][0]), np.array(head["box"][1])
    span = np.where(hi > lo, hi - lo, 1.0)
    return lo + q / (2 ** head["bits"] - 1) * span


def atlas_psnr(atlas: np.ndarray, decoded: np.ndarray) -> float:
    """PSNR (dB) of a decoded uint8 image against the original: the squared errors summed as integers (exact:
    the float64 mean of them gives the same, at 3 MP 4x the time), over their count."""
    d = decoded.astype(np.int16) - atlas
    se = np.einsum("i,i->", d.ravel(), d.ravel(), dtype=np.int64) if d.size else 0
    mse = float(se) / max(d.size, 1)
    return 10 * np.log10(255.0 ** 2 / max(mse, 1e-12))


def stream_files(meshes, textured, frames, name: str, rung: str, fps: float, bits: int, crf: int,
                 draco_bits: int = 14) -> tuple[dict, dict]:
    """(files, report) of one rung (module docstring); the report measures it against its input: bytes,
    Mbit/s at 30 fps and at ``fps``, geometry error (mm) and atlas PSNR (dB) after decoding."""
    import DracoPy

    if len(textured) != len(meshes):
        raise NodeError(f"export.stream: {len(textured)} textured meshes for {len(meshes)} tracked frames")
    folder = f"{name}/{rung}"
    files, segs, errors, psnrs = {}, [], [], []
    video_bytes = geometry_bytes = connectivity_bytes = 0
    for s, (a, c) in enumerate(sequence_segments(meshes)):
        src, uv, atlases = _segment(meshes, textured, frames, a, c)
        faces = np.asarray(textured[a].faces)
        points = np.stack([np.asarray(meshes[k].vertices, np.float64)[src] for k in range(a, c)])
        stem = f"seg_{s:04d}"
        drc = DracoPy.encode(points[0].astype(np.float32), faces.astype(np.uint32), quantization_bits=draco_bits,
                             compression_level=7, preserve_order=True, tex_coord=np.asarray(uv, np.float64),
                             tex_coord_quantization_bits=14)
        pos = encode_positions(points, bits, faces)
        mp4 = atlas_video(atlases, fps, crf)
        files.update({f"{folder}/{stem}.drc": drc, f"{folder}/{stem}.pos": pos, f"{folder}/{stem}.mp4": mp4})
        geometry_bytes += len(drc) + len(pos)
        connectivity_bytes += len(drc)
        video_bytes += len(mp4)
        back = decode_positions(pos)
        errors.append(np.linalg.norm(back - points, axis=2).ravel())
        for img, dec in zip(atlases, read_video(mp4)):
            psnrs.append(atlas_psnr(img, dec[:img.shape[0], :img.shape[1]]))
        segs.append({"name": stem, "first_frame": int(frames[a]), "frames": int(c - a), "vertices": int(len(src)),
                     "faces": int(len(faces)), "geometry": f"{stem}.drc", "positions": f"{stem}.pos",
                     "video": f"{stem}.mp4", "atlas": list(atlases[0].shape[1::-1]), "bits": int(bits)})
    manifest = {"format": FORMAT, "version": VERSION, "name": name, "rung": rung, "fps": fps,
                "frames": [int(f) for f in frames], "up": "+Z", "units": "m", "segments": segs}
    files[f"{folder}/manifest.json"] = json.dumps(manifest, indent=1).encode()
    err = np.concatenate(errors) * 1000
    total = geometry_bytes + video_bytes
    seconds = len(meshes) / fps
    report = {"rung": rung, "frames": len(meshes), "faces": max(s["faces"] for s in segs),
              "atlas": segs[0]["atlas"], "geometry_bytes": int(geometry_bytes), "video_bytes": int(video_bytes),
              "connectivity_bytes": int(connectivity_bytes),
              "mbit_s_motion_at_30fps": round((total - connectivity_bytes) * 8 / (len(meshes) / 30.0) / 1e6, 4),
              "mbit_s": round(total * 8 / seconds / 1e6, 4),
              "mbit_s_at_30fps": round(total * 8 / (len(meshes) / 30.0) / 1e6, 4),
              "geometry_error_mm_mean": round(float(err.mean()), 5), "geometry_error_mm_max": round(float(err.max()), 5),
              "atlas_psnr_db_mean": round(float(np.mean(psnrs)), 3), "atlas_psnr_db_min": round(float(np.min(psnrs)), 3)}
    return files, report


def read_stream(source, rung: str | None = None) -> list[dict]:
    """Per frame {"frame", "vertices" (V, 3), "faces", "uv" (V, 2, trimesh's origin), "atlas" (H, W, 3)} of a
    rung: ``source`` is a rung folder (or the ladder folder with ``rung``), or the files dict of the node."""
    import DracoPy

    if isinstance(source, dict):
        prefix = next(k.rsplit("/", 1)[0] for k in source if k.endswith("manifest.json") and (rung is None or
                                                                                          k.split("/")[-2] == rung))
        read = lambda n: source[f"{prefix}/{n}"]  # noqa: E731
    else:
        folder = Path(source) / rung if rung else Path(source)
        read = lambda n: (folder / n).read_bytes()  # noqa: E731
    manifest = json.loads(read("manifest.json"))
    if manifest.get("format") != FORMAT or manifest.get("version") != VERSION:
        raise NodeError(f"not a {FORMAT} v{VERSION} rung (format {manifest.get('format')!r}, version "
                        f"{manifest.get('version')!r})")
    out, numbers = [], iter(manifest["frames"])
    for seg in manifest["segments"]:
        mesh = DracoPy.decode(read(seg["geometry"]))
        faces = np.asarray(mesh.faces).reshape(-1, 3)
        uv = np.asarray(mesh.tex_coord, np.float64).reshape(-1, 2)
        points = decode_positions(read(seg["positions"]))
        atlases = read_video(read(seg["video"]))
        w, h = seg["atlas"]
        if len(points) != seg["frames"] or len(atlases) < seg["frames"] or points.shape[1] != len(uv):
            raise NodeError(f"stream segment {seg['name']}: {len(points)} position frames, {len(atlases)} video frames, "
                            f"{points.shape[1]} vertices vs {len(uv)} UVs; the manifest says {seg['frames']} frames")
        for k in range(seg["frames"]):
            out.append({"frame": next(numbers), "vertices": points[k], "faces": faces, "uv": uv,
                        "atlas": atlases[k][:h, :w]})
    return out
