"""relax: fairing inside the silhouette shell (synthetic quality, sphere accuracy, NumPy vs OpenCL, golden,
errors, real data)."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from meshcases import ball_masks, figure_case, plain_mc, real_meshes, rig, silhouette_errors, FIGURE

from nodegraph import NodeError
from nodegraph.testing import run_node
from nodes.common.types import MaskSet, Mesh
from nodes.eval.health import mesh_health
from nodes.eval.silhouette import silhouette_report
from nodes.hull.hull import visual_hull


def test_relax_keeps_silhouettes_and_removes_roughness():
    """128^3 figure: relax after refine keeps the mean IoU within 0.002, halves the roughness, leaves no fold and
    no sliver, keeps the faces and (almost) the volume."""
    cams, masks, vol, mesh = figure_case(128)
    refined = run_node("refine", {"mesh": mesh, "volume": vol, "masks": masks, "cameras": cams})["mesh"]
    out = run_node("relax", {"mesh": refined, "masks": masks, "cameras": cams}, roundtrip=True)["mesh"]
    free = run_node("relax", {"mesh": refined}, {"keep_silhouettes": False})["mesh"]
    np.testing.assert_array_equal(out.faces, refined.faces)
    (iou0, out0, miss0), (iou1, out1, miss1), (iouf, _, _) = (silhouette_errors(m, masks, cams) for m in (refined, out, free))
    h_mc, h0, h1 = mesh_health(mesh), mesh_health(refined), mesh_health(out)
    print(f"mean IoU {iou0.mean():.5f} -> {iou1.mean():.5f} (free {iouf.mean():.5f}); outside {out0} -> {out1}, missed "
          f"{miss0} -> {miss1}; roughness mc {h_mc['roughness_deg']:.2f}, refined {h0['roughness_deg']:.2f} -> "
          f"{h1['roughness_deg']:.2f} deg; volume {out.volume / refined.volume:.4f}")
    assert iou0.mean() - iou1.mean() <= 0.002 and iou1.min() >= 0.99
    assert h1["roughness_deg"] <= 0.5 * h_mc["roughness_deg"] and h1["roughness_deg"] < h0["roughness_deg"]
    assert h1["folded_edges"] == 0 and h1["min_angle_below_5"] <= 0.005
    assert out.is_watertight and abs(out.volume / refined.volume - 1) < 0.01


def test_sphere_accuracy_and_normals():
    """64^3 hull of a unit ball from 40 cameras (soft alpha): every surface point within 0.25 voxel of the
    sphere after refine + relax, and the face normals' mean error against the sphere's at most half of plain
    marching cubes'."""
    cams = rig(40, 128, fov=35)
    masks = ball_masks([((0, 0, 0), 1.0)], cams)
    vol = visual_hull(masks, cams, np.array([[-1.15] * 3, [1.15] * 3]), 64)
    mesh = plain_mc(vol)
    refined = run_node("refine", {"mesh": mesh, "volume": vol, "masks": masks, "cameras": cams})["mesh"]
    out = run_node("relax", {"mesh": refined, "masks": masks, "cameras": cams})["mesh"]
    voxel = vol.voxel_size[0]

    def hausdorff(m):  # the mesh is star-shaped around the centre: radial error of vertices and surface samples
        pts = np.vstack([m.vertices, trimesh.sample.sample_surface(m, 20000, seed=0)[0]])
        return np.abs(np.linalg.norm(pts, axis=1) - 1).max() / voxel

    def normal_error(m):
        c = m.triangles_center
        cos = np.einsum("ij,ij->i", m.face_normals, c / np.linalg.norm(c, axis=1, keepdims=True))
        return float(np.degrees(np.arccos(np.clip(cos, -1, 1))) @ m.area_faces / m.area)

    h = [hausdorff(m) for m in (mesh, refined, out)]
    e = [normal_error(m) for m in (mesh, refined, out)]
    print(f"Hausdorff to the sphere, voxels: plain MC {h[0]:.3f}, refined {h[1]:.3f}, relaxed {h[2]:.3f}; normal error "
          f"{e[0]:.2f} / {e[1]:.2f} / {e[2]:.2f} deg")
    assert h[2] <= 0.25 and h[0] > 0.4  # the plain grid is visibly off: the test can tell
    assert e[2] <= 0.5 * e[0]


