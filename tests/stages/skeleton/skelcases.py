"""Small dynamic meshes with a known skeleton for the skeleton tests: a tube bending at two rotation-only
joints (true LBS: smooth weights along its length), and the synth figure's frames."""
from __future__ import annotations

import math

import numpy as np


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


TUBE_JOINTS = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.4], [0.0, 0.0, 0.8]])
TUBE_PARENTS = [-1, 0, 1]


def tube(rings: int = 36, around: int = 16, length: float = 1.2, radius: float = 0.08):
    """(vertices, faces, weights (V, 3)) of a closed tube along z from 0 to ``length``, three bones with
    pivots at z = 0, 0.4, 0.8 and weights blending over 0.1 around each joint."""
    z = np.linspace(0.0, length, rings)
    a = np.linspace(0, 2 * np.pi, around, endpoint=False)
    ring = np.stack([radius * np.cos(a), radius * np.sin(a)], 1)
    verts = np.concatenate([np.c_[ring, np.full(around, zz)] for zz in z] + [[[0, 0, 0]], [[0, 0, length]]])
    faces = []
    for i in range(rings - 1):
        for k in range(around):
            p, q = i * around + k, i * around + (k + 1) % around
            faces += [[p, q, q + around], [p, q + around, p + around]]
    bottom, top = len(verts) - 2, len(verts) - 1
    for k in range(around):
        faces.append([bottom, (k + 1) % around, k])
        last = (rings - 1) * around
        faces.append([top, last + k, last + (k + 1) % around])
    zz = verts[:, 2]
    s1 = np.clip((zz - 0.35) / 0.1, 0, 1)
    s2 = np.clip((zz - 0.75) / 0.1, 0, 1)
    w = np.stack([1 - s1, s1 * (1 - s2), s1 * s2], 1)
    return verts, np.array(faces), w


def tube_pose(t: int) -> tuple[np.ndarray, np.ndarray]:
    """Bone motions (R (3, 3, 3), T (3, 3)) rest -> frame t: the root turns about z and slides along x,
    joint 1 bends about x, joint 2 about y; frame 0 is the straight rest pose."""
    root = np.array([[math.cos(0.1 * t), -math.sin(0.1 * t), 0], [math.sin(0.1 * t), math.cos(0.1 * t), 0], [0, 0, 1]])
    l1 = _rot_x(0.6 * math.sin(0.5 * t))
    l2 = _rot_y(0.8 * math.sin(0.37 * t))
    r = [root, root @ l1, root @ l1 @ l2]
    offset = np.array([0.05 * t, 0.0, 0.0])
    tr = []
    for j, p in enumerate(TUBE_PARENTS):
        if p < 0:
            tr.append(offset - r[0] @ TUBE_JOINTS[0] + TUBE_JOINTS[0])
        else:
            pivot = r[p] @ TUBE_JOINTS[j] + tr[p]
            tr.append(pivot - r[j] @ TUBE_JOINTS[j])
    return np.array(r), np.array(tr)


def tube_sequence(frames: int = 12, noise: float = 0.0, seed: int = 0):
    """(frames (F, V, 3), faces, true weights, true rotations (F, 3, 3, 3), translations (F, 3, 3))."""
    v, f, w = tube()
    rs, ts = zip(*(tube_pose(t) for t in range(frames)))
    rs, ts = np.array(rs), np.array(ts)
    out = np.einsum("vj,fjab,vb->fva", w, rs, v) + np.einsum("vj,fja->fva", w, ts)
    if noise:
        out = out + np.random.default_rng(seed).normal(0, noise, out.shape)
    return out, f, w, rs, ts


def tube_meshes(frames: int = 12, noise: float = 0.0):
    """The tube sequence as trimesh meshes (what a MeshSequence holds), frame numbers in metadata."""
    import trimesh

    pts, f, _, _, _ = tube_sequence(frames, noise)
    out = []
    for t, p in enumerate(pts):
        m = trimesh.Trimesh(p, f, process=False)
        m.metadata["frame"] = t
        out.append(m)
    return out
