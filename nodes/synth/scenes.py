"""Procedural scenes with known ground truth for the ``synth`` node (metres, +Z up, floor at z = 0).

    sphere   a checkered ball above the floor (tests)
    cup      a striped cup: a closed, watertight surface of revolution with a real concavity
    figure   an articulated figure (torso, head, arms, legs): a smooth union of capsules meshed once by
             marching cubes, then posed per frame by linear blend skinning, so the topology is constant and
             vertex i is the same body point in every frame. Skeleton joints and LBS weights come with it.
             It walks in place, turning slowly.
    touch    the same figure lowering its arms onto its hips and holding them there while it twists and sways
             (24-frame cycle): a limb touching the body, where a tracker may slide the surface sideways

Every scene carries its surface pattern: texture coordinates are rest-pose positions (the pattern moves
with the body), one material per face (layout: nodes.common.raster.MATERIAL_FLOATS).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

from typing import TYPE_CHECKING

import numpy as np

from nodes.common.raster import CHECKER, PLAIN, STRIPES
from nodes.common.types import SkeletonData

if TYPE_CHECKING:
    import trimesh

SCENES = ("sphere", "cup", "figure", "touch")


def material(color_a, color_b=(0, 0, 0), pattern=PLAIN, period=1.0, lit=True, shadow=False) -> list[float]:
    """One row of the material table read by kernel ``shade``."""
    return [*color_a, *color_b, pattern, period, float(lit), float(shadow), 0.0, 0.0]


@dataclass
class Scene:
    mesh: trimesh.Trimesh            # ground truth surface for this frame
    texcoords: np.ndarray            # (V, 3) rest-pose positions: where the procedural pattern is evaluated
    face_material: np.ndarray        # (F,) int
    materials: np.ndarray            # (M, 12) float
    center: np.ndarray               # fixed over frames: centre and radius of a ball holding every frame
    radius: float
    skeleton: SkeletonData | None = None


def build(name: str, frame: int = 0) -> Scene:
    """The scene ``name`` posed at ``frame``."""
    if name == "sphere":
        return _sphere()
    if name == "cup":
        return _cup()
    if name in ("figure", "touch"):
        return _figure(frame, "walk" if name == "figure" else "touch")
    raise ValueError(f"unknown scene '{name}'; expected one of {', '.join(SCENES)}")


# ---------------------------------------------------------------- sphere and cup
@lru_cache(maxsize=None)
def _sphere_rest():
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    m.apply_translation([0, 0, 0.6])
    return m


def _sphere() -> Scene:
    m = _sphere_rest().copy()
    mats = np.array([material((0.9, 0.85, 0.2), (0.2, 0.3, 0.8), CHECKER, 0.15)])
    return Scene(m, m.vertices.copy(), np.zeros(len(m.faces), np.int32), mats, np.array([0, 0, 0.6]), 0.5)


def cup_profile(radius=0.35, height=0.45, wall=0.04, bottom=0.05, step=0.015) -> np.ndarray:
    """(r, z) outline of a cup, from the outer bottom centre round the rim to the inner bottom centre,
    resampled every ``step`` so triangles stay small. Both ends lie on the axis: the revolution is closed."""
    corners = np.array([(0, 0), (radius, 0), (radius, height), (radius - wall, height),
                        (radius - wall, bottom), (0, bottom)], float)
    pts = [corners[0]]
    for a, b in zip(corners[:-1], corners[1:]):
        n = max(1, int(math.ceil(np.linalg.norm(b - a) / step)))
        pts += [a + (b - a) * k / n for k in range(1, n + 1)]
    return np.array(pts)


@lru_cache(maxsize=None)
def _cup_rest():
    import trimesh

    m = trimesh.creation.revolve(cup_profile(), sections=96)
    m.merge_vertices()
    return m


def _cup() -> Scene:
    m = _cup_rest().copy()
    mats = np.array([material((0.85, 0.35, 0.2), (0.95, 0.9, 0.75), STRIPES, 0.04)])
    return Scene(m, m.vertices.copy(), np.zeros(len(m.faces), np.int32), mats, np.array([0, 0, 0.225]), 0.45)


# ---------------------------------------------------------------- figure
JOINTS = {  # name: (rest position, parent)
    "pelvis": ((0.0, 0.0, 0.98), None), "chest": ((0.0, 0.0, 1.28), "pelvis"), "neck": ((0.0, 0.0, 1.50), "chest"),
    "head": ((0.0, 0.0, 1.66), "neck"),
    "l_shoulder": ((0.19, 0.0, 1.43), "chest"), "l_elbow": ((0.36, 0.0, 1.20), "l_shoulder"),
    "l_wrist": ((0.50, 0.0, 0.98), "l_elbow"),
    "r_shoulder": ((-0.19, 0.0, 1.43), "chest"), "r_elbow": ((-0.36, 0.0, 1.20), "r_shoulder"),
    "r_wrist": ((-0.50, 0.0, 0.98), "r_elbow"),
    "l_hip": ((0.10, 0.0, 0.92), "pelvis"), "l_knee": ((0.11, 0.0, 0.52), "l_hip"), "l_ankle": ((0.12, 0.0, 0.10), "l_knee"),
    "r_hip": ((-0.10, 0.0, 0.92), "pelvis"), "r_knee": ((-0.11, 0.0, 0.52), "r_hip"), "r_ankle": ((-0.12, 0.0, 0.10), "r_knee"),
}
NAMES = list(JOINTS)
PARENTS = [-1 if p is None else NAMES.index(p) for _, p in JOINTS.values()]
REST = np.array([pos for pos, _ in JOINTS.values()])

SHIRT, SKIN, TROUSERS = 0, 1, 2
# capsules: (joint a, joint b or a point, radius, owning joint for skinning, material)
CAPSULES = [
    ("pelvis", "chest", 0.13, "pelvis", SHIRT), ("chest", "neck", 0.14, "chest", SHIRT),
    ("neck", "head", 0.05, "neck", SKIN), ("head", (0.0, 0.0, 1.72), 0.10, "head", SKIN),
    ("chest", "l_shoulder", 0.07, "chest", SHIRT), ("chest", "r_shoulder", 0.07, "chest", SHIRT),
    ("l_shoulder", "l_elbow", 0.05, "l_shoulder", SHIRT), ("r_shoulder", "r_elbow", 0.05, "r_shoulder", SHIRT),
    ("l_elbow", "l_wrist", 0.04, "l_elbow", SKIN), ("r_elbow", "r_wrist", 0.04, "r_elbow", SKIN),
    ("pelvis", "l_hip", 0.10, "pelvis", TROUSERS), ("pelvis", "r_hip", 0.10, "pelvis", TROUSERS),
    ("l_hip", "l_knee", 0.07, "l_hip", TROUSERS), ("r_hip", "r_knee", 0.07, "r_hip", TROUSERS),
    ("l_knee", "l_ankle", 0.05, "l_knee", TROUSERS), ("r_knee", "r_ankle", 0.05, "r_knee", TROUSERS),
    ("l_ankle", (0.12, -0.13, 0.05), 0.045, "l_ankle", SKIN), ("r_ankle", (-0.12, -0.13, 0.05), 0.045, "r_ankle", SKIN),
]
FIGURE_MATERIALS = np.array([
    material((0.2, 0.45, 0.8), (0.9, 0.9, 0.85), CHECKER, 0.06),     # shirt
    material((0.85, 0.62, 0.5), (0.78, 0.55, 0.45), CHECKER, 0.03),  # skin, faint pattern
    material((0.25, 0.25, 0.3), (0.55, 0.5, 0.35), STRIPES, 0.05),   # trousers
])


def _point(p) -> np.ndarray:
    return REST[NAMES.index(p)] if isinstance(p, str) else np.asarray(p, float)


def capsule_distances(points: np.ndarray) -> np.ndarray:
    """Signed distance (P, C) from points to every capsule of the figure's rest pose."""
    out = np.empty((len(points), len(CAPSULES)))
    for i, (a, b, r, _, _) in enumerate(CAPSULES):
        pa, pb = _point(a), _point(b)
        ab = pb - pa
        t = np.clip((points - pa) @ ab / (ab @ ab), 0, 1)
        out[:, i] = np.linalg.norm(points - (pa + t[:, None] * ab), axis=1) - r
    return out


