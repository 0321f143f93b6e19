"""Nodes of the track stage: classify a mesh sequence (Table 8.1), crop silhouettes for sequence work, track
keyframe meshes into a dynamic mesh. The exports are in export.py (their own module: editing a writer does not
re-run the tracking)."""
from __future__ import annotations

import time

import numpy as np

from kernels import source
from nodegraph import Input, Node, NodeError, Output, Param, Table
from nodes.common.types import CameraSet, Masks, MaskSet, Mesh, MeshSequence

from .deform import FitParams
from .topology import classify_sequence, mesh_topology, sequence_class
from .tracking import Frames, TrackParams, track_sequence

_TRACK, _FIT = TrackParams(), FitParams()


class Classify(Node):
    """The class of a mesh sequence after the seed chapter's Table 8.1 (Arcila 2011), per frame range: dynamic
    mesh (constant vertex count, connectivity and topology), stable mesh sequence (constant topology) or
    unconstrained mesh sequence (topology changes); with vertex count, genus and components per frame.
    Connect either per-frame meshes or a mesh sequence (e.g. the output of track)."""

    type_name = "track.classify"
    version = 1
    per = "sequence"
    inputs = {
        "meshes": Input(Mesh, optional=True, doc="per-frame meshes (arrive as a list)"),
        "sequence": Input(MeshSequence, optional=True, doc="or a mesh sequence"),
    }
    outputs = {"report": Output(Table, "class of the whole sequence, ranges with their class, per-frame topology")}

    def run(self, meshes=None, sequence=None):
        if (meshes is None) == (sequence is None):
            raise NodeError("track.classify: connect exactly one of 'meshes' and 'sequence'")
        seq = sequence if sequence is not None else meshes
        frames = list(self.frames) if meshes is not None and len(self.frames) == len(seq) else [
            int(m.metadata.get("frame", i)) for i, m in enumerate(seq)]
        pairs = [(np.asarray(m.vertices), np.asarray(m.faces)) for m in seq]
        topo = [mesh_topology(v, f) for v, f in pairs]
        ranges = classify_sequence(pairs, topo)
        for r in ranges:
            r["frames"] = r["stop"] - r["start"] + 1
            r["start"], r["stop"] = frames[r["start"]], frames[r["stop"]]
        counts = {}
        for r in ranges:
            counts[r["class"]] = counts.get(r["class"], 0) + r["frames"]
        return {"report": {
            "class": sequence_class(pairs, topo),
            "ranges": ranges,
            "frames_per_class": counts,
            "topology": {"components": [t["components"] for t in topo], "genus": [t["genus"] for t in topo],
                         "vertices": [t["vertices"] for t in topo]},
            "frame_numbers": {"first": frames[0] if frames else None, "last": frames[-1] if frames else None},
        }}


class CropViews(Node):
    """Masks and cameras cropped to the silhouette's bounding box plus a margin (principal point shifted):
    the same point test and silhouettes in a fraction of the memory, for a sequence node that holds every
    frame's masks (track). Mesh pixels beyond the margin are not seen by a silhouette score on cropped views."""

    type_name = "track.crop"
    version = 1
    inputs = {"masks": Masks, "cameras": CameraSet}
    outputs = {"masks": Masks, "cameras": CameraSet}
    params = {"margin": Param(int, 48, range=(0, 100000), doc="pixels kept around each silhouette's box")}

    def run(self, masks, cameras, *, margin):
        import cv2

        from nodes.common.cameras import Cameras
        from nodes.common.silhouettes import check_masks

        binary = check_masks(masks, cameras, "track.crop")
        out_m, out_a, out_c = [], [], []
        for i, (cam, m) in enumerate(zip(cameras, binary)):
            bx, by, bw, bh = cv2.boundingRect((m > 127).view(np.uint8))   # the box of the pixels > 127 (np.nonzero's: 5x slower)
            if bw == 0:
                x0, y0, x1, y1 = 0, 0, 1, 1
            else:
                x0, y0 = max(0, bx - margin), max(0, by - margin)
                x1, y1 = min(m.shape[1], bx + bw + margin), min(m.shape[0], by + bh + margin)
            out_m.append(np.ascontiguousarray(m[y0:y1, x0:x1]))
            if masks.alpha is not None:
                out_a.append(np.ascontiguousarray(masks.alpha[i][y0:y1, x0:x1]))
            out_c.append(cam.cropped(x0, y0, x1 - x0, y1 - y0))
        return {"masks": MaskSet(out_m, out_a if masks.alpha is not None else None, list(masks.names)),
                "cameras": Cameras(out_c)}


