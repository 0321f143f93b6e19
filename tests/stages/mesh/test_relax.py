"""relax: Taubin lambda|mu smoothing that keeps the silhouettes (kernel vs NumPy vs trimesh, synthetic quality)."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from test_refine import FIGURE, ball_masks, figure_case, hull_volume, plain_mc, real_chain, rig, silhouette_errors

from nodes.common.types import Mesh
from nodegraph import NodeError
from nodegraph.testing import run_node
from nodes.eval.silhouette import silhouette_report
from nodes.common.silhouettes import Silhouettes
from nodes.mesh.relax import LAMBDA, MU, taubin_cl, taubin_reference
from nodes.common.meshops import vertex_neighbours


def roughness(mesh) -> float:
    """Mean angle between the normals of adjacent faces, degrees."""
    return float(np.degrees(mesh.face_adjacency_angles.mean()))


def noisy_sphere(seed=0):
    m = trimesh.creation.icosphere(3)
    rng = np.random.default_rng(seed)
    return trimesh.Trimesh(m.vertices * (1 + 0.03 * rng.standard_normal((len(m.vertices), 1))), m.faces, process=False)


def test_neighbours_are_the_mesh_edges():
    m = noisy_sphere()
    offsets, nb = vertex_neighbours(m.faces, len(m.vertices))
    assert offsets[-1] == 2 * len(m.edges_unique)
    for i in (0, 17, 300):
        assert sorted(nb[offsets[i] : offsets[i + 1]]) == sorted(m.vertex_neighbors[i])


def test_kernel_matches_reference_and_trimesh():
    m = noisy_sphere()
    offsets, nb = vertex_neighbours(m.faces, len(m.vertices))
    got = taubin_cl(m.vertices, offsets, nb, 5)
    want = taubin_reference(m.vertices, offsets, nb, 5)
    assert np.abs(got - want).max() < 1e-6
    # trimesh counts half-steps and takes mu as a positive number
    base = trimesh.smoothing.filter_taubin(m.copy(), lamb=LAMBDA, nu=-MU, iterations=10)
    assert np.abs(got - base.vertices).max() < 1e-5
    assert roughness(trimesh.Trimesh(got, m.faces)) < 0.6 * roughness(m)


def test_relax_numpy_method_matches_opencl():
    cams, masks, views, vol, mesh = figure_case(20, count=4, size=64, soft=True)
    args = {"mesh": mesh, "masks": masks, "cameras": cams}
    got = run_node("relax", args, {"iterations": 3})["mesh"].vertices
    want = run_node("relax", args, {"iterations": 3, "method": "numpy"})["mesh"].vertices
    reach = float(mesh.edges_unique_length.mean())
    close = np.linalg.norm(got - want, axis=1) < 1e-5
    assert close.mean() > 0.99, close.mean()
    assert np.abs(got - want).max() < 2 * reach / 2**10
    free = run_node("relax", {"mesh": mesh}, {"iterations": 3, "keep_silhouettes": False})["mesh"].vertices
    assert (np.linalg.norm(free - want, axis=1) > 1e-4).sum() > 10  # the clamp did act


def test_relax_keeps_silhouettes_and_removes_roughness():
    cams, masks, views, vol, mesh = figure_case(128)
    refined = run_node("refine", {"mesh": mesh, "volume": vol, "masks": masks, "cameras": cams})["mesh"]
    out = run_node("relax", {"mesh": refined, "masks": masks, "cameras": cams}, roundtrip=True)["mesh"]
    free = run_node("relax", {"mesh": refined}, {"keep_silhouettes": False})["mesh"]
    np.testing.assert_array_equal(out.faces, refined.faces)
    iou0, out0, miss0 = silhouette_errors(refined, masks, cams)
    iou1, out1, miss1 = silhouette_errors(out, masks, cams)
    r0, r1 = roughness(refined), roughness(out)
    print(f"mean IoU {iou0.mean():.5f} -> {iou1.mean():.5f} (max view drop {(iou0 - iou1).max():.5f}); "
          f"outside {out0} -> {out1}, missed {miss0} -> {miss1}; roughness {r0:.2f} -> {r1:.2f} deg "
          f"(free Taubin {roughness(free):.2f}); volume {out.volume / refined.volume:.4f}")
    assert iou0.mean() - iou1.mean() <= 0.002
    assert r1 <= 0.5 * r0
    assert out1 <= out0 + 10  # no growth past the silhouettes
    assert out.is_watertight and out.volume > 0.99 * refined.volume


def test_sphere_hausdorff_after_refine_and_relax():
    """64^3 hull of a unit ball from 40 cameras (soft alpha): every surface point within 0.25 voxel."""
    cams = rig(40, 128, fov=35)
    masks = ball_masks([((0, 0, 0), 1.0)], cams)
    views = Silhouettes.from_inputs(masks, cams)
    vol = hull_volume(views, [[-1.15] * 3, [1.15] * 3], 64)
    mesh = plain_mc(vol)
    refined = run_node("refine", {"mesh": mesh, "volume": vol, "masks": masks, "cameras": cams})["mesh"]
    out = run_node("relax", {"mesh": refined, "masks": masks, "cameras": cams})["mesh"]
    voxel = vol.voxel_size[0]

    def hausdorff(m):  # the mesh is star-shaped around the centre: radial error of vertices and surface samples
        pts = np.vstack([m.vertices, trimesh.sample.sample_surface(m, 20000, seed=0)[0]])
        return np.abs(np.linalg.norm(pts, axis=1) - 1).max() / voxel

    h = [hausdorff(m) for m in (mesh, refined, out)]
    print(f"Hausdorff to the sphere, voxels: plain MC {h[0]:.3f}, refined {h[1]:.3f}, refined + relaxed {h[2]:.3f}")
    assert h[2] <= 0.25
    assert h[0] > 0.4  # the plain grid is visibly off: the test can tell


def test_relax_golden(golden):
    cams, masks, views, vol, mesh = figure_case(12, count=4, size=48)
    refined = run_node("refine", {"mesh": mesh, "volume": vol, "masks": masks, "cameras": cams}, {"steps": 12})["mesh"]
    out = run_node("relax", {"mesh": refined, "masks": masks, "cameras": cams}, {"iterations": 4})["mesh"]
    golden.check("relax_figure_12", out, Mesh, hausdorff=1e-3 * vol.voxel_size[0])


def test_relax_needs_masks_to_keep_silhouettes():
    m = noisy_sphere()
    with pytest.raises(NodeError, match="keep_silhouettes needs the 'masks' and 'cameras'"):
        run_node("relax", {"mesh": m})
    cams = rig(3, 32)
    masks = ball_masks(FIGURE, cams)
    with pytest.raises(NodeError, match="relax: 2 masks for 3 cameras"):
        run_node("relax", {"mesh": m, "masks": type(masks)(masks.masks[:2]), "cameras": cams})


@pytest.mark.realdata
@pytest.mark.parametrize("name", ["thu_wd_human", "inria_dancer"])
def test_real_relax_after_refine(dataset_run, name):
    """Issue 5 target at 128^3: relax after refine drops the mean IoU by <= 0.002 while roughness drops clearly
    (measured: thu_wd_human IoU 0.9730 -> 0.9721, roughness 20.0 -> 10.9 deg; inria_dancer 0.9588 -> 0.9574,
    19.7 -> 10.7 deg); no more mesh pixels outside the masks."""
    masks, cams, _, ref, out = real_chain(dataset_run, name)
    a = silhouette_report(ref.vertices, ref.faces, cams, masks)
    b = silhouette_report(out.vertices, out.faces, cams, masks)
    ra, rb = roughness(ref), roughness(out)
    print(f"{name} relax: IoU {a['mean_iou']:.4f} -> {b['mean_iou']:.4f}, outside {a['mesh_outside_mask']} -> "
          f"{b['mesh_outside_mask']}, not covered {a['mask_not_covered']} -> {b['mask_not_covered']}, "
          f"roughness {ra:.2f} -> {rb:.2f} deg")
    assert a["mean_iou"] - b["mean_iou"] <= 0.002
    assert rb <= 0.7 * ra
    assert b["mesh_outside_mask"] <= a["mesh_outside_mask"]
    assert out.is_watertight
