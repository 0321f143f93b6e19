"""The one camera-rig builder of the tests: pinhole cameras (nodes.common.cameras.look_at, z up) on a ring or
spread over a sphere, looking at a target.

    ring_rig(8, 160, 120, radius=3.0, z=0.8)                    # 8 cameras round the origin, 0.8 above it
    ring_rig(4, 320, 240, radius=4.0, z=lambda i, a: 1.5 + 0.2 * i, phase=0.3, target=(0.1, -0.2, 0.4),
             center=(0, 0, 0), fov=55, name="view{i}")
    sphere_rig(20, 128, distance=4.0)                           # Fibonacci sphere, square images
"""
from __future__ import annotations

import math

import numpy as np

from nodes.common.cameras import Cameras, look_at


def ring_rig(n: int, width: int, height: int, *, radius: float = 3.0, z=0.0, target=(0.0, 0.0, 0.0), center=None,
             fov: float = 50.0, phase: float = 0.0, angles=None, name: str = "cam{i}", dist=None) -> Cameras:
    """``n`` cameras at ``radius`` round ``center`` (default: the target) in the horizontal plane, raised by ``z``
    (a number, or z(i, angle)), at angles 2 pi i / n + phase (or the given ``angles``), looking at ``target``.
    ``dist``: OpenCV distortion given to every camera, or dist(i) per camera. Names: ``name.format(i=i)``."""
    target = np.asarray(target, dtype=np.float64)
    centre = target if center is None else np.asarray(center, dtype=np.float64)
    angles = [2 * math.pi * i / n + phase for i in range(n)] if angles is None else list(angles)
    cams = []
    for i, a in enumerate(angles):
        rise = z(i, a) if callable(z) else z
        eye = centre + [radius * math.cos(a), radius * math.sin(a), rise]
        cam = look_at(eye, target, [0, 0, 1], fov, width, height, name.format(i=i))
        if dist is not None:
            d = np.ravel(dist(i) if callable(dist) else dist).astype(np.float64)
            cam.dist = np.zeros(5)
            cam.dist[: min(5, d.size)] = d[:5]
        cams.append(cam)
    return Cameras(cams)


def sphere_rig(n: int, size: int, *, center=(0.0, 0.0, 0.0), distance: float = 4.0, fov: float = 40.0,
               name: str = "cam{i:03d}") -> Cameras:
    """``n`` cameras spread evenly over a sphere (Fibonacci) of radius ``distance`` round ``center``, looking at
    it, with square ``size`` x ``size`` images."""
    center = np.asarray(center, dtype=np.float64)
    cams = []
    for i in range(n):
        zc = 1 - 2 * (i + 0.5) / n
        phi = i * math.pi * (3 - math.sqrt(5))
        d = np.array([math.sqrt(1 - zc * zc) * math.cos(phi), math.sqrt(1 - zc * zc) * math.sin(phi), zc])
        up = (0, 0, 1) if abs(d[2]) < 0.95 else (0, 1, 0)
        cams.append(look_at(center + distance * d, center, up, fov, size, size, name=name.format(i=i)))
    return Cameras(cams)


def two_segments():
    """A tracked sequence of five frames (10..14) in two segments: a growing ball (keyframe 10), then a moving
    box (keyframe 13), with the metadata track writes."""
    import trimesh

    sphere, box = trimesh.creation.icosphere(2), trimesh.creation.box()
    seq = [trimesh.Trimesh(sphere.vertices * (1 + 0.1 * k), sphere.faces, process=False) for k in range(3)]
    seq += [trimesh.Trimesh(box.vertices + [0.1 * k, 0, 0], box.faces, process=False) for k in range(2)]
    for i, m in enumerate(seq):
        m.metadata.update(segment=int(i >= 3), keyframe=10 if i < 3 else 13, frame=10 + i)
    return seq
