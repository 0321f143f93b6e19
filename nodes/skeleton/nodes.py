"""Nodes of the skeleton stage: skeletonize (a joint tree from one frame's solid), skeletonize.sequence (a
skeleton from the rigid parts of a dynamic mesh's motion), skin (LBS weights and bone motions fitted to the
sequence, rotation-only joints), skeleton.humanoid (a named humanoid template fitted to one body),
skeleton.load (a skeleton from a BVH file) and skeleton.export (UsdSkel and glTF skin + animation)."""
from __future__ import annotations

import time

import numpy as np

from nodegraph import Files, InPath, Input, Node, NodeError, Output, Param, Table
from nodes.common.types import (FPS_PARAM, CameraSet, Mesh, MeshSequence, Skeleton, SkeletonData, Volume,
                               sequence_segments)

from .humanoid import FOOT, HAND, REST_POSES, TOOLS
from .skinning import family_weights, is_helper

# the template's hands and feet (skeleton.humanoid, skeletonize.humanoid)
HAND_PARAM = Param(float, HAND, range=(0.0, 0.15), doc="the wrist this share of the body's height back from the hand's "
                   "end of the arm's centre line (people: MediaPipe's wrists on three real captures, 0.075-0.107); 0: a "
                   "body without hands (the synthetic figure: its arms end at the wrists)")
FOOT_PARAM = Param(float, FOOT, range=(0.04, 0.2), doc="the ankle this share of the body's height back from the toe's "
                   "end of the leg's centre line, the knee halfway up from it to the hip (people: MediaPipe's ankles on "
                   "three real captures, 0.113-0.148; the synthetic figure's short feet: 0.08)")

# ---------------------------------------------------------------- per frame

PERSON_HEIGHT_M = (0.3, 2.5)       # a skeleton named as a person outside: a warning (units? up?)


class Skeletonize(Node):
    """Curve skeleton of one frame's solid (a closed mesh, voxelized, or a voxel volume) as a joint tree:
    TEASAR centre lines through the distance field (what kimimaro does), short branches cut, re-rooted at
    the tree's centre, joints at branch points, at bends (Douglas-Peucker) and at the extremities. A tree
    with five extremities is named as a person (head, hand_0/1, foot_0/1, by ``up``)."""

    type_name = "skeletonize"
    version = 1
    inputs = {
        "mesh": Input(Mesh, optional=True, doc="a closed mesh (voxelized at 'resolution')"),
        "volume": Input(Volume, optional=True, doc="or an occupancy volume (> 0.5 is inside)"),
    }
    outputs = {
        "skeleton": Output(Skeleton, "joint tree (no weights)"),
        "report": Output(Table, "joints, extremities and their names, voxel size (the wall time is in the log)"),
    }
    params = {
        "resolution": Param(int, 128, range=(16, 1024), doc="voxels along the mesh's longest side (mesh input)"),
        "scale": Param(float, 1.5, range=(0.0, 10.0), doc="a path explains voxels within scale x radius + const"),
        "const": Param(float, 2.0, range=(0.0, 100.0), doc="... + const voxels"),
        "prune": Param(float, 2.0, range=(0.0, 20.0), doc="cut extremity branches shorter than prune x radius at their fork"),
        "bend": Param(float, 2.0, range=(0.1, 100.0), doc="Douglas-Peucker tolerance for bend joints, voxels"),
        "smooth": Param(float, 1.0, range=(0.0, 100.0), doc="branch smoothing along the arc before simplifying, voxels"),
        "up": Param(list, [0.0, 0.0, 1.0], item=float, length=3, doc="world up, to name a person's extremities"),
    }

    def run(self, mesh=None, volume=None, *, resolution, scale, const, prune, bend, smooth, up):
        from .curve import curve_skeleton, voxelize

        if (mesh is None) == (volume is None):
            raise NodeError("skeletonize: connect exactly one of 'mesh' and 'volume'")
        t0 = time.perf_counter()
        if mesh is not None:
            if len(mesh.faces) == 0:
                raise NodeError("skeletonize: input 'mesh' has no faces")
            occ, origin, voxel = voxelize(mesh.vertices, mesh.faces, resolution)
            spacing = voxel
        else:
            occ = np.asarray(volume.occupancy) > (0.5 if volume.occupancy.dtype.kind == "f" else 0)
            origin, spacing = volume.bbox_min, volume.voxel_size
            if not np.allclose(spacing, spacing[0], rtol=1e-3):
                self.log.warning("skeletonize: anisotropic voxels %s; distances use the true spacing", spacing)
        if not occ.any():
            raise NodeError(f"skeletonize: the {'mesh encloses no voxel' if mesh is not None else 'volume is empty'}")
        sk = curve_skeleton(occ, origin, spacing, scale=scale, const=const, prune=prune, bend=bend, smooth=smooth, up=up)
        self.log.info("skeletonize: %d joints in %.2f s", len(sk.parents), time.perf_counter() - t0)
        leaves = sk.leaves
        report = {
            "joints": len(sk.parents), "extremities": len(leaves), "names": [sk.names[j] for j in leaves],
            "kinds": {k: sk.kind.count(k) for k in ("root", "branch", "bend", "end")},
            "voxel": float(np.min(spacing)), "voxels_inside": int(occ.sum()),
        }
        if "head" in report["names"]:       # named as a person: a plausible height along up (the world frame's metres)
            u = np.asarray(up, np.float64) / (np.linalg.norm(up) or 1.0)
            pts = np.asarray(mesh.vertices) if mesh is not None else origin + (np.argwhere(occ) + 0.5) * spacing
            report["height"] = round(float(np.ptp(pts @ u)), 4)
            if not PERSON_HEIGHT_M[0] <= report["height"] <= PERSON_HEIGHT_M[1]:
                self.log.warning("skeletonize: a person %.3g m tall along up %s: is the world frame in metres "
                                 "(capture: units) and upright (capture: up)?", report["height"], list(up))
        return {"skeleton": SkeletonData(sk.joints, list(sk.parents), list(sk.names)), "report": report}