def test_relax_numpy_method_matches_opencl():
    cams, masks, vol, mesh = figure_case(20, count=4, size=64, soft=True)
    args = {"mesh": mesh, "masks": masks, "cameras": cams}
    got = run_node("relax", args, {"iterations": 3})["mesh"].vertices
    want = run_node("relax", args, {"iterations": 3, "method": "numpy"})["mesh"].vertices
    assert np.abs(got - want).max() < 1e-4 * vol.voxel_size[0]
    free = run_node("relax", {"mesh": mesh}, {"iterations": 3, "keep_silhouettes": False})["mesh"].vertices
    assert (np.linalg.norm(free - want, axis=1) > 1e-4).sum() > 10  # the shell did act


def test_relax_golden(golden):
    cams, masks, vol, mesh = figure_case(12, count=4, size=48)
    refined = run_node("refine", {"mesh": mesh, "volume": vol, "masks": masks, "cameras": cams})["mesh"]
    out = run_node("relax", {"mesh": refined, "masks": masks, "cameras": cams}, {"iterations": 4})["mesh"]
    golden.check("relax_figure_12", out, Mesh, hausdorff=1e-3 * vol.voxel_size[0])


def test_relax_errors():
    m = trimesh.creation.icosphere(2)
    with pytest.raises(NodeError, match="keep_silhouettes needs the 'masks' and 'cameras'"):
        run_node("relax", {"mesh": m})
    cams = rig(3, 32)
    masks = ball_masks(FIGURE, cams)
    with pytest.raises(NodeError, match="relax: 2 masks for 3 cameras"):
        run_node("relax", {"mesh": m, "masks": MaskSet(masks.masks[:2]), "cameras": cams})
    with pytest.raises(NodeError, match="shell is empty"):
        run_node("relax", {"mesh": m, "masks": masks, "cameras": cams}, {"inside_px": -0.5, "outside_px": 0.2})


@pytest.mark.realdata
@pytest.mark.parametrize("name, iou", [("thu_wd_human", 0.966), ("inria_dancer", 0.945)])
def test_real_relax_after_refine(data_dir, name, iou):
    """128^3, shipped masks: after refine + relax no folded edge, no triangle under 5 degrees, faces as mc's,
    roughness below refine's, mean IoU above plain mc's (measured: thu_wd_human IoU 0.9584 mc -> 0.9677,
    roughness 16.3 -> 8.2 deg; inria_dancer 0.9295 -> 0.9483, 17.2 -> 8.4 deg). Below the seed's refine with
    2 split rounds (0.973 / 0.959, at 3.7x / 2.2x mc's faces): see the README."""
    masks, cams, vol, mesh = real_meshes(data_dir, name, 128)
    ref = run_node("refine", {"mesh": mesh, "volume": vol, "masks": masks, "cameras": cams})["mesh"]
    out = run_node("relax", {"mesh": ref, "masks": masks, "cameras": cams})["mesh"]
    a, b = (silhouette_report(m.vertices, m.faces, cams, masks) for m in (mesh, out))
    h_ref, h = mesh_health(ref), mesh_health(out)
    print(f"{name}: IoU mc {a['mean_iou']:.4f} -> relaxed {b['mean_iou']:.4f}, outside {a['mesh_outside_mask']} -> "
          f"{b['mesh_outside_mask']}, not covered {a['mask_not_covered']} -> {b['mask_not_covered']}; roughness "
          f"{h_ref['roughness_deg']:.2f} -> {h['roughness_deg']:.2f}; folds {h['folded_edges']}, slivers {h['min_angle_below_5']:.4%}")
    assert h["folded_edges"] == 0 and h["min_angle_below_5"] <= 0.005 and h["faces"] == len(mesh.faces)
    assert b["mean_iou"] >= iou and b["mean_iou"] > a["mean_iou"]
    assert h["roughness_deg"] < h_ref["roughness_deg"]
    assert out.is_watertight


def test_relax_computes_from_its_inputs_alone():
    """relax's result depends on the refined mesh's vertices and faces, not on the object refine made (refine once
    hung its last search on it: relax then differed in every vertex under the same cache key)."""
    cams, masks, vol, mesh = figure_case(64)
    refined = run_node("refine", {"mesh": mesh, "volume": vol, "masks": masks, "cameras": cams})["mesh"]
    handed = run_node("relax", {"mesh": refined, "masks": masks, "cameras": cams})["mesh"]
    alone = run_node("relax", {"mesh": trimesh.Trimesh(refined.vertices.copy(), refined.faces.copy(), process=False),
                               "masks": masks, "cameras": cams}, roundtrip=True)["mesh"]
    np.testing.assert_array_equal(handed.vertices, alone.vertices)
    np.testing.assert_array_equal(handed.faces, alone.faces)
    assert mesh_health(handed)["folded_edges"] == 0
