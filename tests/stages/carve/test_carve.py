"""carve: OpenCL kernels == NumPy reference (voxel for voxel, colour for colour), the synthetic cup carved to
its photo hull (volume error halved, inside the hull, silhouettes kept), the strict silhouette guard (no mask
pixel the hull covered is left uncovered, even at threshold 0), device silhouettes, bad input, colours through
mc / refine / relax, golden file, and a real-data run on the Middlebury temple."""
from __future__ import annotations

import numpy as np
import pytest

from nodegraph import NodeError
from nodegraph.testing import run_node
from nodes.carve.carving import (CarveParams, carve, fill_colours, fill_colours_reference, hull_distance,
                                 layer_list, sweep_lists, sweep_lists_reference)
from nodes.common import raster
from nodes.common.types import ImageSet, Volume, VoxelGrid


@pytest.fixture(scope="module")
def small_cup():
    """Cup from a dome of 8 cameras at 120x90, hull at 16^3: small enough for the NumPy reference."""
    s = run_node("synth", {}, {"scene": "cup", "rig": "dome", "cameras": 8, "width": 120, "height": 90})
    s["hull"] = run_node("hull", {"masks": s["masks"], "cameras": s["cameras"], "bounds": s["bounds"]},
                         {"resolution": 16})["volume"]
    return s


@pytest.fixture(scope="module")
def cup():
    """Cup from a dome of 16 cameras at 320x240, hull at 64^3."""
    s = run_node("synth", {}, {"scene": "cup", "rig": "dome", "cameras": 16, "width": 320, "height": 240})
    s["hull"] = run_node("hull", {"masks": s["masks"], "cameras": s["cameras"], "bounds": s["bounds"]},
                         {"resolution": 64})["volume"]
    return s


def inputs(s, volume=None):
    return {"volume": s["hull"] if volume is None else volume, "images": s["images"], "masks": s["masks"],
            "cameras": s["cameras"]}


@pytest.mark.parametrize("algorithm", ["space_carving", "voxel_coloring"])
@pytest.mark.parametrize("space, threshold, contrast", [("rgb", 30.0, 1.0), pytest.param("lab", 10.0, 0.0, marks=pytest.mark.slow),
                                                      pytest.param("rgb", 0.0, 0.0, marks=pytest.mark.slow)])
def test_kernels_match_numpy_reference(small_cup, algorithm, space, threshold, contrast):
    """Every step (sweeps, item passes, the guard's counts and bids, layers) in OpenCL and in NumPy: the same
    voxels and colours; threshold 0 makes nearly every surface voxel a candidate, so the guard decides."""
    p = CarveParams(space=space, threshold=threshold, contrast=contrast)
    cl = carve(small_cup["hull"], small_cup["images"], small_cup["masks"], small_cup["cameras"], p, algorithm)
    ref = carve(small_cup["hull"], small_cup["images"], small_cup["masks"], small_cup["cameras"], p, algorithm, "numpy")
    a, b = cl.volume.occupancy, ref.volume.occupancy
    assert np.array_equal(a, b), f"{int((a != b).sum())} voxels differ between OpenCL and NumPy"
    assert np.array_equal(cl.volume.colors, ref.volume.colors)
    assert cl.stats["passes"][-1]["removed"] == 0 if algorithm == "space_carving" else True
    removed = int(small_cup["hull"].occupancy.sum() - a.sum())
    assert removed > 0.05 * small_cup["hull"].occupancy.sum(), f"only {removed} voxels carved: the test is vacuous"


@pytest.mark.slow
def test_cup_photo_hull(cup):
    """The cup's inside, filled by the hull, is carved: volume error at most half the hull's; nothing leaves the
    hull; the carved mesh keeps the hull's silhouettes (IoU >= 0.99 per view); colours agree better over views."""
    out = run_node("carve.space_carving", inputs(cup))
    vol, report = out["volume"], out["report"]
    hull = cup["hull"]
    assert not np.any(vol.occupancy & ~hull.occupancy.astype(bool)), "voxels outside the hull"
    vox = float(np.prod(hull.voxel_size))
    true = cup["mesh"].volume
    err_hull = abs(hull.occupancy.sum() * vox - true)
    err = abs(vol.occupancy.sum() * vox - true)
    assert err <= 0.5 * err_hull, f"volume error {err:.4f} vs hull {err_hull:.4f}"
    mh = run_node("mc", {"volume": hull})["mesh"]
    mc = run_node("mc", {"volume": vol})["mesh"]
    for a, b in zip(raster.silhouette(mh.vertices, mh.faces, cup["cameras"]),
                    raster.silhouette(mc.vertices, mc.faces, cup["cameras"])):
        iou = ((a > 0) & (b > 0)).sum() / ((a > 0) | (b > 0)).sum()
        assert iou >= 0.98, f"silhouette IoU with the hull's {iou:.4f}"
    colour = run_node("carve.space_carving", inputs(cup), {"max_passes": 0})["report"]
    assert report["variance_out"] < 0.3 * colour["variance_out"]
    assert report["passes"][-1]["removed"] == 0                     # converged