class Humanoid(Node):
    """A named humanoid skeleton fitted to one body (humanoid.py): pelvis, spine, chest, neck, head, clavicles,
    shoulders, elbows, wrists, hips, knees, ankles, toes (and the head's, hands' ends) placed along the body's
    curve skeleton by the template's proportions, elbows and knees at the limb's bend; left and right from the
    feet, which point forwards. Names as ours or as Mixamo, the Unreal mannequin or SMPL name them."""

    type_name = "skeleton.humanoid"
    version = 4     # 2: the landmarks place the limb joints; 3: wrists, ankles and knees from ``hand`` and ``foot``;
                    # 4: shoulders, elbows, knees, head and clavicles placed anew (stop 44)
    inputs = {"mesh": Input(Mesh, optional=True, doc="a closed body mesh"),
              "volume": Input(Volume, optional=True, doc="or its occupancy"),
              "points": Input(Table, optional=True, doc="body landmarks in 3D (skeleton.keypoints): they name the "
                              "head, hands and feet, tell left from right (a person's face does) and place the "
                              "shoulders, elbows, wrists, knees and ankles along the limbs' centre lines")}
    outputs = {"skeleton": Output(Skeleton, "the named joint tree (rest pose = this body)"),
               "report": Output(Table, "where the sides came from, elbow/knee bends, bone lengths, height")}
    params = {
        "resolution": Param(int, 128, range=(16, 512), doc="voxels along the mesh's longest side"),
        "up": Param(list, [0.0, 0.0, 1.0], item=float, length=3, doc="world up (the world frame's +Z)"),
        "naming": Param(str, "volcap", choices=("volcap",) + TOOLS, doc="joint names: ours, or a retargeting "
                        "tool's (joints it has no name for keep ours)"),
        "hand": HAND_PARAM,
        "foot": FOOT_PARAM,
    }

    def run(self, mesh=None, volume=None, points=None, *, resolution, up, naming, hand, foot):
        from .curve import voxelize
        from .humanoid import body_marks, fit_humanoid, retarget_names

        marks = None
        if points is not None:
            try:
                marks = body_marks(dict(zip(points["landmarks"], points["points"])))
            except (KeyError, TypeError):
                raise NodeError("skeleton.humanoid: input 'points' is not skeleton.keypoints' table (landmarks, "
                                "points)") from None
            if marks is None:
                self.log.warning("skeleton.humanoid: the landmarks lack a nose, a hand, a foot, hips or shoulders "
                                 "in 3D: extremities and sides from the shape")

        if (mesh is None) == (volume is None):
            raise NodeError("skeleton.humanoid: connect exactly one of 'mesh' and 'volume'")
        if mesh is not None:
            occ, origin, spacing = voxelize(mesh.vertices, mesh.faces, resolution)
        else:
            occ = np.asarray(volume.occupancy) > (0.5 if volume.occupancy.dtype.kind == "f" else 0)
            origin, spacing = volume.bbox_min, volume.voxel_size
        if not occ.any():
            raise NodeError("skeleton.humanoid: the body encloses no voxel")
        joints, parents, names, report = fit_humanoid(occ, origin, spacing, up, marks=marks, hand=hand, foot=foot)
        if naming != "volcap":
            table = retarget_names(naming)
            names = [table.get(n, n) for n in names]
        report["names"] = names
        return {"skeleton": SkeletonData(joints, parents, names), "report": report}


class LoadSkeleton(Node):
    """A skeleton from a BVH file (its hierarchy's rest pose: the offsets; metres, +Y up as BVH is, into the world
    frame's +Z up): e.g. your own template's bone lengths for skeletonize.humanoid (the seed's "skeletal model
    provided at the start"), joints named as the template's or as Mixamo, the Unreal mannequin or SMPL name them."""

    type_name = "skeleton.load"
    version = 1
    outputs = {"skeleton": Output(Skeleton, "the joint tree at the file's rest pose (no weights, no motion)")}
    params = {"path": Param(InPath, doc="a .bvh file")}

    def run(self, *, path):
        from pathlib import Path

        from .formats import read_bvh

        try:
            bvh = read_bvh(Path(path).read_text())
        except (ValueError, IndexError, UnicodeDecodeError) as exc:
            raise NodeError(f"skeleton.load: {path} is not a BVH this reads ({exc or 'truncated'})") from None
        self.log.info("skeleton.load: %s: %d joints", path, len(bvh["names"]))
        return {"skeleton": SkeletonData(bvh["rest"], bvh["parents"], bvh["names"])}


class Keypoints(Node):
    """Body landmarks seen in several views (key.person's keypoints) triangulated into 3D points (keypoints.py):
    per landmark the point nearest the rays of the views that see it, the view that reprojects worst dropped
    while beyond ``max_error`` pixels: named 3D body points per frame (a check of the rig, a mocap-style track)."""

    type_name = "skeleton.keypoints"
    version = 1
    publishes = True   # OUT/tables/<node>/<frame>.json: the 3D landmarks per frame
    inputs = {"keypoints": Input(Table, doc="key.person's table: per camera the landmarks in pixels"),
              "cameras": CameraSet}
    outputs = {"points": Output(Table, "landmarks: names; points: [x, y, z] or null; views; rms_px")}
    params = {
        "min_visibility": Param(float, 0.5, range=(0.0, 1.0), doc="a view's landmark counts from this visibility"),
        "max_error": Param(float, 30.0, range=(0.5, None), doc="reprojection error (pixels) beyond which a view is dropped"),
    }

    def run(self, keypoints, cameras, *, min_visibility, max_error):
        from .keypoints import triangulate

        try:
            names, per_cam = keypoints["landmarks"], keypoints["cameras"]
        except (KeyError, TypeError):
            raise NodeError("skeleton.keypoints: 'keypoints' is not key.person's table (landmarks, cameras)") from None
        unknown = sorted(set(per_cam) - set(cameras.names))
        if unknown:
            raise NodeError(f"skeleton.keypoints: cameras {unknown} of the keypoints are not in the rig "
                            f"{cameras.names}")
        pts = {n: (None if not c["found"] else c["points"]) for n, c in per_cam.items()}
        xyz, views, rms = triangulate(pts, cameras, min_visibility, max_error)
        if len(xyz) and not np.isfinite(xyz).any():
            self.log.warning("skeleton.keypoints: no landmark is seen in two views that agree")
        return {"points": {"landmarks": list(names),
                           "points": [None if not np.isfinite(x).all() else np.round(x, 5).tolist() for x in xyz],
                           "views": views.tolist(),
                           "rms_px": [None if not np.isfinite(r) else round(float(r), 2) for r in rms]}}


