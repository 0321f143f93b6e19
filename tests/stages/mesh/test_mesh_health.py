"""eval.mesh: folded edges, minimum angles, roughness and the normal error against a reference, on meshes whose
answers are known."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from nodegraph import NodeError
from nodegraph.testing import run_node
from nodes.eval.health import mesh_health, triangle_min_angles
from nodes.common.types import VoxelGrid


def test_min_angles_of_known_triangles():
    v = np.array([[0, 0, 0], [1, 0, 0], [0.5, np.sqrt(3) / 2, 0], [0, 1, 0], [10, 0.5, 0]], float)
    f = np.array([[0, 1, 2], [0, 1, 3], [0, 1, 4], [0, 0, 1]])
    np.testing.assert_allclose(triangle_min_angles(v, f), [60, 45, np.degrees(np.arctan2(0.5, 9) - np.arctan2(0.5, 10)), 0], atol=0.05)


@pytest.mark.slow
def test_folds_roughness_and_normal_error():
    cube = trimesh.creation.box()
    h = run_node("eval.mesh", {"mesh": cube})["report"]
    assert h["folded_edges"] == 0 and h["faces"] == 12 and h["watertight"]
    # cube: 12 edges at 90 degrees and 6 face diagonals at 0
    assert h["roughness_deg"] == pytest.approx(90 * 12 / 18)
    assert h["min_angle_below_5"] == 0 and h["min_angle_median_deg"] == pytest.approx(45)
    # fold: a square of two triangles whose fourth corner is pulled across the shared diagonal
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    assert mesh_health(trimesh.Trimesh(v, f, process=False))["folded_edges"] == 0
    v[3] = [0.8, 0.2, 0.01]
    assert mesh_health(trimesh.Trimesh(v, f, process=False))["folded_edges"] == 1
    s = trimesh.creation.icosphere(2)
    assert mesh_health(s)["folded_edges"] == 0
    # normal error: 0 against itself; a sphere against a finer one: the facets' small tilt; the band filters
    ref = trimesh.creation.icosphere(5)
    vol = VoxelGrid(np.zeros((10, 10, 10), np.uint8), [-1, -1, -1], [1, 1, 1])   # voxel 0.2
    own = run_node("eval.mesh", {"mesh": ref, "reference": ref, "volume": vol})["report"]
    assert own["normal_error_mean_deg"] < 0.5 and own["area_within_band"] == pytest.approx(1.0)
    coarse = run_node("eval.mesh", {"mesh": s, "reference": ref}, {"band": 0.2})["report"]
    assert coarse["normal_error_mean_deg"] < 2  # at its centroid a facet is parallel to the sphere
    rng = np.random.default_rng(0)
    noisy = trimesh.Trimesh(s.vertices * (1 + 0.03 * rng.standard_normal((len(s.vertices), 1))), s.faces)
    rough = run_node("eval.mesh", {"mesh": noisy, "reference": ref}, {"band": 0.2})["report"]
    assert 5 < rough["normal_error_mean_deg"] < 30 and rough["roughness_deg"] > coarse["roughness_deg"] + 2
    moved = trimesh.Trimesh(s.vertices + [0.5, 0, 0], s.faces)
    far = run_node("eval.mesh", {"mesh": moved, "reference": ref}, {"band": 0.05})["report"]
    assert far["area_within_band"] < 0.5
    with pytest.raises(NodeError, match="needs a band"):
        run_node("eval.mesh", {"mesh": s, "reference": ref})