def test_colour_only_keeps_the_volume(small_cup):
    out = run_node("carve.space_carving", inputs(small_cup), {"max_passes": 0})["volume"]
    hull = small_cup["hull"].occupancy
    assert np.array_equal(out.occupancy, hull)
    from scipy import ndimage

    surface = hull.astype(bool) & ~ndimage.binary_erosion(hull.astype(bool), border_value=0)
    assert out.colors.shape == (*hull.shape, 3)
    assert np.all(out.colors[surface].max(axis=1) > 0), "a surface voxel without colour"
    assert not np.any(out.colors[~surface])


def cube_silhouettes(vol, cameras):
    """Per view, the pixels covered by the volume's voxel cubes."""
    import trimesh

    X = vol.centers()[vol.occupancy > 0]
    box = trimesh.creation.box(vol.voxel_size)
    V = (box.vertices[None] + X[:, None]).reshape(-1, 3)
    F = (box.faces[None] + 8 * np.arange(len(X))[:, None, None]).reshape(-1, 3)
    return [m > 0 for m in raster.silhouette(V, F, cameras)]


@pytest.mark.slow
def test_guard_is_strict_with_zero_threshold(cup):
    """Threshold 0 calls almost every surface voxel inconsistent: the guard alone decides what stays. The carved
    voxels' cubes still cover every mask pixel the hull's cubes covered, in every view (the count of uncovered
    ones is 0, rendered by the z-buffer rasterizer, which shares no code with the guard), nothing leaves the
    hull, and it did carve: more than half the hull's voxels are gone."""
    out = carve(cup["hull"], cup["images"], cup["masks"], cup["cameras"],
                CarveParams(threshold=0.0, contrast=0.0, largest=False))
    occ, hull = out.volume.occupancy.astype(bool), cup["hull"].occupancy.astype(bool)
    assert occ.sum() < 0.5 * hull.sum(), f"{int(occ.sum())} of {int(hull.sum())} voxels kept"
    assert not np.any(occ & ~hull)
    uncovered = [int(((m > 127) & a & ~b).sum()) for m, a, b in
                 zip(cup["masks"].masks, cube_silhouettes(cup["hull"], cup["cameras"]),
                     cube_silhouettes(out.volume, cup["cameras"]))]
    assert uncovered == [0] * len(uncovered), f"mask pixels the hull covered, uncovered per view: {uncovered}"


def test_device_silhouettes_give_the_same_voxels(small_cup):
    """Masks handed over as device silhouettes (MaskSet.device, as the chroma key makes them) carve exactly as the
    host masks do; the pixel windows from their block tables equal those from the host masks."""
    from nodes.common.silhouettes import SilhouetteBits, mask_window, silhouette_windows
    from nodes.common.types import MaskSet

    s = small_cup
    host = [np.asarray(m) for m in s["masks"].masks]
    bits = SilhouetteBits.from_masks(host)
    assert silhouette_windows(bits).tolist() == [list(mask_window(m)) for m in host]
    lazy = MaskSet.lazy(lambda: pytest.fail("the host masks were read"), s["masks"].names, device=bits)
    a = carve(s["hull"], s["images"], s["masks"], s["cameras"]).volume
    b = carve(s["hull"], s["images"], lazy, s["cameras"]).volume
    assert np.array_equal(a.occupancy, b.occupancy) and np.array_equal(a.colors, b.colors)


def test_voxel_coloring_refuses_cameras_around_the_object():
    s = run_node("synth", {}, {"scene": "sphere", "rig": "ring", "cameras": 6, "width": 80, "height": 60})
    hull = run_node("hull", {"masks": s["masks"], "cameras": s["cameras"], "bounds": s["bounds"]},
                    {"resolution": 12})["volume"]
    with pytest.raises(NodeError, match="convex hull of the camera centres"):
        run_node("carve.voxel_coloring", {"volume": hull, "images": s["images"], "masks": s["masks"],
                                          "cameras": s["cameras"]})