# ---------------------------------------------------------------- sequences
def dynamic_mesh(node: Node, meshes, sequence, segment: int):
    """(frames (F, V, 3), faces, frame numbers, segment range, segment count) of the chosen constant-
    connectivity run of the connected input (per-frame meshes or a mesh sequence)."""
    if (meshes is None) == (sequence is None):
        raise NodeError(f"{node.type_name}: connect exactly one of 'meshes' and 'sequence'")
    seq = list(sequence if sequence is not None else meshes)
    if not seq:
        raise NodeError(f"{node.type_name}: no meshes")
    numbers = list(node.frames) if meshes is not None and len(node.frames) == len(seq) else [
        int(m.metadata.get("frame", i)) for i, m in enumerate(seq)]
    runs = sequence_segments(seq)
    if segment >= len(runs):
        raise NodeError(f"{node.type_name}: param 'segment' is {segment} but the input has {len(runs)} segment(s)")
    start, stop = runs[segment] if segment >= 0 else max(runs, key=lambda r: r[1] - r[0])
    if stop - start < 2:
        raise NodeError(f"{node.type_name}: the longest run of meshes with one connectivity has {stop - start} frame; "
                        "a skeleton from motion needs a tracked sequence (track) of at least 2 frames")
    faces = np.asarray(seq[start].faces, np.int64)
    for i in range(start, stop):
        if len(seq[i].vertices) != len(seq[start].vertices):
            raise NodeError(f"{node.type_name}: frame {numbers[i]} has {len(seq[i].vertices)} vertices, frame {numbers[start]} of its "
                            f"segment {len(seq[start].vertices)}")
    frames = np.stack([np.asarray(m.vertices, np.float64) for m in seq[start:stop]])
    if not np.all(np.isfinite(frames)):
        raise NodeError(f"{node.type_name}: non-finite vertex positions in frames {numbers[start]}..{numbers[stop - 1]}")
    return frames, faces, numbers[start:stop], (start, stop), len(runs)


class SkeletonizeSequence(Node):
    """A skeleton from the motion of a dynamic mesh (a tracked sequence: constant connectivity): the rest
    mesh (first frame of the segment) cut into surface patches, patches merged greedily where one rigid
    motion per frame explains both, parts then removed one at a time where their neighbours' motions explain
    their vertices (a part straddling a joint splits between both sides), vertices moved to the part that
    fits their trajectory; joints where adjacent parts' motions agree (least squares, nearest the border
    along a hinge's axis), a maximum-border spanning tree rooted at the largest part. Output: rest joints,
    hard weights (the parts) and each bone's Kabsch motion per frame."""

    type_name = "skeletonize.sequence"
    version = 1
    per = "sequence"
    inputs = {
        "meshes": Input(Mesh, optional=True, doc="per-frame meshes with one connectivity (arrive as a list)"),
        "sequence": Input(MeshSequence, optional=True, doc="or a mesh sequence (track's output)"),
    }
    outputs = {
        "skeleton": Output(Skeleton, "rest joints, parts as hard weights, bone motions per frame"),
        "rest": Output(Mesh, "the rest mesh (first frame of the segment)"),
        "report": Output(Table, "bones, per-bone rigid residual, joint mismatch, segment, seconds"),
    }
    params = {
        "bones": Param(int, 0, range=(0, 256), doc="number of bones; 0 = automatic (tolerance)"),
        "tolerance": Param(float, 0.005, range=(1e-5, 1.0), doc="automatic: keep parts whose vertices another part's motion misses by more (rms, x bbox diagonal)"),
        "patches": Param(int, 200, range=(2, 5000), doc="initial surface patches"),
        "segment": Param(int, -1, range=(-1, None), doc="which constant-connectivity segment; -1 = the longest"),
    }

    def run(self, meshes=None, sequence=None, *, bones, tolerance, patches, segment):
        import trimesh

        from .motion import build_rig, rigid_parts

        frames, faces, numbers, (start, stop), nseg = dynamic_mesh(self, meshes, sequence, segment)
        if bones > frames.shape[1]:
            raise NodeError(f"skeletonize.sequence: {bones} bones for {frames.shape[1]} vertices")
        t0 = time.perf_counter()
        parts = rigid_parts(frames[0], frames, faces, bones=bones, tolerance=tolerance, patch_count=patches, log=self.log.info)
        rig = build_rig(frames[0], faces, parts)
        seconds = time.perf_counter() - t0
        self.log.info("skeletonize.sequence: %d bones, joints and tree in %.1f s", len(rig.parents), seconds)
        weights = np.zeros((frames.shape[1], len(rig.parents)))
        weights[np.arange(frames.shape[1]), rig.labels] = 1.0
        sk = SkeletonData(rig.joints, rig.parents, rig.names, weights, rig.rotations, rig.translations, numbers)
        diag = float(np.linalg.norm(np.ptp(frames[0], axis=0)))
        report = {
            "bones": len(rig.parents), "frames": len(numbers), "vertices": int(frames.shape[1]),
            "segment": {"first_frame": int(numbers[0]), "last_frame": int(numbers[-1]), "count": nseg},
            "vertices_per_bone": np.bincount(rig.labels, minlength=len(rig.parents)).tolist(),
            "rigid_residual_rms": rig.residual.tolist(), "joint_mismatch_rms": rig.joint_error.tolist(),
            "diagonal": diag, "seconds": seconds,
        }
        rest = trimesh.Trimesh(frames[0], faces, process=False)
        return {"skeleton": sk, "rest": rest, "report": report}


