"""Visual hull: NumPy reference == dense OpenCL == sparse coarse-to-fine OpenCL, on synthetic rigs."""
from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest

from nodegraph import NodeError
from nodes.common.types import Volume
from nodes.common.cameras import Camera, Cameras
from rig import ring_rig
from nodegraph.testing import run_node
from nodes.common.types import MaskSet
from nodes.hull.hull import hull_grid, visual_hull

BOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
CENTRE, RADIUS = np.array([0.1, -0.05, 0.0]), 0.6


def ring(n=8, w=160, h=120, dist=None) -> Cameras:
    return ring_rig(n, w, h, radius=3.0, z=lambda i, a: 0.8 * np.sin(3 * a), fov=50, name="c{i}", dist=dist)


def sphere_masks(cams: Cameras, centre=CENTRE, radius=RADIUS) -> MaskSet:
    """Silhouettes of a ball: filled convex hull of its projected surface samples (lens distortion included)."""
    u = np.random.default_rng(0).normal(size=(4000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    masks = []
    for v, cam in enumerate(cams):
        uv, _ = cams.project(centre + radius * u, v)
        m = np.zeros((cam.height, cam.width), np.uint8)
        cv2.fillPoly(m, [cv2.convexHull(np.round(uv * 16).astype(np.int32))], 255, cv2.LINE_8, shift=4)
        masks.append(m)
    return MaskSet(masks)


def all_methods(masks, cams, res, **kw) -> np.ndarray:
    """Run the three methods, assert they agree voxel for voxel, return the occupancy."""
    ref = visual_hull(masks, cams, BOX, res, method="numpy", **kw).occupancy
    dense = visual_hull(masks, cams, BOX, res, method="dense", **kw).occupancy
    sparse = visual_hull(masks, cams, BOX, res, method="sparse", **kw).occupancy
    assert np.array_equal(ref, dense), f"dense differs from NumPy in {int((ref != dense).sum())} voxels"
    assert np.array_equal(ref, sparse), f"sparse differs from NumPy in {int((ref != sparse).sum())} voxels"
    return ref


def ball_iou(occ: np.ndarray, res: int) -> float:
    bmin, bmax, dims = hull_grid(BOX, res)
    vs = (bmax - bmin) / np.array(dims)
    axes = [bmin[a] + (np.arange(n) + 0.5) * vs[a] for a, n in enumerate(dims)]
    X = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    ball = np.linalg.norm(X - CENTRE, axis=-1) <= RADIUS
    return float((ball & (occ > 0)).sum() / (ball | (occ > 0)).sum())


@pytest.mark.parametrize("res", [17, 40])
def test_methods_agree_on_a_ball(res):
    cams = ring()
    occ = all_methods(sphere_masks(cams), cams, res)
    assert occ.shape == hull_grid(BOX, res)[2]
    assert 0.75 < ball_iou(occ, res) < 1.0  # 8 views: a hull slightly larger than the ball


def test_methods_agree_with_lens_distortion():
    cams = ring(dist=[-0.25, 0.08, 0.002, -0.003, 0.01])
    masks = sphere_masks(cams)
    occ = all_methods(masks, cams, 36)
    assert ball_iou(occ, 36) > 0.75
    # ignoring the distortion gives a different hull: the distortion is really used
    plain = Cameras([Camera(c.name, c.width, c.height, c.K, c.Rt) for c in cams])
    assert (visual_hull(masks, plain, BOX, 36).occupancy != occ).sum() > 100


def test_min_views_survives_one_bad_silhouette():
    cams = ring()
    masks = sphere_masks(cams)
    clean = all_methods(masks, cams, 32)
    bad = MaskSet([m.copy() for m in masks.masks])
    bad.masks[3][:, 70:90] = 0  # a stripe missing in one view
    holed = all_methods(bad, cams, 32)
    assert clean.sum() - holed.sum() > 200
    tolerant = all_methods(bad, cams, 32, min_views=7)
    assert np.all(tolerant >= clean) and tolerant.sum() > clean.sum()
    assert all_methods(bad, cams, 32, min_views=8).sum() == holed.sum()


def test_outside_policy():
    cams = ring(6)
    zoom = cams[0]  # a narrow camera that sees only the middle of the box
    K = zoom.K.copy()
    K[0, 0] *= 3
    K[1, 1] *= 3
    cams = Cameras([Camera(zoom.name, zoom.width, zoom.height, K, zoom.Rt), *cams.cameras[1:]])
    masks = sphere_masks(cams)
    carve = all_methods(masks, cams, 30, policy="carve")
    ignore = all_methods(masks, cams, 30, policy="ignore")
    assert np.all(ignore >= carve) and ignore.sum() - carve.sum() > 500


def test_bare_projection_matrices():
    metric = ring(6)
    masks = sphere_masks(metric)
    # -P projects the same points; its third row points backwards, which pack()[24] records
    bare = Cameras([Camera.from_P(c.name, -c.P, c.width, c.height) for c in metric])
    assert np.all(bare.pack()[:, 24] == -1)
    a = all_methods(masks, bare, 30)
    b = visual_hull(masks, metric, BOX, 30).occupancy
    assert a.sum() > 1000 and (a != b).sum() <= 0.01 * b.sum()


def test_node_golden(golden):
    cams = ring(6, 64, 48)
    out = run_node("hull", {"masks": sphere_masks(cams), "cameras": cams}, {"resolution": 16, "bbox": BOX.ravel().tolist()},
                   roundtrip=True)
    vol = out["volume"]
    assert vol.occupancy.dtype == np.uint8 and vol.occupancy.shape == (16, 16, 16)
    assert 200 < vol.occupancy.sum() < 16**3 / 2
    golden.check("hull_sphere", vol, Volume)


def test_node_reads_bounds_input_and_reports_bad_input():
    cams = ring(4, 64, 48)
    masks = sphere_masks(cams)
    a = run_node("hull", {"masks": masks, "cameras": cams, "bounds": BOX}, {"resolution": 12})["volume"]
    b = run_node("hull", {"masks": masks, "cameras": cams}, {"resolution": 12, "bbox": BOX.ravel().tolist()})["volume"]
    assert np.array_equal(a.occupancy, b.occupancy) and a.occupancy.sum() > 0
    with pytest.raises(NodeError, match="bbox"):
        run_node("hull", {"masks": masks, "cameras": cams}, {"resolution": 12})
    with pytest.raises(NodeError, match="camera 'c2'"):
        small = MaskSet([m if i != 2 else m[:-1] for i, m in enumerate(masks.masks)])
        run_node("hull", {"masks": small, "cameras": cams, "bounds": BOX}, {"resolution": 12})
    with pytest.raises(NodeError, match="min_views 5"):
        run_node("hull", {"masks": masks, "cameras": cams, "bounds": BOX}, {"min_views": 5})
    with pytest.raises(NodeError, match="max > min"):
        run_node("hull", {"masks": masks, "cameras": cams}, {"bbox": [0, 0, 0, 1, -1, 1]})


def test_box_beyond_float32_or_missing_the_object():
    """The kernels work in float32: a box that overflows it (inf, 3e38 - -3e38) or has no float32 extent is
    a NodeError; a box that misses the object gives an empty volume and a warning in the node's log."""
    cams = ring(4, 64, 48)
    masks = sphere_masks(cams)
    for box in ([-3e38, 0, 0, 3e38, 1, 1], [1.0, 0, 0, 1.0 + 1e-12, 1, 1]):
        with pytest.raises(NodeError, match="finite .*float32.* max > min"):
            run_node("hull", {"masks": masks, "cameras": cams}, {"resolution": 8, "bbox": box})
    with pytest.raises(ValueError, match="expects a finite number"):  # an infinite param never reaches the node
        run_node("hull", {"masks": masks, "cameras": cams}, {"resolution": 8, "bbox": [0, 0, 0, float("inf"), 1, 1]})
    with pytest.raises(NodeError, match="float32"):
        run_node("hull", {"masks": masks, "cameras": cams, "bounds": np.array([[0, 0, 0], [np.inf, 1, 1]])}, {"resolution": 8})
    records = []
    handler = logging.Handler(logging.WARNING)
    handler.emit = records.append
    logging.getLogger("volcap").addHandler(handler)
    try:
        far = run_node("hull", {"masks": masks, "cameras": cams}, {"resolution": 8, "bbox": [0.9, 0.9, -0.05, 1.0, 1.0, 0.05]})["volume"]
    finally:
        logging.getLogger("volcap").removeHandler(handler)
    assert far.occupancy.shape == (8, 8, 8) and far.occupancy.sum() == 0
    assert any("no voxel is inside the silhouettes" in r.getMessage() for r in records)


def test_camera_facing_away_from_the_box_is_named():
    """Camera c2 turned 180 degrees about its y axis has the box behind it: with outside='carve' that is a
    NodeError naming it (it would carve every voxel), with outside='ignore' the other views make the hull."""
    cams = ring(4, 64, 48)
    masks = sphere_masks(cams)
    turned = cams[2].Rt.copy()
    turned[[0, 2]] *= -1
    bad = Cameras([c if i != 2 else Camera(c.name, c.width, c.height, c.K, turned) for i, c in enumerate(cams)])
    with pytest.raises(NodeError, match=r"behind camera\(s\) 2 'c2'"):
        run_node("hull", {"masks": masks, "cameras": bad}, {"resolution": 12, "bbox": BOX.ravel().tolist()})
    kept = run_node("hull", {"masks": masks, "cameras": bad}, {"resolution": 12, "bbox": BOX.ravel().tolist(), "outside": "ignore"})
    assert kept["volume"].occupancy.sum() > 0
    assert run_node("hull", {"masks": masks, "cameras": cams}, {"resolution": 12, "bbox": BOX.ravel().tolist()})["volume"].occupancy.sum() > 0


@pytest.mark.parametrize("res", [72, 150])
def test_sparse_equals_dense_over_three_or_more_levels(res):
    cams = ring()
    masks = sphere_masks(cams)
    dense = visual_hull(masks, cams, BOX, res, method="dense").occupancy
    for _ in range(2):  # the level buffers are reused between calls
        assert np.array_equal(visual_hull(masks, cams, BOX, res, method="sparse").occupancy, dense)


@pytest.mark.slow
@pytest.mark.realdata
@pytest.mark.parametrize("name, min_iou", [("thu_wd_human", 0.954), ("inria_dancer", 0.912)])
def test_real_human_hull_mesh(real_capture, name, min_iou):
    import trimesh

    from nodes.common.bounds import auto_bounds
    from nodes.eval.silhouette import silhouette_report
    from nodes.common.meshops import largest_component
    from nodes.mesh.mc import marching_cubes

    cap = real_capture(name)
    masks, cams = cap["masks"], cap["cameras"]
    box = auto_bounds(masks.masks, cams)
    vol = visual_hull(masks, cams, box, 128)
    assert max(vol.occupancy.shape) == 128
    assert np.array_equal(vol.occupancy, visual_hull(masks, cams, box, 128, method="dense").occupancy)
    mesh = trimesh.Trimesh(*largest_component(*marching_cubes(vol)), process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert len(mesh.split(only_watertight=False)) == 1
    report = silhouette_report(mesh.vertices, mesh.faces, cams, masks)
    assert report["mean_iou"] >= min_iou, report["mean_iou"]


def test_silhouette_bits_from_masks_hold_the_masks_and_their_block_tables():
    """SilhouetteBits.from_masks: device bits unpack to the masks, the tables are the 8x8 block summed-area tables."""
    from nodes.common.silhouettes import SilhouetteBits, block_table_reference

    rng = np.random.default_rng(3)
    masks = [(rng.random((h, w)) < 0.4).astype(np.uint8) * rng.integers(128, 256, (h, w), dtype=np.uint8)
             for w, h in ((53, 37), (64, 48), (9, 17))]  # odd sizes; values > 127 are inside
    sil = SilhouetteBits.from_masks(masks)
    assert isinstance(sil, SilhouetteBits) and sil.sizes == [(53, 37), (64, 48), (9, 17)]
    for m, bits, table in zip(masks, sil.masks(), sil.block_tables()):
        assert np.array_equal(bits, np.where(m > 127, 255, 0))
        assert np.array_equal(table, block_table_reference(m))
        assert table[-1, -1] == (m > 127).sum() > 0


def test_silhouette_bits_of_opaque_pixels():
    """SilhouetteBits.from_masks(opaque=True), refine's and relax's silhouettes of an alpha's fully opaque pixels:
    inside exactly where the level is 255 (254 and 128 are not), in the 8-pixel groups and the row tails of odd
    widths alike; the tables are block_table_reference's with opaque."""
    from nodes.common.silhouettes import SilhouetteBits, block_table_reference

    rng = np.random.default_rng(4)
    levels = np.array([0, 1, 127, 128, 200, 254, 255, 255, 255], np.uint8)
    masks = [levels[rng.integers(0, len(levels), (h, w))] for w, h in ((53, 37), (64, 48), (9, 17), (7, 5))]
    masks[1][10, 8:16] = 255          # a whole group opaque, and one with a single 254 in it
    masks[1][11, 8:16] = 255
    masks[1][11, 13] = 254
    sil = SilhouetteBits.from_masks(masks, opaque=True)
    for m, bits, table in zip(masks, sil.masks(), sil.block_tables()):
        assert np.array_equal(bits, np.where(m == 255, 255, 0))
        assert np.array_equal(table, block_table_reference(m, opaque=True))
        assert 0 < table[-1, -1] == (m == 255).sum() < (m > 127).sum()


def test_bounds_golden(small_stage, golden):
    out = run_node("bounds", {"masks": small_stage["masks"], "cameras": small_stage["cameras"]}, {"resolution": 32})
    box = out["bounds"]
    # the automatic box must contain the true mesh and stay reasonably tight (8 views: a loose hull)
    lo, hi = small_stage["mesh"].bounds
    assert np.all(box[0] <= lo) and np.all(box[1] >= hi)
    assert np.prod(box[1] - box[0]) < 4 * np.prod(hi - lo)
    from nodegraph import Array

    golden.check("bounds_figure_8cams", box, Array, atol=1e-6)


def hull_warnings(masks, cams, **params) -> list[str]:
    records = []
    handler = logging.Handler(logging.WARNING)
    handler.emit = records.append
    logging.getLogger("volcap").addHandler(handler)
    try:
        run_node("hull", {"masks": masks, "cameras": cams}, {"resolution": 12, "bbox": BOX.ravel().tolist(), **params})
    finally:
        logging.getLogger("volcap").removeHandler(handler)
    return [r.getMessage() for r in records]


def test_silhouettes_cut_by_the_border_in_most_views_warn_with_carve():
    """outside: carve drops every voxel projecting outside an image: an object cut by the border of most
    views loses what lies beyond it; the hull's log says so, naming the views and outside: ignore."""
    cams = ring(6, 64, 48)
    base = sphere_masks(cams).masks

    def cut(views):
        out = [m.copy() for m in base]
        for v in views:
            out[v][20:30, -1] = 255 if v % 2 else 0
            out[v][-1, 30:34] = 0 if v % 2 else 255
        return MaskSet(out)

    msg = ("hull: the silhouettes touch the image border in 4 of the 6 views (c0, c1, c2, c4): the object is cut "
           "by the image border there, and outside: carve removes every voxel that projects outside an image, so "
           "what lies beyond the border is lost; set outside: ignore to keep it")
    assert msg in hull_warnings(cut([0, 1, 2, 4]), cams)
    from nodes.common.silhouettes import SilhouetteBits

    host = cut([0, 1, 2, 4])
    on_device = MaskSet(host.masks, device=SilhouetteBits.from_masks(host.masks))  # read from the block tables
    assert msg in hull_warnings(on_device, cams)
    assert not any("image border" in w for w in hull_warnings(cut([0, 1, 2, 4]), cams, outside="ignore"))
    assert not any("image border" in w for w in hull_warnings(cut([0, 3, 5]), cams))  # half the views: not most


def test_initial_box_equals_the_pixel_list_reference():
    """bounds' first box from OpenCV's moments and box of each silhouette: the same floats as from the list of its
    pixels (np.nonzero: centroid = their mean, extent = the box's diagonal), bit for bit; masks of any non-zero
    level count, an empty view is left out."""
    from nodes.common.bounds import initial_box

    cams = ring_rig(4, 64, 48)

    def reference(masks):
        origins, dirs, extents = [], [], []
        for v, m in enumerate(masks):
            ys, xs = np.nonzero(m)
            if len(xs) == 0:
                continue
            o, d = cams.rays(v, [[xs.mean(), ys.mean()]])
            origins.append(o[0])
            dirs.append(d[0])
            extents.append(np.hypot(xs.max() - xs.min(), ys.max() - ys.min()) / 2)
        A = sum(np.eye(3) - np.outer(d, d) for d in dirs)
        b = sum((np.eye(3) - np.outer(d, d)) @ o for o, d in zip(origins, dirs))
        p0 = np.linalg.lstsq(A, b, rcond=None)[0]
        radius = 0.0
        for v, (o, ext) in enumerate(zip(origins, extents)):
            eps = 1e-4 * np.linalg.norm(p0 - o)
            J = np.stack([(cams.project(p0 + eps * e, v)[0] - cams.project(p0 - eps * e, v)[0])[0] / (2 * eps)
                          for e in np.eye(3)], axis=1)
            radius = max(radius, ext / np.linalg.svd(J, compute_uv=False)[1])
        return np.array([p0 - 1.5 * radius, p0 + 1.5 * radius])

    rng = np.random.default_rng(4)
    for k in range(12):
        masks = []
        for v in range(4):
            m = np.zeros((cams[v].height, cams[v].width), np.uint8)
            if v or k % 3:                           # every third case: camera 0 sees nothing
                y0, x0 = rng.integers(0, 30), rng.integers(0, 40)
                m[y0:y0 + rng.integers(1, 18), x0:x0 + rng.integers(1, 24)] = rng.choice([1, 128, 255])
                m[rng.integers(0, m.shape[0], 5), rng.integers(0, m.shape[1], 5)] = 255
            masks.append(m)
        assert initial_box(masks, cams).tobytes() == reference(masks).tobytes()
