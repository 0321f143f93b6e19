"""The smooth silhouette field and its searches (kernels/hullfit.cl vs the NumPy references in
nodes/mesh/hullfit.py): packed bits, the field along a straight edge, the point test, segment crossings, the
search along directions and the shell interval, for binary and soft masks and every vote rule."""
from __future__ import annotations

import numpy as np
import pytest
from meshcases import figure_case, rig

from nodes.common.cameras import Cameras, look_at
from nodes.common.types import MaskSet
from nodes.mesh.hullfit import (FieldCL, SilhouetteField, active_views_reference, ball_cull, cross_reference, inside_at,
                                level_of, onto_reference, shell_interval_reference, split_cull, view_values)
from nodes.mesh.refine import lattice_edges


def test_levels_of_a_straight_edge():
    """level_of: 0.5 on the pixel edge, slope 1 per pixel there, 0 / 1 a pixel and a half away; the field of a
    view whose mask has a vertical edge matches it along a row."""
    assert level_of(0) == pytest.approx(0.5)
    assert level_of(0.5) == pytest.approx(0.875) and level_of(-0.5) == pytest.approx(0.125)
    assert level_of(1.5) == pytest.approx(1.0) and level_of(-1.5) == pytest.approx(0.0)
    assert (level_of(0.01) - level_of(-0.01)) / 0.02 == pytest.approx(1.0, rel=1e-2)
    cam = look_at((0, 0, 5), (0, 0, 0), (0, 1, 0), 40, 40, 30)
    m = np.zeros((30, 40), np.uint8)
    m[:, :20] = 255                                  # inside left of the pixel edge u = 19.5
    field = SilhouetteField.from_inputs(MaskSet([m]), Cameras([cam]), np.zeros(3))
    u = np.linspace(17.0, 22.0, 41)
    rays = Cameras([cam]).rays(0, np.stack([u, np.full_like(u, 14.0)], 1))
    pts = (rays[0] + 5 * rays[1] / rays[1][:, 2:3] * np.sign(rays[1][:, 2:3])).astype(np.float32)
    f = view_values(pts, field, 0)
    want = [level_of(19.5 - x) for x in u]
    np.testing.assert_allclose(f, want, atol=2e-3)


def test_a_keys_8_bit_alpha_gives_the_same_levels_as_its_float_alpha():
    """The keys' MaskSet carries its soft alpha as 8-bit levels: the field takes them as they are (no float alpha
    made), the levels rint(alpha * 255) of the same alpha read as float32 give, bit for bit."""
    cams, masks, vol, _ = figure_case(24, count=3, size=61, soft=True)
    levels = [np.clip(np.rint(np.asarray(a, np.float32) * 255), 0, 255).astype(np.uint8) for a in masks.alpha]
    eight = MaskSet(list(masks.masks), None, list(masks.names), alpha8=levels)
    as_float = MaskSet(list(masks.masks), [np.divide(a, np.float32(255), dtype=np.float32) for a in levels], list(masks.names))
    origin = 0.5 * (vol.bbox_min + vol.bbox_max)
    a, b = SilhouetteField.from_inputs(eight, cams, origin), SilhouetteField.from_inputs(as_float, cams, origin)
    assert a.soft and b.soft and eight._alpha is None, "the float alpha was never made"
    for x, y in zip(a.masks, b.masks):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("soft", [False, True])