class SkeletonizeHumanoid(Node):
    """The named humanoid template on a tracked segment (humanoid.py ``bind_humanoid``): fitted to a frame of the
    segment where it fits (legs apart preferred), each vertex on its nearest bone, each joint's part moving
    rigidly with the sequence, each joint carried to every frame by the surface around it (the motion skin's
    ``hold`` keeps the posed joints near), rest = the segment's first frame; give it to
    ``skin`` (lengths: fixed: rotation-only joints, bone lengths constant over the sequence) and
    ``skeleton.export`` (UsdSkel, glTF skin, BVH) for a character with standard (or Mixamo/Unreal/SMPL) names.
    ``lengths``: the bone lengths of another skeleton kept (another segment's fit, so that one character holds
    over a sequence, or a template of your own: skeleton.load), each joint aimed from its parent at where the fit
    put it."""

    type_name = "skeletonize.humanoid"
    version = 4     # 3: wrists, ankles and knees from ``hand`` and ``foot``; 4: the new shoulders, elbows, knees, head,
                    # clavicles, proportions of the segment's stature
    per = "sequence"
    inputs = {
        "meshes": Input(Mesh, optional=True, doc="per-frame meshes with one connectivity (arrive as a list)"),
        "sequence": Input(MeshSequence, optional=True, doc="or a mesh sequence (track's output)"),
        "lengths": Input(Skeleton, optional=True, doc="a skeleton whose bone lengths the fit keeps (another "
                         "segment's, so that they are one over the sequence, or your own), joints named as the "
                         "template's or as a retargeting tool's"),
    }
    outputs = {"skeleton": Output(Skeleton, "the template's joints (no end markers), parts and motion, for skin"),
               "rest": Output(Mesh, "the rest mesh (first frame of the segment)"),
               "report": Output(Table, "sides, bends, bone lengths, vertices per joint, segment")}
    params = {
        "resolution": Param(int, 128, range=(16, 512), doc="voxels along the first frame's longest side"),
        "up": Param(list, [0.0, 0.0, 1.0], item=float, length=3, doc="world up (the world frame's +Z)"),
        "naming": Param(str, "volcap", choices=("volcap",) + TOOLS, doc="joint names: ours, or a retargeting tool's"),
        "segment": Param(int, -1, range=(-1, None), doc="which constant-connectivity segment; -1 = the longest"),
        "hand": HAND_PARAM,
        "foot": FOOT_PARAM,
    }

    def run(self, meshes=None, sequence=None, lengths=None, *, resolution, up, naming, segment, hand, foot):
        import trimesh

        from .humanoid import bind_humanoid, retarget_names, skeleton_lengths

        frames, faces, numbers, _, nseg = dynamic_mesh(self, meshes, sequence, segment)
        given = None
        if lengths is not None:
            given = skeleton_lengths(lengths.joints, lengths.parents, lengths.names)
            if not given:
                raise NodeError(f"skeletonize.humanoid: input 'lengths' names none of the template's joints "
                                f"({', '.join(lengths.names[:4])}, ...): give a template rig's skeleton")
        joints, parents, names, weights, rot, tr, report = bind_humanoid(frames, faces, resolution, up, lengths=given,
                                                                         hand=hand, foot=foot)
        if given:
            report["lengths_given"] = sorted(given)
        if naming != "volcap":
            table = retarget_names(naming)
            names = [table.get(n, n) for n in names]
        report.update(names=names, segment={"first_frame": int(numbers[0]), "last_frame": int(numbers[-1]),
                                             "count": nseg}, fitted_on_frame=int(numbers[report.pop("fitted_on_index")]))
        sk = SkeletonData(joints, parents, names, weights, rot, tr, numbers)
        return {"skeleton": sk, "rest": trimesh.Trimesh(frames[0], faces, process=False), "report": report}