def test_layer_order_grows_along_every_viewing_ray(small_cup):
    """Voxel colouring's order function (distance beyond the cameras' convex hull) never decreases along a ray
    from any camera through a voxel, and the layers hold every voxel once, in that order."""
    hull = small_cup["hull"]
    vs = hull.voxel_size.astype(np.float32)
    centres = small_cup["cameras"].centers - hull.bbox_min
    occ = hull.occupancy.astype(np.uint8)
    idx, offsets = layer_list(occ, vs, centres)
    assert sorted(idx.tolist()) == np.flatnonzero(occ).tolist()
    X = (np.stack(np.unravel_index(idx.astype(np.int64), occ.shape), 1) + 0.5) * vs
    g = hull_distance(X, centres, vs, occ.shape)
    layer = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
    assert np.all(np.diff(layer) >= 0) and np.all(np.diff(g) >= -1e-9)
    for c in centres:
        d = X - c
        for t in (0.25, 1.0, 3.0):
            ahead = hull_distance(X + t * float(vs.max()) * d / np.linalg.norm(d, axis=1, keepdims=True), centres, vs,
                                  occ.shape)
            assert np.all(ahead >= g - 1e-9)


def test_bad_inputs_name_the_problem(small_cup):
    s = small_cup
    with pytest.raises(NodeError, match="carve.space_carving: 7 images for 8 cameras"):
        run_node("carve.space_carving", {**inputs(s), "images": ImageSet(s["images"].images[:7])})
    small = ImageSet([im[:40] for im in s["images"].images])
    with pytest.raises(NodeError, match="image of camera 'cam000' is 120x40"):
        run_node("carve.space_carving", {**inputs(s), "images": small})
    with pytest.raises(NodeError, match="min_views 9 is more than the 8 cameras"):
        run_node("carve.space_carving", inputs(s), {"min_views": 9})
    flat = VoxelGrid(np.zeros((4, 4), np.uint8), [0, 0, 0], [1, 1, 1])
    with pytest.raises(NodeError, match="3-D array"):
        run_node("carve.voxel_coloring", {**inputs(s), "volume": flat})


def test_colours_reach_the_mesh_and_survive_refine_and_relax(small_cup):
    s = small_cup
    vol = run_node("carve.space_carving", inputs(s), roundtrip=True)["volume"]
    assert vol.colors is not None
    mesh = run_node("mc", {"volume": vol}, roundtrip=True)["mesh"]
    assert mesh.visual.kind == "vertex"
    rgb = np.asarray(mesh.visual.vertex_colors)[:, :3]
    # each vertex lies on a grid edge: its colour is the colour of the edge's occupied end
    g = (np.asarray(mesh.vertices) - vol.bbox_min) / vol.voxel_size - 0.5
    axis = np.argmax(np.abs(g - np.round(g)), axis=1)
    lo = np.round(g).astype(int)
    lo[np.arange(len(g)), axis] = np.floor(g[np.arange(len(g)), axis]).astype(int)
    hi = lo.copy()
    hi[np.arange(len(g)), axis] += 1
    shape = np.array(vol.occupancy.shape)
    lo_in = np.all((lo >= 0) & (lo < shape), axis=1) & (vol.occupancy[tuple(np.clip(lo, 0, shape - 1).T)] > 0)
    inside = np.where(lo_in[:, None], lo, hi)
    assert np.array_equal(rgb, vol.colors[tuple(inside.T)])
    refined = run_node("refine", {"mesh": mesh, "volume": vol, "masks": s["masks"], "cameras": s["cameras"]},
                       roundtrip=True)["mesh"]
    assert refined.visual.kind == "vertex" and len(refined.visual.vertex_colors) == len(refined.vertices)
    got = np.asarray(refined.visual.vertex_colors)[:, :3]
    if len(refined.vertices) == len(mesh.vertices):  # mc's vertices, moved: their own colours
        assert np.array_equal(got, rgb)
    else:  # a fold's edge collapsed: every vertex still carries a colour of the carved volume's surface
        assert {tuple(c) for c in got} <= {tuple(c) for c in rgb}
    relaxed = run_node("relax", {"mesh": refined, "masks": s["masks"], "cameras": s["cameras"]}, roundtrip=True)["mesh"]
    before, after = np.asarray(refined.visual.vertex_colors), np.asarray(relaxed.visual.vertex_colors)
    if len(relaxed.vertices) == len(refined.vertices):
        assert np.array_equal(after, before)
    else:  # relax collapsed a fold's edge
        assert len(after) == len(relaxed.vertices) and {tuple(c) for c in after} <= {tuple(c) for c in before}
    for m in (refined, relaxed):  # whatever collapsed, the faces index the vertices there are
        assert m.faces.max() < len(m.vertices) and m.is_watertight