def test_kernels_match_reference(soft):
    cams, masks, vol, mesh = figure_case(24, count=5, size=61, soft=soft)  # odd width: partial bit bytes
    origin = 0.5 * (vol.bbox_min + vol.bbox_max)
    field = SilhouetteField.from_inputs(masks, cams, origin)
    assert field.soft == soft
    fc = FieldCL.get().prepare(field)
    if not soft:
        want = [np.packbits(m > 127, axis=1, bitorder="little").ravel() for m in masks.masks]  # SilhouetteBits
        np.testing.assert_array_equal(fc.pixels(), np.concatenate(want))
    rng = np.random.default_rng(1)
    pts = rng.uniform(-0.8, 0.9, (3000, 3)).astype(np.float32)
    for tau in (0.125, 0.5, 0.875):
        want = inside_at(pts, field, tau)
        assert 300 < want.sum() < 2700  # both kinds of point present
        np.testing.assert_array_equal(fc.inside_host(pts, tau), want)

    a, b, ok = lattice_edges(mesh.vertices, vol)
    a, b = (a[ok] - origin).astype(np.float32), (b[ok] - origin).astype(np.float32)
    keep = 0.5 * (a + b)
    got, found = fc.cross_host(a, b, keep, 0.5, 8)
    want, found_ref = cross_reference(a, b, keep, field, 0.5, 8)
    assert found.mean() > 0.7  # 2.5 pixels per voxel, a 4-pixel alpha ramp: the nearest-pixel grid and the field differ
    np.testing.assert_array_equal(found, found_ref)
    assert (np.abs(got - want).max(axis=1) == 0).mean() > 0.999  # same float32 arithmetic: bit for bit
    assert np.abs(got - want).max() < 1e-3 * vol.voxel_size[0]
    # the crossing is on level 0.5: just inside is in, just outside is out
    d = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
    eps = 1e-3 * vol.voxel_size[0]
    assert inside_at(got[found] - eps * d[found], field, 0.5).mean() > 0.99
    assert (~inside_at(got[found] + eps * d[found], field, 0.5)).mean() > 0.99

    voxel = float(vol.voxel_size[0])
    p = (mesh.vertices - origin).astype(np.float32)
    n = mesh.vertex_normals.astype(np.float32)
    got, found = fc.onto_host(p, n, voxel, 0.5, 8)
    want, found_ref = onto_reference(p, n, voxel, field, 0.5, 8)
    assert found.mean() > 0.95
    np.testing.assert_array_equal(found, found_ref)
    assert np.abs(got - want).max() < 1e-3 * voxel

    shell = fc.shell_host(p, n, voxel, level_of(0.3), level_of(-0.3), 8)
    want = shell_interval_reference(p, n, voxel, field, level_of(0.3), level_of(-0.3), 8)
    assert np.abs(shell - want).max() < 1e-4
    ok = (shell[:, 1] > 0) & (shell[:, 2] < 1)
    assert ok.mean() > 0.8 and np.all(shell[ok, 1] <= shell[ok, 2] + 1e-6)  # the eroded exit comes first


@pytest.mark.parametrize("min_views, outside", [(4, "carve"), (0, "ignore")])
def test_other_vote_rules_match_reference(min_views, outside):
    """min_views and the ignore policy take the vote's own bisection: kernel == NumPy, and min_views 4 of 5
    gives a bigger hull than the strict vote."""
    cams, masks, vol, mesh = figure_case(20, count=5, size=48)
    origin = 0.5 * (vol.bbox_min + vol.bbox_max)
    field = SilhouetteField.from_inputs(masks, cams, origin, min_views, outside)
    fc = FieldCL.get().prepare(field)
    pts = np.random.default_rng(2).uniform(-1.2, 1.2, (2000, 3)).astype(np.float32)
    want = inside_at(pts, field, 0.5)
    np.testing.assert_array_equal(fc.inside_host(pts, 0.5), want)
    strict = inside_at(pts, SilhouetteField.from_inputs(masks, cams, origin), 0.5)
    assert want.sum() >= strict.sum() and not np.any(strict & ~want)
    p = (mesh.vertices - origin).astype(np.float32)
    n = mesh.vertex_normals.astype(np.float32)
    voxel = float(vol.voxel_size[0])
    got, found = fc.onto_host(p, n, voxel, 0.5, 6)
    ref, found_ref = onto_reference(p, n, voxel, field, 0.5, 6)
    assert found.mean() > 0.5 and (found == found_ref).mean() > 0.99
    both = found & found_ref
    assert np.abs(got[both] - ref[both]).max() < 1e-3 * voxel