class Skin(Node):
    """Linear-blend-skinning weights and bone motions fitted to a dynamic mesh (SSDR, Le & Deng 2012), from
    skeletonize.sequence's skeleton: at most ``influences`` weights per vertex, smooth where the motion
    leaves them open; ``lengths: fixed`` keeps the skeleton a tree of rotation-only joints (bone lengths
    never change; the rest joints and the rest shape are refined), ``free`` lets every bone move rigidly on
    its own as Dem Bones does; a bone that ends up skinning no vertex is merged into its parent (with ``pivots``
    off, the given skeleton's tree is kept whole and such bones are reported) and a rest joint is never moved out
    of the body. With ``pivots`` off (a given skeleton, skeletonize.humanoid) ``hold`` keeps each posed joint near
    where its input motion takes it (the fit's joint carried by the surface around it): on child_rope the LBS fit
    alone put 17-22 % of the (frame, joint) pairs more than 2 cm outside the tracked body, wrists up to 19 cm.
    ``twist`` keeps each joint's turn about its own bone against its parent within ``twist_range`` (the vertices
    alone, following what slides over the body, twisted child_rope's elbows and spine half round).
    Stops when an iteration improves the error by less than ``tol``; logs each iteration. Reports the LBS
    reconstruction error per frame, the iterations used and the posed joints outside the tracked body."""

    type_name = "skin"
    version = 2
    per = "sequence"
    inputs = {
        "meshes": Input(Mesh, optional=True, doc="per-frame meshes with one connectivity (arrive as a list)"),
        "sequence": Input(MeshSequence, optional=True, doc="or a mesh sequence (track's output)"),
        "skeleton": Input(Skeleton, doc="skeletonize.sequence's skeleton (parts, motions) of the same input"),
    }
    outputs = {
        "skeleton": Output(Skeleton, "rest joints, LBS weights, bone motions per frame"),
        "rest": Output(Mesh, "the rest shape the weights skin"),
        "error": Output(Table, "LBS reconstruction error per frame (rms, max; metres and % of the bbox diagonal), "
                        "iterations, removed bones"),
    }
    params = {
        "influences": Param(int, 4, range=(1, 8), doc="most bones per vertex"),
        "iterations": Param(int, 15, range=(1, 100), doc="most weights / motion alternations (stops earlier when converged)"),
        "tol": Param(float, 1e-3, range=(0.0, 1.0), doc="converged: an iteration lowers the LBS rms by less than this "
                     "share, or by less than 1e-5 of the bounding-box diagonal (10 um per metre); 0: every iteration"),
        "smooth": Param(float, 1e-6, range=(0.0, 1.0), doc="Laplacian weight smoothing (x frames x diagonal^2)"),
        "lengths": Param(str, "fixed", choices=("fixed", "free"), doc="fixed: rotation-only joints; free: rigid bones (Dem Bones)"),
        "rest_fit": Param(bool, True, doc="refit the rest shape (a posed first frame is no exact LBS rest)"),
        "pivots": Param(bool, True, doc="move the rest joints to fit the motion (never out of the body); off: the "
                        "joints stay where the skeleton put them (a fitted template, skeletonize.humanoid)"),
        "rest_pose": Param(str, "captured", choices=REST_POSES, doc="the rest (bind) pose: the segment's first frame "
                           "as captured, or a T or A pose (arms out or 45 deg down, legs and spine straight along "
                           "the world's +Z; a template rig: skeletonize.humanoid); the motion is the same"),
        "rest_rounds": Param(int, 6, range=(0, 50), doc="T or A rest pose: rounds of the fit carried on about it (bone "
                             "motions, weights, rest shape); 0: the captured rig's motion exactly, re-expressed"),
        "hold": Param(float, 0.3, range=(0.0, 100.0), doc="lengths fixed, pivots off (a given skeleton): keep each "
                      "posed joint near where the input skeleton's motion takes it (skeletonize.humanoid: where the "
                      "surface around the fitted joint goes) against the LBS error; the joints together weigh this "
                      "many times the vertices; 0: the vertices alone"),
        "twist": Param(float, 0.3, range=(0.0, 1000.0), doc="lengths fixed: how strongly each joint's twist against "
                       "its parent (its turn about its own bone) is kept within twist_range: a radian beyond it weighs "
                       "this many times the bone's vertices each a twentieth of the body's size off; 0: the vertices "
                       "alone (on child_rope they twisted 8-20 % of the (frame, joint) pairs more than 90 degrees "
                       "against their parents, elbows and spine flipping half round from one frame to the next)"),
        "twist_range": Param(float, 45.0, range=(0.0, 180.0), doc="degrees of twist against the parent that cost nothing"),
        "helpers": Param(int, 0, range=(0, 256), doc="helper bones added last: free rigid bones (as Dem Bones moves "
                         "them), each under the rig's bone whose vertices' LBS error it takes (loose clothes, soft "
                         "tissue), named helper_<host>_<k>; the rig's own bones keep their rest joints and lengths "
                         "(their motion is refitted beside the helpers, with hold and twist as above): a retargeting "
                         "tool reads those, and the BVH holds them alone; 0: none"),
        "segment": Param(int, -1, range=(-1, None), doc="which constant-connectivity segment; -1 = the longest"),
    }

    def run(self, skeleton, meshes=None, sequence=None, *, influences, iterations, tol, smooth, lengths, rest_fit, pivots,
            rest_pose, rest_rounds, hold, twist, twist_range, helpers, segment):
        import trimesh

        from .motion import Rig, Trajectories
        from .skinning import fit_skin

        frames, faces, numbers, _, _ = dynamic_mesh(self, meshes, sequence, segment)
        if skeleton.weights is None or skeleton.rotations is None:
            raise NodeError("skin: input 'skeleton' has no parts or motion: connect skeletonize.sequence's skeleton")
        if skeleton.weights.shape[0] != frames.shape[1]:
            raise NodeError(f"skin: the skeleton's weights cover {skeleton.weights.shape[0]} vertices, the meshes have "
                            f"{frames.shape[1]}: connect the same sequence (and segment) as skeletonize.sequence")
        if skeleton.rotations.shape[0] != frames.shape[0] or (skeleton.frames and list(skeleton.frames) != numbers):
            raise NodeError(f"skin: the skeleton's motion has {skeleton.rotations.shape[0]} frames, the segment "
                            f"{frames.shape[0]}: connect the same sequence (and segment) as skeletonize.sequence")
        t0 = time.perf_counter()
        labels = np.argmax(skeleton.weights, axis=1)
        rig = Rig(np.asarray(skeleton.joints, np.float64), list(skeleton.parents), list(skeleton.names),
                  np.asarray(skeleton.rotations, np.float64), np.asarray(skeleton.translations, np.float64), labels,
                  np.zeros(len(skeleton.parents)), np.zeros(len(skeleton.parents)))
        traj = Trajectories(frames[0], frames)
        fit = fit_skin(traj, faces, rig, influences=influences, iterations=iterations, smooth=smooth,
                       fixed_lengths=lengths == "fixed", rest=rest_fit, pivots=pivots, tol=tol, merge=pivots,
                       hold=0.0 if pivots else hold,
                       targets=np.einsum("fjab,jb->fja", rig.rotations, rig.joints) + rig.translations,
                       twist=twist, twist_range=np.radians(twist_range), log=self.log.info, progress=self.progress)
        names = [skeleton.names[b] for b in fit.kept]
        if rest_pose != "captured":
            targets = np.einsum("fjab,jb->fja", rig.rotations, rig.joints) + rig.translations
            fit = self._reposed(traj.with_rest(fit.rest), faces, fit, names, rest_pose, lengths, influences, smooth,
                                rest_rounds, 0.0 if pivots else hold, targets[:, fit.kept], twist, np.radians(twist_range))
        rig_rmse = float(np.sqrt((fit.rmse ** 2).mean()))
        if helpers:
            poses = "free" if lengths != "fixed" else dict(
                hold=0.0 if pivots else hold, twist=twist, twist_range=np.radians(twist_range),
                targets=(np.einsum("fjab,jb->fja", rig.rotations, rig.joints) + rig.translations)[:, fit.kept])
            fit, names = self._helpers(traj.with_rest(fit.rest), faces, fit, names, helpers, influences, smooth,
                                       iterations, tol, rest_fit, poses)
        seconds = time.perf_counter() - t0
        diag = float(np.linalg.norm(np.ptp(frames[0], axis=0)))
        removed = [n for b, n in enumerate(skeleton.names) if b not in set(fit.kept)]
        if removed:
            self.log.warning("skin: bone(s) %s skin no vertex (no vertex has them as its strongest influence): merged "
                             "into their parents", ", ".join(removed))
        sk = SkeletonData(fit.joints, fit.parents, names, fit.weights, fit.rotations, fit.translations, numbers)
        table = error_table(fit, numbers, diag, seconds, lengths, names)
        table["joints_outside"] = joints_outside(frames, faces, fit, names, numbers)
        table["twist"] = twist_table(fit, names, numbers, twist_range)
        family = family_weights(fit.weights, fit.parents, names)      # a helper's weights count for its host too
        weightless = [names[b] for b in np.flatnonzero(np.bincount(np.argmax(family, axis=1), minlength=len(names)) == 0)
                      if not is_helper(names[b])]
        if weightless:
            self.log.warning("skin: bone(s) %s are the strongest influence of no vertex: kept (pivots: false, the "
                             "skeleton's joints are given), moving with their neighbours", ", ".join(weightless))
        table.update(removed=removed, weightless=weightless, pivot_moves_refused=fit.refused)
        if helpers:
            table["helpers"] = {"bones": sum(map(is_helper, names)), "asked": helpers, "rig_rmse": rig_rmse,
                                "rmse": table["rmse"]}
        return {"skeleton": sk, "rest": trimesh.Trimesh(fit.rest, faces, process=False), "error": table}

    def _helpers(self, traj, faces, fit, names, count, influences, smooth, iterations, tol, rest_fit, poses):
        """``fit`` with ``count`` helper bones (skinning.fit_helpers), its errors measured again; and the names."""
        import dataclasses

        from .skinning import errors, fit_helpers

        rest, w, rot, tr, joints, parents, names, history = fit_helpers(
            traj, faces, fit.weights, fit.rotations, fit.translations, fit.joints, fit.parents, names, count,
            influences=influences, smooth=smooth, iterations=iterations, tol=tol, rest_fit=rest_fit, rig_poses=poses,
            log=self.log.info, progress=self.progress)
        rmse, mx = errors(traj.with_rest(rest), w, rot, tr)
        self.log.info("skin: %d helper bones: LBS rms %.4g -> %.4g mm", len(parents) - len(fit.parents),
                      1000 * np.sqrt((fit.rmse ** 2).mean()), 1000 * np.sqrt((rmse ** 2).mean()))
        return dataclasses.replace(fit, rest=rest, weights=w, rotations=rot, translations=tr, joints=joints,
                                   parents=parents, rmse=rmse, max_error=mx, history=fit.history + history), names

    def _reposed(self, traj, faces, fit, names, pose, lengths, influences, smooth, refits, hold, targets, twist,
                 twist_range):
        """``fit`` about a T or A rest pose (humanoid.rest_pose, skinning.repose), its errors measured again."""
        import dataclasses

        from .humanoid import rest_pose
        from .skinning import errors, repose

        if lengths != "fixed":
            raise NodeError(f"skin: rest_pose {pose} needs lengths: fixed (a T or A pose turns rotation-only joints)")
        try:
            turns, joints = rest_pose(fit.joints, fit.parents, names, pose)
        except ValueError as exc:
            raise NodeError(f"skin: rest_pose {pose}: {exc}") from None
        traj, weights, rot, tr = repose(traj, faces, fit.parents, fit.weights, fit.rotations, fit.translations, fit.joints,
                                        turns, joints, influences=influences, smooth=smooth, refits=refits, hold=hold,
                                        targets=targets, twist=twist, twist_range=twist_range)
        rmse, mx = errors(traj, weights, rot, tr)
        self.log.info("skin: rest pose %s: LBS rms %.4g -> %.4g mm", pose, 1000 * np.sqrt((fit.rmse ** 2).mean()),
                      1000 * np.sqrt((rmse ** 2).mean()))
        return dataclasses.replace(fit, rest=traj.rest, weights=weights, rotations=rot, translations=tr, joints=joints,
                                   rmse=rmse, max_error=mx)


