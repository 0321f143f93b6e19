"""Camera model: NumPy vs OpenCL projection (kernels/project.cl), rays, packing."""
import numpy as np
import pytest

from nodes.common.cameras import Camera, Cameras, project_points_cl
from rig import ring_rig


def ring(n, radius, height, target, width, height_px, fov=50.0, dist=None, name="c"):
    scaled = None if dist is None else (lambda i: np.asarray(dist, dtype=np.float64) * (1 + 0.1 * i))
    return list(ring_rig(n, width, height_px, radius=radius, z=height, target=target, fov=fov, dist=scaled,
                         name=name + "{i}"))


def scenes():
    """(cameras, points) at realistic coordinates: a Tsinghua-like dome (units ~0.1 m, object 24 units from
    the world origin), a Utrecht-like room in mm with strong barrel distortion, and bare-P cameras."""
    rng = np.random.default_rng(1)
    target = np.array([0.0, 0.0, 24.0])
    dome = ring(4, 24, 3, target, 1024, 768) + ring(3, 24, 5, target, 1024, 768, dist=[-0.04, 0.06, 0, 0, 0], name="d")
    room_t = np.array([350.0, 0.0, -900.0])
    room = ring(4, 4500, -1500, room_t, 644, 486, fov=66, dist=[-0.37, 0.2, 3e-4, 2e-5, -0.07], name="r")
    bare = [Camera.from_P(f"p{i}", s * c.P, c.width, c.height) for i, (s, c) in enumerate(zip([1.0, -3.0, 0.01], dome))]
    return [
        (Cameras(dome), target + rng.uniform(-6, 6, (500, 3))),
        (Cameras(room), room_t + rng.uniform(-1800, 1800, (500, 3))),
        (Cameras(bare), target + rng.uniform(-6, 6, (500, 3))),
    ]


@pytest.mark.parametrize("k", range(3), ids=["dome", "room_distorted", "bare_P"])
def test_opencl_projection_matches_numpy(k):
    cams, X = scenes()[k]
    uv, depth = project_points_cl(cams, X)
    for v in range(len(cams)):
        ref_uv, ref_z = cams.project(X, v)
        assert np.all(ref_z > 0)
        assert np.abs(uv[v] - ref_uv).max() < 1e-4, f"view {v}: {np.abs(uv[v] - ref_uv).max()} px"
        assert np.abs(depth[v] - ref_z).max() < 1e-6 * np.abs(ref_z).max()


def test_distortion_moves_points():
    """The distorted room cameras really distort (a test of the test data): undistorted projection differs."""
    cams, X = scenes()[1]
    plain = Cameras([Camera(c.name, c.width, c.height, c.K, c.Rt) for c in cams])
    assert np.abs(cams.project(X, 0)[0] - plain.project(X, 0)[0]).max() > 5


def test_pack_origin_is_equivalent():
    """pack(origin) with points shifted by origin projects exactly like pack() (checked in float64 by
    reimplementing the packed formula)."""
    cams, X = scenes()[2]
    o = X.mean(0)
    for packed, pts in ((cams.pack(), X), (cams.pack(origin=o), X - o)):
        for v in range(len(cams)):
            c = packed[v].astype(np.float64)
            xc = pts @ c[0:12].reshape(3, 4)[:, :3].T + c[0:12].reshape(3, 4)[:, 3]
            u = c[12] * xc[:, 0] / xc[:, 2] + c[13] * xc[:, 1] / xc[:, 2] + c[14]
            ref = cams.project(X, v)[0][:, 0]
            assert np.abs(u - ref).max() < 0.05  # float32 packing of raw P entries; the CL test is the exact one


@pytest.mark.parametrize("k", range(3), ids=["dome", "room_distorted", "bare_P"])
def test_rays_pass_through_points(k):
    cams, X = scenes()[k]
    scale = np.abs(X).max()
    for v in range(len(cams)):
        uv, z = cams.project(X, v)
        o, d = cams.rays(v, uv)
        np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
        t = ((X - o) * d).sum(1)
        assert np.all(t > 0), "rays must point into the scene"
        assert np.abs(o + t[:, None] * d - X).max() < 1e-8 * scale


def test_centres_of_look_at_rig():
    cams = Cameras(ring(6, 5.0, 1.0, [1.0, 2.0, 3.0], 64, 48))
    for i, c in enumerate(cams):
        a = 2 * np.pi * i / 6
        np.testing.assert_allclose(c.center, [1 + 5 * np.cos(a), 2 + 5 * np.sin(a), 4.0], atol=1e-9)
    bare = Camera.from_P("p", -2 * cams[0].P, 64, 48)
    np.testing.assert_allclose(bare.center, cams[0].center, atol=1e-9)