def test_field_checks_name_the_camera():
    from nodegraph import NodeError

    cams = rig(3, 32)
    masks = [np.zeros((32, 32), np.uint8) for _ in range(3)]
    alpha = [np.zeros((32, 32), np.float32) for _ in range(3)]
    alpha[1] = np.full((32, 32), np.nan, np.float32)
    with pytest.raises(NodeError, match="cam001.*NaN"):
        SilhouetteField.from_inputs(MaskSet(masks, alpha), cams, np.zeros(3))
    with pytest.raises(NodeError, match="min_views 4"):
        SilhouetteField.from_inputs(MaskSet(masks), cams, np.zeros(3), min_views=4)


@pytest.mark.parametrize("soft, distorted", [(False, False), (True, False), (False, True)])
def test_view_culling_is_exact(soft, distorted):
    """active_views (kernel == NumPy): a view marked inactive sees every point of the vertex's ball at field 1
    (so it cannot cut a search there), about half the views are skipped, and the searches with the cull give
    the very same results as without it (bit for bit), also for segments that leave the ball (all views)."""
    cams, masks, vol, mesh = figure_case(32, count=6, size=256, soft=soft)
    if distorted:  # strong lens distortion and a skewed, non-square pixel: the ball's projected bound must hold
        for k, c in enumerate(cams):
            c.dist = np.array([-0.25, 0.08, 0.002, -0.003, 0.01]) * (1 + 0.2 * k)
            c.K[0, 1], c.K[1, 1] = 0.4, 1.1 * c.K[1, 1]
        masks = ball_masks_from(cams, masks)
    origin = 0.5 * (vol.bbox_min + vol.bbox_max)
    field = SilhouetteField.from_inputs(masks, cams, origin)
    fc = FieldCL.get().prepare(field)
    voxel = float(vol.voxel_size[0])
    p = (mesh.vertices - origin).astype(np.float32)
    radius = 0.8 * voxel  # 4.7 pixels
    cull = fc.active(ball_cull(p, radius))
    np.testing.assert_array_equal(cull["act"], active_views_reference(cull["cull"], field))
    bits = np.unpackbits(cull["act"].view(np.uint8), axis=1, bitorder="little")[:, :len(cams)].astype(bool)
    print(f"active views {bits.mean():.2f}")
    assert 0.1 < bits.mean() < 0.75
    rng = np.random.default_rng(4)
    for v in range(len(cams)):  # points spread over each ball (its surface too) where view v is inactive
        idle = np.flatnonzero(~bits[:, v])
        d = rng.standard_normal((len(idle), 3))
        d *= (radius * rng.uniform(0.5, 1.0, (len(idle), 1)) ** 0.3) / np.linalg.norm(d, axis=1, keepdims=True)
        assert np.all(view_values((p[idle] + d).astype(np.float32), field, v) == 1.0)
    n = mesh.vertex_normals.astype(np.float32)
    for reach in (0.25 * voxel, 3.0 * voxel):  # within the balls; beyond them (every view visited)
        want = fc.shell_host(p, n, reach, 0.5, level_of(-0.4), 8)
        np.testing.assert_array_equal(fc.shell_host(p, n, reach, 0.5, level_of(-0.4), 8, cull), want)
        got, found = fc.onto_host(p, n, reach, 0.5, 8, cull)
        np.testing.assert_array_equal(got, fc.onto_host(p, n, reach, 0.5, 8)[0])
    a, b, ok = lattice_edges(mesh.vertices, vol)
    a, b = (a - origin).astype(np.float32), (b - origin).astype(np.float32)
    np.testing.assert_array_equal(fc.cross_host(a, b, p, 0.5, 8, cull)[0], fc.cross_host(a, b, p, 0.5, 8)[0])
    # the cull of points split from edges: balls inside both ends' balls, views active for both
    edges = np.array([[0, 1], [2, 3]])
    sub = split_cull(cull, edges)
    assert len(sub["cull"]) == len(p) + 2
    np.testing.assert_array_equal(sub["act"][-2:], cull["act"][[0, 2]] & cull["act"][[1, 3]])


def ball_masks_from(cams, masks):
    from meshcases import FIGURE, ball_masks

    return MaskSet(ball_masks(FIGURE, cams).masks, None if masks.alpha is None else ball_masks(FIGURE, cams).alpha)