def twist_table(fit, names, numbers, twist_range: float) -> dict:
    """Each joint's twist against its parent over the frames (skinning.twists, degrees): the share of (frame, joint)
    pairs beyond ``twist_range`` and beyond 90 degrees, the 95th percentile, the worst (joint, frame), and the share
    of (frame, joint) steps that change the twist by more than 45 degrees from one frame to the next."""
    from .skinning import bone_axes, twists

    own = len(fit.parents) - sum(map(is_helper, names))     # the rig's own joints first; helpers (free bones) after
    parents = list(fit.parents[:own])
    tw = np.degrees(twists(fit.rotations[:, :own], parents, bone_axes(fit.joints[:own], parents)))
    kids = [k for k, p in enumerate(parents) if p >= 0]
    if not kids or not len(tw):
        return {"pairs": 0}
    a = np.abs(tw[:, kids])
    f, k = np.unravel_index(int(np.argmax(a)), a.shape)
    step = np.abs(np.angle(np.exp(1j * np.radians(np.diff(tw[:, kids], axis=0)))))
    return {"pairs": int(a.size), "range_deg": float(twist_range), "beyond_range": round(float(np.mean(a > twist_range)), 4),
            "over_90": round(float(np.mean(a > 90)), 4), "p95_deg": round(float(np.percentile(a, 95)), 1),
            "max_deg": round(float(a.max()), 1), "worst_joint": names[kids[k]], "worst_frame": int(numbers[f]),
            "jumps_over_45": round(float(np.mean(step > np.radians(45))), 4) if len(step) else 0.0}


def bone_lengths(joints, parents, rotations, translations) -> np.ndarray:
    """(F, J) distance between each joint's pivot and its parent's over frames (0 for the root)."""
    pivots = np.einsum("fjab,jb->fja", rotations, joints) + translations
    out = np.zeros(pivots.shape[:2])
    for j, p in enumerate(parents):
        if p >= 0:
            own = pivots[:, j]
            # where the parent's motion takes j's pivot: equal to own for rotation-only joints
            out[:, j] = np.linalg.norm(own - pivots[:, p], axis=1)
    return out


