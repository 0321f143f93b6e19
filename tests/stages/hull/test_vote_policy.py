"""The vote rule with a min_views tolerance keeps the outside policy (issue 12, item 4). min_views > 0 used to
switch the policy off: with outside='carve' a point outside one camera's image was inside the hull when
min_views other views saw it inside, so refine and relax moved vertices out of the region every camera
sees (up to 1.7 voxels outside the user's box); with outside='ignore' a point seen by few views was carved.

Rule: tolerance t = nviews - min_views (0 when min_views is 0). carve: inside when every view sees the point
and at most t see it on background; ignore: inside when at most t views see it on background and at least
one inside."""
from __future__ import annotations

import numpy as np
import pytest

from nodes.common.cameras import Camera, Cameras
from bench.legacy_hulltest import HullTestCL
from nodes.common.silhouettes import Silhouettes, inside_hull, vote
from nodes.common.types import MaskSet
from nodes.hull.hull import hull_grid, visual_hull
from rig import ring_rig

BOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


@pytest.mark.parametrize("n_in, n_bg, min_views, policy, inside", [
    (3, 0, 3, "carve", False),   # one of 4 views does not see the point: carve it (was: inside)
    (4, 0, 3, "carve", True),
    (3, 1, 3, "carve", True),    # one background vote tolerated
    (2, 1, 3, "carve", False),
    (2, 0, 3, "ignore", True),   # 2 views see it inside, none on background, 2 do not see it (was: carved)
    (1, 1, 3, "ignore", True),
    (1, 2, 3, "ignore", False),
    (0, 0, 3, "ignore", False),
    (4, 0, 0, "carve", True), (3, 0, 0, "carve", False), (3, 1, 0, "carve", False),
    (1, 0, 0, "ignore", True), (3, 1, 0, "ignore", False),
])
def test_vote_table(n_in, n_bg, min_views, policy, inside):
    assert bool(vote(np.array([n_in]), np.array([n_bg]), 4, min_views, policy)[0]) is inside


def zoomed_rig() -> Cameras:
    """Six cameras round the box; the first one zoomed 3x, so it sees only the middle of the box."""
    cams = ring_rig(6, 160, 120, radius=3.0, z=lambda i, a: 0.8 * np.sin(3 * a), fov=50, name="c{i}")
    zoom = cams[0]
    K = zoom.K.copy()
    K[0, 0] *= 3
    K[1, 1] *= 3
    return Cameras([Camera(zoom.name, zoom.width, zoom.height, K, zoom.Rt), *cams.cameras[1:]])