class Frame(Node):
    """One frame of a tracked sequence, for the per-frame stages after tracking: the frame's tracked mesh and
    its segment's keyframe mesh (same faces, fixed shape: give it to ``texture`` as ``reference`` and every
    frame of a segment gets the same atlas, so the texture stays in place over time)."""

    type_name = "track.frame"
    version = 1
    uses_frame = True
    inputs = {"sequence": Input(MeshSequence, doc="a tracked sequence (track)")}
    outputs = {"mesh": Output(Mesh, "this frame's tracked mesh"),
               "keyframe": Output(Mesh, "its segment's keyframe mesh (the segment's first when none is recorded)")}

    def run(self, sequence, *, frame):
        from nodes.common.types import sequence_segments

        at = [i for i, m in enumerate(sequence) if m.metadata.get("frame") == frame]
        if not at:
            known = [m.metadata.get("frame") for m in sequence]
            raise NodeError(f"track.frame: frame {frame} is not in the sequence (frames "
                            f"{known[0]}..{known[-1]}): run it over the frames the sequence was tracked on")
        i = at[0]
        start, stop = next((a, b) for a, b in sequence_segments(sequence) if a <= i < b)
        key = sequence[i].metadata.get("keyframe")
        k = next((j for j in range(start, stop) if sequence[j].metadata.get("frame") == key), start)
        return {"mesh": sequence[i], "keyframe": sequence[k]}


class Simplify(Node):
    """A tracked sequence with fewer faces and the same motion (simplify.py): per segment the keyframe's quadric
    edge collapses replayed on every frame, so each segment keeps one connectivity (a stream's lower rung)."""

    type_name = "track.simplify"
    version = 1
    per = "sequence"
    inputs = {"sequence": Input(MeshSequence, doc="a tracked sequence (track)")}
    outputs = {"sequence": Output(MeshSequence, "the same frames and segments, fewer faces"),
               "report": Output(Table, "faces in and out per segment")}
    params = {"faces": Param(float, 0.25, range=(0.01, 1.0), doc="fraction of the faces to keep (about)")}

    def run(self, sequence, *, faces):
        from .simplify import simplify_sequence

        if not sequence:
            raise NodeError("track.simplify: the sequence is empty")
        out, report = simplify_sequence(list(sequence), faces)
        return {"sequence": out, "report": report}


class Track(Node):
    """Per-frame reconstructions (an unconstrained mesh sequence) -> a dynamic mesh per segment: keyframes
    chosen automatically by trial (up to ``tries`` candidates per round, ranked by fewest components, lowest
    genus, largest area; the longest segment is kept), each keyframe's mesh deformed forwards and backwards
    onto every frame's reconstruction (embedded deformation graph with an ARAP regulariser; point-to-plane
    terms both ways and a silhouette term near the outlines when masks and cameras are connected; then
    per-vertex detail along the normals and the vertices put on the reconstruction), a new segment where the
    fit fails (topology change, too fast a motion). Output: the tracked sequence (one face array per segment) and per-frame
    residuals in voxels (surface distance both ways, silhouette IoU against the reconstruction's own)."""

    type_name = "track"
    version = 1
    per = "sequence"
    kernels = [source("closest.cl"), source("rotations.cl"), source("raster.cl"), source("outline.cl"),
               source("edt.cl")]
    # closest points (nodes.common.closest), ARAP rotations, silhouette IoU, the silhouette term and its distance outline
    inputs = {
        "meshes": Input(Mesh, doc="each frame's reconstruction (arrive as a list)"),
        "masks": Input(Masks, optional=True, doc="silhouettes per frame (track.crop keeps them small)"),
        "cameras": Input(CameraSet, optional=True, doc="cameras per frame, with masks"),
    }
    outputs = {
        "sequence": Output(MeshSequence, "tracked meshes, metadata segment / keyframe / frame"),
        "residuals": Output(Table, "per-frame residuals (voxels), segments, keyframes"),
    }
    # the defaults are the library's (TrackParams, FitParams): the benches that call track_sequence directly
    # measure what a graph gets
    params = {
        "voxel": Param(float, _TRACK.voxel, range=(0.0, None), doc="metres per voxel (distances are in voxels); 0 = 2 x median edge length"),
        "spacing": Param(float, _TRACK.spacing, range=(1.0, 100.0), doc="deformation graph node spacing, voxels"),
        "iterations": Param(int, _FIT.iterations, range=(1, 100), doc="ICP iterations per frame (limbs that move "
                            "several voxels a frame: 15, as graphs/track_child_rope.yaml)"),
        "arap": Param(float, _FIT.arap, range=(0.0, None), doc="ARAP stiffness at the last iteration (starts 4x higher)"),
        "coverage": Param(float, _FIT.coverage, range=(0.0, None), doc="weight of the reconstruction -> tracked term (limbs that moved are reached)"),
        "silhouette": Param(float, _FIT.silhouette, range=(0.0, None), doc="silhouette term weight (with masks and cameras)"),
        "samples": Param(int, _FIT.samples, range=(100, None), doc="vertices sampled per surface for the fit"),
        "fail_mean": Param(float, _TRACK.fail_mean, range=(0.0, None), doc="a fit fails beyond this mean surface distance, voxels"),
        "fail_p95": Param(float, _TRACK.fail_p95, range=(0.0, None), doc="... or this 95th percentile distance, either direction"),
        "max_iou_drop": Param(float, _TRACK.max_iou_drop, range=(0.0, 1.0), doc="... or this silhouette IoU below the reconstruction's"),
        "min_views": Param(int, 0, range=(0, None), doc="silhouette vote: 0 = all views; k = inside at least k"),
        "extrapolate": Param(float, _TRACK.extrapolate, range=(0.0, 1.0), doc="each frame starts from the last state plus this share of the last motion"),
        "tries": Param(int, _TRACK.tries, range=(1, 100), doc="keyframe candidates tracked per round; the longest segment is kept"),
        "retry": Param(int, _TRACK.retry, range=(0, 100), doc="a failed fit is tried again from the previous frame's state (no motion "
                       "prediction) with this many times the iterations (0, 1: no second try)"),
        "bridge": Param(int, _TRACK.bridge, range=(0, 1000), doc="after a failed fit, frames tracked on to one that fits, then filled "
                        "backwards from it (0: a failed fit ends the segment)"),
    }

    def run(self, meshes, masks=None, cameras=None, *, voxel, spacing, iterations, arap, coverage, silhouette, samples,
            fail_mean, fail_p95, max_iou_drop, min_views, extrapolate, tries, retry, bridge):
        if (masks is None) != (cameras is None):
            raise NodeError("track: connect both 'masks' and 'cameras', or neither")
        if not meshes:
            raise NodeError("track: no meshes")
        for name, lst in (("masks", masks), ("cameras", cameras)):
            if lst is not None and len(lst) != len(meshes):
                raise NodeError(f"track: {len(lst)} {name} for {len(meshes)} meshes")
        frames = list(self.frames) if len(self.frames) == len(meshes) else list(range(len(meshes)))
        t0 = time.perf_counter()
        data = Frames(meshes, masks, cameras, voxel, min_views, numbers=frames)
        params = TrackParams(spacing, data.voxel, fail_mean, fail_p95, max_iou_drop, extrapolate,
                             FitParams(iterations=iterations, arap=arap, arap_start=_FIT.arap_start / _FIT.arap * arap, coverage=coverage, silhouette=silhouette,
                                       samples=samples), tries, bridge, retry)
        results, segments = track_sequence(data, params, progress=self.progress)
        seconds = time.perf_counter() - t0
        import trimesh

        out = []
        for i, r in enumerate(results):
            seg = segments[r.segment]
            m = trimesh.Trimesh(r.vertices, seg.faces, process=False)
            m.metadata.update(segment=r.segment, keyframe=frames[seg.keyframe], frame=frames[i])
            out.append(m)
        for seg in segments:
            self.log.info("segment %d: keyframe %d, frames %d..%d; %s | %s", seg.index, frames[seg.keyframe],
                          frames[seg.start], frames[seg.stop], seg.reason_start, seg.reason_stop)
        return {"sequence": out, "residuals": residual_table(results, segments, frames, data, seconds)}