def joints_outside(frames, faces, fit, names, numbers) -> dict:
    """Posed joints outside the tracked body: per (frame, joint) how far the joint lies outside the frame's mesh
    (skinning.posed_clearance), against its limit (the thickness of the thicker bone meeting there, in the rest
    shape: skinning.joint_clearance). Counts beyond the limit and beyond 2 cm, the worst, and per joint its worst.
    Helper bones are no joints of the body: a host's thickness counts its helpers' vertices (family_weights), and
    their pivots (the centre of a patch of surface) are counted apart, beyond 2 cm (``helpers``)."""
    from .skinning import family_weights, joint_clearance, posed_clearance

    own = len(fit.parents) - sum(map(is_helper, names))
    rot, tr, joints, parents = fit.rotations[:, :own], fit.translations[:, :own], fit.joints[:own], fit.parents[:own]
    _, limit = joint_clearance(fit.rest, faces, family_weights(fit.weights, fit.parents, names)[:, :own], joints,
                               parents, lazy=True)
    out = posed_clearance(frames, faces, rot, tr, joints, np.minimum(limit, 0.02))
    out = np.where(out > np.minimum(limit, 0.02), out, 0.0)      # nearer: inside or not, within both bounds
    f, j = np.unravel_index(int(np.argmax(out)), out.shape)
    table = {"beyond_limit": int((out > limit).sum()), "beyond_2cm": int((out > 0.02).sum()), "pairs": int(out.size),
             "worst": float(out.max()), "worst_joint": names[j], "worst_frame": int(numbers[f]),
             "worst_by_joint": {n: float(x) for n, x in zip(names, out.max(0))},
             "limit": {n: float(x) for n, x in zip(names, limit)}}
    if own < len(names):
        near = np.full(len(names) - own, 0.02)
        hp = posed_clearance(frames, faces, fit.rotations[:, own:], fit.translations[:, own:], fit.joints[own:], near)
        table["helpers"] = {"pairs": int(hp.size), "beyond_2cm": int((hp > 0.02).sum()), "worst": float(hp.max())}
    return table


def error_table(fit, numbers, diag, seconds, lengths, names=()) -> dict:
    """The skin node's error Table: totals, and per frame (frame, rmse, max) in metres and % of diagonal; the bone
    lengths' spread over the rig's own bones (helper bones, named so in ``names``, are free)."""
    total = float(np.sqrt((fit.rmse ** 2).mean()))
    bl = bone_lengths(fit.joints, fit.parents, fit.rotations, fit.translations)
    child = [j for j, p in enumerate(fit.parents) if p >= 0 and not (names and is_helper(names[j]))]
    spread = float(np.max((bl[:, child].max(0) - bl[:, child].min(0)) / np.maximum(bl[:, child].mean(0), 1e-12))) if child else 0.0
    nnz = (fit.weights > 0).sum(1)
    return {
        "bones": len(fit.parents), "frames": len(numbers), "lengths": lengths, "diagonal": diag,
        "rmse": total, "rmse_percent": 100 * total / diag, "max": float(fit.max_error.max()),
        "max_percent": 100 * float(fit.max_error.max()) / diag,
        "bone_length_spread": spread, "influences_max": int(nnz.max()), "influences_mean": float(nnz.mean()),
        "iterations": len(fit.history), "history": [float(h) for h in fit.history], "seconds": seconds,
        "residual": {"rmse": [float(x) for x in fit.rmse], "max": [float(x) for x in fit.max_error]},
        "timeline": {"frame": [int(f) for f in numbers], "rmse": [float(x) for x in fit.rmse],
                     "max": [float(x) for x in fit.max_error],
                     "rmse_percent": [float(100 * x / diag) for x in fit.rmse]},
    }