def test_fill_colours_matches_its_reference():
    """The unseen surface voxels' colours from their coloured neighbours: the same bytes as the whole-grid version,
    on a blob at the grid's border with unseen patches several rounds deep, and with nothing seen."""
    rng = np.random.default_rng(3)
    z, y, x = np.mgrid[:20, :18, :16]
    occ = ((x - 7.5) ** 2 + (y - 9) ** 2 + (z - 4) ** 2 < 60).astype(np.uint8)     # cut by the grid's z = 0 face
    views = (rng.random(occ.shape) < 0.5).astype(np.uint8) * occ
    views[:, :, :6] = 0                                                         # unseen more than a ring deep
    colors = (rng.integers(0, 256, occ.shape + (3,)) * occ[..., None]).astype(np.uint8)
    for v in (views, np.zeros_like(views)):
        got, want = fill_colours(occ, colors, v), fill_colours_reference(occ, colors, v)
        assert np.array_equal(got, want)
    filled = fill_colours(occ, colors, views, rounds=2)
    assert not np.array_equal(filled, colors) and np.array_equal(filled, fill_colours_reference(occ, colors, views, 2))


def test_sweep_lists_match_their_reference(small_cup):
    occ = (np.asarray(small_cup["hull"].occupancy) > 0).astype(np.uint8)
    occ[0, 3, 2] = 1          # a voxel on the grid's border
    long = (np.random.default_rng(4).random((3, 300, 2)) < 0.5).astype(np.uint8)   # planes beyond an 8-bit key
    for grid in (occ, long, np.zeros((2, 1, 3), np.uint8)):
        got, want = sweep_lists(grid), sweep_lists_reference(grid)
        assert got.keys() == want.keys()
        for k in got:
            assert got[k].dtype == want[k].dtype and np.array_equal(got[k], want[k]), k


def test_golden_space_carving(small_cup, golden):
    out = run_node("carve.space_carving", inputs(small_cup), roundtrip=True)
    golden.check("carve_cup_16", out["volume"], Volume)


def test_golden_voxel_coloring(small_cup, golden):
    out = run_node("carve.voxel_coloring", inputs(small_cup), roundtrip=True)
    golden.check("carve_vc_cup_16", out["volume"], Volume)


@pytest.mark.slow
@pytest.mark.realdata
def test_temple_photo_hull(data_dir):
    """Middlebury templeSR at 64^3: the carved temple stays one piece, covers the masks as the hull does (no
    hole through it), and its surface colours agree better across views than the hull's."""
    from scipy import ndimage

    cap = run_node("capture", {}, {"path": str(data_dir / "middlebury_templeSR")})
    masks = run_node("key.threshold", {"images": cap["images"]}, {"threshold": 0.19, "dilate": 10, "erode": 7})["masks"]
    hull = run_node("hull", {"masks": masks, "cameras": cap["cameras"]},
                    {"resolution": 64, "bbox": [-0.047606, -0.031878, -0.063887, 0.054817, 0.043303, 0.096277]})["volume"]
    args = {"volume": hull, "images": cap["images"], "masks": masks, "cameras": cap["cameras"]}
    out = run_node("carve.space_carving", args)
    occ = out["volume"].occupancy
    assert 0.02 * hull.occupancy.sum() < hull.occupancy.sum() - occ.sum() < 0.3 * hull.occupancy.sum()
    labels, n = ndimage.label(occ)
    assert n == 1 or np.bincount(labels.ravel())[1:].max() >= 0.999 * occ.sum()
    cover = []
    for vol in (hull, out["volume"]):
        m = run_node("mc", {"volume": vol}, {"largest": True})["mesh"]
        sil = raster.silhouette(m.vertices, m.faces, cap["cameras"])
        cover.append(sum(int(((mk > 127) & (s > 0)).sum()) for mk, s in zip(masks.masks, sil)))
    assert cover[1] >= 0.995 * cover[0], f"mask pixels covered: hull {cover[0]}, carved {cover[1]}"
    hull_var = run_node("carve.space_carving", args, {"max_passes": 0})["report"]["variance_out"]
    assert out["report"]["variance_out"] < 0.85 * hull_var