def ball_masks(cams, centre=(0.1, -0.05, 0.0), radius=0.75) -> MaskSet:
    import cv2

    u = np.random.default_rng(0).normal(size=(4000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    out = []
    for v, cam in enumerate(cams):
        uv, _ = cams.project(np.asarray(centre) + radius * u, v)
        m = np.zeros((cam.height, cam.width), np.uint8)
        cv2.fillPoly(m, [cv2.convexHull(np.round(uv * 16).astype(np.int32))], 255, cv2.LINE_8, shift=4)
        out.append(m)
    return MaskSet(out)


def seen_by(cams: Cameras, v: int, X: np.ndarray) -> np.ndarray:
    uv, z = cams.project(X, v)
    fu, fv = uv[:, 0] + 0.5, uv[:, 1] + 0.5
    return (z > 0) & (fu >= 0) & (fu < cams[v].width) & (fv >= 0) & (fv < cams[v].height)


def voxel_centres(res):
    bmin, bmax, dims = hull_grid(BOX, res)
    vs = (bmax - bmin) / np.array(dims)
    axes = [bmin[a] + (np.arange(n) + 0.5) * vs[a] for a, n in enumerate(dims)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def hulls(masks, cams, res, **kw) -> np.ndarray:
    ref = visual_hull(masks, cams, BOX, res, method="numpy", **kw).occupancy
    for method in ("dense", "sparse"):
        got = visual_hull(masks, cams, BOX, res, method=method, **kw).occupancy
        assert np.array_equal(ref, got), f"{method} differs from NumPy in {int((ref != got).sum())} voxels ({kw})"
    return ref


def test_min_views_keeps_the_outside_policy_in_the_hull():
    cams = zoomed_rig()
    masks = ball_masks(cams)
    res = 28
    X = voxel_centres(res)
    seen0 = seen_by(cams, 0, X)
    assert 0.1 < seen0.mean() < 0.9
    carve = hulls(masks, cams, res, min_views=5, policy="carve").ravel() > 0
    assert carve.sum() > 500
    assert not np.any(carve & ~seen0), f"{int((carve & ~seen0).sum())} voxels outside camera 0's image kept with carve"
    ignore = hulls(masks, cams, res, min_views=5, policy="ignore").ravel() > 0
    strict_ignore = hulls(masks, cams, res, policy="ignore").ravel() > 0
    assert np.all(ignore >= carve) and np.all(ignore >= strict_ignore)
    assert (ignore & ~seen0).sum() > 300, "ignore must keep what camera 0 does not see"


@pytest.mark.parametrize("policy", ["carve", "ignore"])
def test_point_test_of_refine_and_relax_follows_the_same_rule(policy):
    """HullTestCL (kernels/refine.cl through silhouette.h) == inside_hull (NumPy) with min_views, and with
    carve no point outside camera 0's image is inside: refine and relax cannot move a vertex there."""
    cams = zoomed_rig()
    masks = ball_masks(cams)
    views = Silhouettes.from_inputs(masks, cams, min_views=5, outside=policy)
    pts = np.random.default_rng(1).uniform(-1.2, 1.2, (20000, 3)).astype(np.float32)
    ref = inside_hull(pts, views)
    got = HullTestCL(views).inside(pts)
    assert np.array_equal(ref, got), int((ref != got).sum())
    outside0 = ~seen_by(cams, 0, pts)
    if policy == "carve":
        assert ref.sum() > 500 and not np.any(ref & outside0)
    else:
        assert (ref & outside0).sum() > 300


# ---------------------------------------------------------------- min_seen (issue: refuse what goes wrong silently)
@pytest.mark.parametrize("n_in, n_bg, min_views, policy, min_seen, inside", [
    (2, 0, 0, "ignore", 3, False),   # inside the 2 silhouettes that see it, but only 2 views constrain it
    (3, 0, 0, "ignore", 3, True),
    (2, 1, 3, "ignore", 3, True),    # 3 views see it (one on background, tolerated): seen counts both
    (2, 1, 3, "ignore", 4, False),
    (1, 0, 0, "ignore", 0, True), (1, 0, 0, "ignore", 1, True), (0, 0, 0, "ignore", 0, False),
    (4, 0, 0, "carve", 4, True), (3, 1, 3, "carve", 4, True),
])
def test_vote_table_min_seen(n_in, n_bg, min_views, policy, min_seen, inside):
    got = vote(np.array([n_in]), np.array([n_bg]), 4, min_views, policy, min_seen=min_seen)
    assert bool(got[0]) is inside


@pytest.mark.parametrize("res", [28, 70])  # 70: three sparse levels, the coarse cell test decides too
def test_min_seen_in_the_hull_kernels_and_reference(res):
    """min_seen k: kept only when at least k views see the voxel (in front, inside the image), and the vote
    holds in those; dense and sparse OpenCL == NumPy. ignore + min_seen = every view is carve."""
    cams = zoomed_rig()
    masks = ball_masks(cams)
    X = voxel_centres(res)
    seen = sum(seen_by(cams, v, X).astype(int) for v in range(len(cams)))
    plain = hulls(masks, cams, res, policy="ignore").ravel() > 0
    assert (plain & (seen < 6)).sum() > 300
    for k in (5, 6):
        got = hulls(masks, cams, res, policy="ignore", min_seen=k).ravel() > 0
        assert got.sum() > 500 and not np.any(got & (seen < k)) and np.all(got <= plain), k
    assert np.array_equal(hulls(masks, cams, res, policy="ignore", min_seen=6), hulls(masks, cams, res, policy="carve"))
    for min_views, k in ((5, 5), (4, 6)):  # background votes tolerated: a coarse cell partly seen is not inside
        tolerant = hulls(masks, cams, res, policy="ignore", min_views=min_views, min_seen=k).ravel() > 0
        assert tolerant.sum() > 500 and not np.any(tolerant & (seen < k)), (min_views, k)
    assert np.array_equal(hulls(masks, cams, res, policy="ignore", min_seen=1), hulls(masks, cams, res, policy="ignore"))


def test_min_seen_param_of_hull_and_bounds():
    from nodegraph import NodeError
    from nodegraph.testing import run_node

    cams = zoomed_rig()
    masks = ball_masks(cams)
    box = BOX.ravel().tolist()
    a = run_node("hull", {"masks": masks, "cameras": cams}, {"resolution": 16, "bbox": box, "outside": "ignore",
                                                            "min_seen": 6})["volume"].occupancy
    b = run_node("hull", {"masks": masks, "cameras": cams}, {"resolution": 16, "bbox": box})["volume"].occupancy
    assert np.array_equal(a, b) and a.sum() > 0
    for node, params in (("hull", {"bbox": box}), ("bounds", {})):
        with pytest.raises(NodeError, match=f"{node}: min_seen 7 is more than the 6 cameras"):
            run_node(node, {"masks": masks, "cameras": cams}, {**params, "min_seen": 7})
    default = run_node("bounds", {"masks": masks, "cameras": cams})["bounds"]
    same = run_node("bounds", {"masks": masks, "cameras": cams}, {"min_seen": 3})["bounds"]  # the default rule's k
    np.testing.assert_array_equal(default, same)


def test_auto_bounds_hold_only_what_k_views_constrain():
    """The bounds' coarse hull keeps only voxels seen by at least min_seen views, so the box never grows into
    what fewer views constrain: with every view required it lies in what camera 0 (zoomed) sees."""
    from nodes.common.bounds import auto_bounds, coarse_hull

    cams = zoomed_rig()
    masks = ball_masks(cams, radius=0.9).masks
    occ = coarse_hull(masks, cams, BOX, 24, min_seen=6)
    bmin, bmax = BOX
    axes = [bmin[a] + (np.arange(n) + 0.5) * (bmax[a] - bmin[a]) / n for a, n in enumerate(occ.shape)]
    X = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    assert occ.sum() > 100 and np.all(seen_by(cams, 0, X[occ.ravel()]))
    loose, strict = auto_bounds(masks, cams, margin=0.0), auto_bounds(masks, cams, margin=0.0, min_seen=6)
    assert np.all(strict[0] >= loose[0] - 1e-9) and np.all(strict[1] <= loose[1] + 1e-9)
    assert np.prod(strict[1] - strict[0]) < 0.9 * np.prod(loose[1] - loose[0])