class Export(Node):
    """A skinned, animated rig as files: USD (UsdSkel Skeleton + Animation + bound Mesh with joint
    indices/weights, time codes = frame numbers), glTF 2.0 binary (skin, inverse bind matrices, a translation +
    rotation channel per joint) and/or BVH (the motion: hierarchy, offsets, ZXY rotations per frame). Joint
    transforms at frame k reproduce the skinned mesh. Given the tracked frames the rig was fitted to, it reports
    the LBS error per frame, and with ``correctives`` keeps what LBS misses as K corrective blend shapes
    (correctives.py: fitted in the posed space, towards a per-frame ``goal``) with their weights per frame: glTF
    morph targets + a weights channel, UsdSkel BlendShapes + blendShapeWeights."""

    type_name = "skeleton.export"
    version = 3     # 3: correctives fitted towards ``goal``
    per = "sequence"
    publishes = True
    inputs = {
        "skeleton": Input(Skeleton, doc="skin's skeleton (weights and motion)"),
        "rest": Input(Mesh, doc="the rest shape the weights belong to (skin's rest)"),
        "meshes": Input(Mesh, optional=True, doc="the tracked frames skin fitted (its input; arrive as a list): "
                        "the error report and the corrective shapes"),
        "sequence": Input(MeshSequence, optional=True, doc="or skin's mesh sequence"),
    }
    outputs = {"files": Files,
               "report": Output(Table, "with the tracked frames: per file the LBS error per frame (rms, max; metres) "
                                "with 0 and with the corrective shapes; with a goal, the frames still beyond it, each "
                                "with its worst vertex and that vertex's blended transform's smallest singular value "
                                "(near 0: two of its bones turned apart, where LBS collapses and no shape can reach)")}
    params = {
        "name": Param(str, "rig", doc="file name stem"),
        "formats": Param(str, "usd,gltf", doc="which files, comma-separated: usd, gltf, bvh (the motion alone, "
                         "+Y up, metres: rotation-only rigs, i.e. skin's lengths: fixed; without skin's helper bones)"),
        "fps": FPS_PARAM,
        "influences": Param(int, 4, range=(1, 8), doc="joint influences per vertex in USD (glTF: 4)"),
        "correctives": Param(int, 0, range=(0, 1024), doc="corrective blend shapes (glTF morph targets, UsdSkel "
                             "BlendShapes) fitted to the tracked frames; 0 = none; at least the frame count: exact"),
        "goal": Param(list, [0.01, 0.05], item=float, length=2, range=(0.0, 1.0), doc="with correctives: the error each frame should "
                      "stay within, rms and max, as shares of the subject's height (the tracked frames' extent along "
                      "+Z, 95th percentile); frames and vertices beyond it weigh more in up to 5 further rounds of the "
                      "fit, the round with the most frames within kept; a 0: the least-squares fit alone"),
        "frame_shapes": Param(int, 0, range=(0, 1024), doc="with correctives and a goal: up to this many frames the fit "
                              "leaves beyond the goal (the farthest first) get one more shape each, what is left of "
                              "that frame, weighing 1 in it and 0 in every other (the report lists them; with "
                              "correctives >= the frame count every frame is exact: none)"),
    }

    def run(self, skeleton, rest, meshes=None, sequence=None, *, name, formats, fps, influences, correctives, goal,
            frame_shapes):
        from . import formats as fmt

        formats = [f.strip() for f in formats.split(",") if f.strip()]
        unknown = sorted(set(formats) - {"usd", "gltf", "bvh"})
        if unknown or not formats:
            raise NodeError(f"skeleton.export: formats {unknown or formats}: give a comma-separated list of usd, gltf, bvh")

        if skeleton.weights is None or skeleton.rotations is None:
            raise NodeError("skeleton.export: input 'skeleton' has no weights or motion: connect skin's skeleton")
        if skeleton.weights.shape[0] != len(rest.vertices):
            raise NodeError(f"skeleton.export: {skeleton.weights.shape[0]} weighted vertices but the rest mesh has "
                            f"{len(rest.vertices)}: connect skin's rest and skeleton")
        frames = list(skeleton.frames) if skeleton.frames else list(range(skeleton.rotations.shape[0]))
        rig = dict(vertices=np.asarray(rest.vertices), faces=np.asarray(rest.faces), joints=np.asarray(skeleton.joints),
                   parents=list(skeleton.parents), names=list(skeleton.names), weights=np.asarray(skeleton.weights),
                   rotations=np.asarray(skeleton.rotations), translations=np.asarray(skeleton.translations),
                   frames=frames, fps=fps)
        targets = None if meshes is None and sequence is None else self._tracked(meshes, sequence, frames, rig)
        if correctives and targets is None:
            raise NodeError("skeleton.export: correctives need the tracked frames: connect skin's 'sequence' (or "
                            "'meshes') to this node's")
        if frame_shapes and not (correctives and min(goal) > 0):
            raise NodeError("skeleton.export: param 'frame_shapes' adds shapes for frames beyond the goal: it needs "
                            "'correctives' > 0 and a 'goal' without a 0")
        fits, report = {}, {}

        def fitted(k: int, file: str):
            """The corrective shapes (and errors) for the LBS a file with k influences per vertex skins."""
            if targets is None:
                return None
            if k not in fits:
                from .correctives import fit_correctives

                idx, w = fmt.sparse_influences(rig["weights"], k)
                from .humanoid import body_stature

                height = body_stature(targets)
                aim = (goal[0] * height, goal[1] * height) if min(goal) > 0 else None
                fits[k] = fit_correctives(rig["vertices"], idx, w, rig["rotations"], rig["translations"], targets,
                                          correctives, goal=aim, frame_shapes=frame_shapes)
            c = fits[k]
            report[file] = c.table(frames)
            if c.own:
                self.log.info("skeleton.export: %s: frame(s) %s got a corrective shape of their own", file,
                              ", ".join(str(n) for n in report[file]["frame_shapes"]))
            self.log.info("skeleton.export: %s: LBS rms %.3g mm (max %.3g) -> %d corrective shape(s): rms %.3g mm "
                          "(max %.3g)", file, 1000 * report[file]["lbs_rms_total"], 1000 * c.lbs_max.max(),
                          len(c.shapes), 1000 * report[file]["corrected_rms_total"], 1000 * c.max.max())
            return c

        files = {}
        if "usd" in formats:
            files[f"{name}.usd"] = fmt.usd_bytes(influences=influences, **rig, correctives=fitted(
                max(1, min(influences, len(rig["parents"]))), f"{name}.usd"))
        if "gltf" in formats:
            files[f"{name}.glb"] = fmt.gltf_bytes(**rig, correctives=fitted(min(4, len(rig["parents"])), f"{name}.glb"))
        if "bvh" in formats:      # the rig's own joints (helper bones are free leaves that skin this mesh only)
            keep = ([j for j, n in enumerate(rig["names"]) if not is_helper(n)] if rig["names"]
                    else list(range(len(rig["parents"]))))
            at = {j: i for i, j in enumerate(keep)}
            under = [rig["names"][j] for j in keep if rig["parents"][j] >= 0 and rig["parents"][j] not in at]
            if under:
                raise NodeError(f"skeleton.export: joint(s) {', '.join(under)} hang under a helper bone (helper_...): "
                                "a helper is a leaf; rename the joints or their parents")
            bones = dict(rig, joints=rig["joints"][keep], parents=[at.get(rig["parents"][j], -1) for j in keep],
                         names=[rig["names"][j] for j in keep] if rig["names"] else [],
                         rotations=rig["rotations"][:, keep], translations=rig["translations"][:, keep])
            try:
                files[f"{name}.bvh"] = fmt.bvh_text(**bones).encode()
            except ValueError as exc:
                raise NodeError(f"skeleton.export: {exc}") from None
        if report:
            report = {"frames": [int(f) for f in frames], "files": report}
        return {"files": files, "report": report}

    def _tracked(self, meshes, sequence, frames, rig) -> np.ndarray:
        """(F, V, 3) the tracked frames of the connected input that the rig's frames are (its segment)."""
        seq = list(sequence if sequence is not None else meshes or [])
        for segment in range(len(sequence_segments(seq)) if seq else 1):
            try:
                points, _, numbers, _, _ = dynamic_mesh(self, meshes, sequence, segment)
            except NodeError:           # a segment too short to rig, or no meshes: not the rig's
                continue
            if list(numbers) == list(frames) and points.shape[1] == len(rig["vertices"]):
                return points
        raise NodeError(f"skeleton.export: no segment of the tracked frames is the rig's (frames {frames[0]}..{frames[-1]}, "
                        f"{len(rig['vertices'])} vertices): connect the sequence skin fitted")