def residual_table(results, segments, frames, data, seconds) -> dict:
    """The residuals Table: scalars, ``residual`` lists the report draws (distance = mean of both directions,
    the larger 95th percentile of the two, IoU drop), ``timeline`` per frame, ``segments``."""
    dist = [0.5 * (r.accuracy_mean + r.completeness_mean) for r in results]
    lengths = [s.stop - s.start + 1 for s in segments]
    table = {
        "frames": len(results), "segment_count": len(segments), "voxel": data.voxel,
        "segment_length_median": float(np.median(lengths)), "segment_length_min": int(min(lengths)),
        "distance_mean": float(np.mean(dist)), "distance_max": float(np.max(dist)),
        "seconds": seconds, "seconds_per_frame": seconds / len(results),
        "bridged_frames": int(sum(r.bridged for r in results)),
        "residual": {"distance": dist, "distance_p95": [max(r.accuracy_p95, r.completeness_p95) for r in results]},
        "timeline": {
            "frame": frames, "segment": [r.segment for r in results],
            "keyframe": [frames[r.keyframe] for r in results],
            "accuracy_mean": [r.accuracy_mean for r in results], "accuracy_p95": [r.accuracy_p95 for r in results],
            "completeness_mean": [r.completeness_mean for r in results],
            "completeness_p95": [r.completeness_p95 for r in results],
            "seconds": [r.seconds for r in results],
            "bridged": [r.bridged for r in results],
        },
        "segments": [{
            "start": frames[s.start], "stop": frames[s.stop], "frames": s.stop - s.start + 1,
            "keyframe": frames[s.keyframe], "vertices": int(len(results[s.keyframe].vertices)), "faces": int(len(s.faces)),
            "graph_nodes": s.nodes, "genus": data.stats[s.keyframe]["genus"],
            "components": data.stats[s.keyframe]["components"], "ended_before": s.reason_start, "ended_after": s.reason_stop,
        } for s in segments],
    }
    if data.has_views:
        drop = [max(0.0, r.iou_reconstruction - r.iou) for r in results]
        table["residual"]["iou_drop"] = drop
        table["iou_drop_max"] = float(max(drop))
        table["timeline"]["iou"] = [r.iou for r in results]
        table["timeline"]["iou_reconstruction"] = [r.iou_reconstruction for r in results]
    return table