def _smooth_min(d: np.ndarray, k: float = 0.03) -> np.ndarray:
    """Smooth union of signed distances along axis 1 (exponential smooth minimum, blend width ~k)."""
    m = d.min(axis=1)
    return m - k * np.log(np.exp(-(d - m[:, None]) / k).sum(axis=1))


@lru_cache(maxsize=None)
def figure_rest(voxel: float = 0.015):
    """(mesh, weights (V, J), face material (F,)) of the rest pose; meshed once."""
    import trimesh

    from skimage.measure import marching_cubes

    lo = np.array([-0.68, -0.3, -0.05])
    hi = np.array([0.68, 0.2, 1.86])
    axes = [np.arange(lo[a], hi[a] + voxel, voxel) for a in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    sdf = _smooth_min(capsule_distances(grid)).reshape(len(axes[0]), len(axes[1]), len(axes[2]))
    verts, faces, _, _ = marching_cubes(sdf, level=0.0, spacing=(voxel,) * 3)
    mesh = trimesh.Trimesh(verts + lo, faces, process=True)
    if mesh.volume < 0:
        mesh.invert()
    parts = trimesh.graph.connected_components(mesh.face_adjacency, min_len=1)
    if len(parts) > 1:  # keep the body only (marching cubes can leave specks where capsules just touch)
        keep = max(parts, key=len)
        mesh = mesh.submesh([keep], append=True)
    d = capsule_distances(mesh.vertices)
    soft = np.exp(-(d - d.min(axis=1, keepdims=True)) / 0.015)
    soft[soft < 1e-3] = 0
    weights = np.zeros((len(mesh.vertices), len(NAMES)))
    for i, (_, _, _, owner, _) in enumerate(CAPSULES):
        weights[:, NAMES.index(owner)] += soft[:, i]
    weights /= weights.sum(axis=1, keepdims=True)
    nearest = d[mesh.faces].mean(axis=1).argmin(axis=1)
    face_material = np.array([c[4] for c in CAPSULES], np.int32)[nearest]
    return mesh, weights, face_material


def _rot(axis: str, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


def figure_pose(frame: int, motion: str = "walk") -> tuple[np.ndarray, np.ndarray]:
    """Global joint rotations (J, 3, 3) and positions (J, 3) at ``frame``: ``walk`` in place, turning slowly, or
    ``touch``: the arms lowered against the hips (adducted 0.55 rad: the wrists' capsules meet the hips') and held
    there for half of each 24-frame cycle while the pelvis twists and the chest sways."""
    phase = 2 * math.pi * frame / 24.0
    s = math.sin(phase)
    local = {n: np.eye(3) for n in NAMES}
    if motion == "touch":
        a = 0.55 * min(1.0, 2.0 * (0.5 - 0.5 * math.cos(phase)))     # open at 0, against the hips over 6..18
        local["pelvis"] = _rot("z", 0.2 * math.sin(phase / 2))
        local["chest"] = _rot("x", 0.06 * s)
        local["l_shoulder"], local["r_shoulder"] = _rot("y", a), _rot("y", -a)
        local["l_elbow"] = local["r_elbow"] = _rot("x", -0.2)
        local["l_knee"], local["r_knee"] = _rot("x", 0.15 * max(0.0, s)), _rot("x", 0.15 * max(0.0, -s))
    elif motion == "walk":
        local["pelvis"] = _rot("z", 0.25 * math.sin(phase / 2))
        local["chest"] = _rot("x", 0.08 * s)
        local["l_shoulder"], local["r_shoulder"] = _rot("x", 0.5 * s), _rot("x", -0.5 * s)
        local["l_elbow"] = _rot("x", -0.35 - 0.25 * max(0.0, s))
        local["r_elbow"] = _rot("x", -0.35 - 0.25 * max(0.0, -s))
        local["l_hip"], local["r_hip"] = _rot("x", -0.4 * s), _rot("x", 0.4 * s)
        local["l_knee"] = _rot("x", 0.6 * max(0.0, s))
        local["r_knee"] = _rot("x", 0.6 * max(0.0, -s))
    else:
        raise ValueError(f"unknown figure motion '{motion}'")
    rots = np.empty((len(NAMES), 3, 3))
    pos = np.empty((len(NAMES), 3))
    for j, name in enumerate(NAMES):  # parents come first in JOINTS
        p = PARENTS[j]
        if p < 0:
            rots[j], pos[j] = local[name], REST[j]
        else:
            rots[j] = rots[p] @ local[name]
            pos[j] = pos[p] + rots[p] @ (REST[j] - REST[p])
    return rots, pos


def figure_keypoints(frame: int) -> dict[str, np.ndarray]:
    """Ground truth for curve skeletons: key points of the figure's medial axis (its capsules' axes) at
    ``frame``: the branch points (pelvis, chest), the five extremities (head_top, l/r_wrist, l/r_toe) and the
    joints where the axis bends by more than 15 degrees (shoulders, hips, elbows, knees, ankles when bent)."""
    rots, pos = figure_pose(frame)
    p = {n: pos[i] for i, n in enumerate(NAMES)}

    def posed(x, owner):
        j = NAMES.index(owner)
        return rots[j] @ (np.asarray(x, float) - REST[j]) + pos[j]

    p["head_top"] = posed(CAPSULES[3][1], "head")
    p["l_toe"], p["r_toe"] = posed(CAPSULES[16][1], "l_ankle"), posed(CAPSULES[17][1], "r_ankle")
    keys = {k: p[k] for k in ("pelvis", "chest", "head_top", "l_wrist", "r_wrist", "l_toe", "r_toe")}
    for a, b, c in [("chest", "l_shoulder", "l_elbow"), ("chest", "r_shoulder", "r_elbow"), ("l_shoulder", "l_elbow", "l_wrist"),
                    ("r_shoulder", "r_elbow", "r_wrist"), ("pelvis", "l_hip", "l_knee"), ("pelvis", "r_hip", "r_knee"),
                    ("l_hip", "l_knee", "l_ankle"), ("r_hip", "r_knee", "r_ankle"), ("l_knee", "l_ankle", "l_toe"),
                    ("r_knee", "r_ankle", "r_toe")]:
        u, v = p[b] - p[a], p[c] - p[b]
        if np.degrees(np.arccos(np.clip(u @ v / np.linalg.norm(u) / np.linalg.norm(v), -1, 1))) > 15:
            keys[b] = p[b]
    return keys


def skin(vertices: np.ndarray, weights: np.ndarray, rots: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Linear blend skinning: v' = sum_j w_j (R_j (v - rest_j) + p_j)."""
    per_joint = np.einsum("jab,vjb->vja", rots, vertices[:, None, :] - REST[None]) + pos[None]
    return np.einsum("vj,vja->va", weights, per_joint)


def _figure(frame: int, motion: str = "walk") -> Scene:
    import trimesh

    rest, weights, face_material = figure_rest()
    rots, pos = figure_pose(frame, motion)
    mesh = trimesh.Trimesh(skin(rest.vertices, weights, rots, pos), rest.faces.copy(), process=False)
    skeleton = SkeletonData(pos, list(PARENTS), list(NAMES), weights.copy())
    return Scene(mesh, rest.vertices.copy(), face_material.copy(), FIGURE_MATERIALS.copy(),
                 np.array([0.0, 0.0, 0.92]), 0.98, skeleton)
