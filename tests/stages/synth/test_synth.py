"""Rasterizer (kernel vs NumPy reference vs an independent cv2.fillPoly path) and the synth node."""
import cv2
import numpy as np
import pytest
import trimesh

from nodes.common.cameras import Cameras, look_at
from rig import ring_rig
from nodegraph import NodeError
from nodegraph.testing import run_node
from nodegraph.types import Array
from nodes.common.types import Masks
from nodes.common import raster
from nodes.synth import scenes
from nodes.synth.nodes import Synth


def fillpoly_silhouette(vertices, faces, cameras, view, scale=64):
    """Independent silhouette: every projected triangle filled by cv2.fillPoly on a ``scale``x finer grid
    over the mesh's bounding box, read back at the pixel centres (pixel centre (u, v) = fine pixel
    (scale u, scale v)). cv2 also fills pixels touching an edge, so it errs outwards by < 1/scale px."""
    cam = cameras[view]
    uv, z = cameras.project(vertices, view)
    assert (z > 0).all()
    x0, y0 = np.maximum(np.floor(uv.min(axis=0)).astype(int) - 1, 0)
    x1, y1 = np.minimum(np.ceil(uv.max(axis=0)).astype(int) + 1, [cam.width - 1, cam.height - 1])
    fine = np.zeros(((y1 - y0 + 1) * scale, (x1 - x0 + 1) * scale), np.uint8)
    pts = np.round((uv[faces] - [x0, y0]) * scale * 16).astype(np.int32)
    for tri in pts:
        cv2.fillPoly(fine, [tri], 255, lineType=cv2.LINE_8, shift=4)
    out = np.zeros((cam.height, cam.width), bool)
    out[y0:y1 + 1, x0:x1 + 1] = fine[::scale, ::scale] > 0
    return out


def iou(a, b):
    return np.logical_and(a, b).sum() / np.logical_or(a, b).sum()


def small_rig(width=80, height=60, k1=0.0, n=3):
    cams = ring_rig(n, width, height, radius=3.0, z=1.2, center=(0, 0, 0), target=(0, 0, 0.1), fov=45,
                    angles=np.linspace(0, 5, n), name="c{i}")
    cams[1].dist[0] = k1
    return cams


def two_spheres():
    a = trimesh.creation.icosphere(2, radius=0.6)
    b = trimesh.creation.icosphere(2, radius=0.35)
    b.apply_translation([0.5, 0.3, 0.4])      # overlapping: depth order matters
    return trimesh.util.concatenate([a, b])


def test_kernel_matches_reference():
    m = two_spheres()
    cams = small_rig(k1=-0.15)
    for view in range(len(cams)):
        t_cl, d_cl, b_cl = raster.MeshRaster(m.vertices, m.faces, cams).rasterize(view)
        t_np, d_np, b_np = raster.rasterize_reference(m.vertices, m.faces, cams, view)
        cov_cl, cov_np = t_cl >= 0, t_np >= 0
        assert cov_np.sum() > 500
        assert (cov_cl != cov_np).sum() <= 3, "coverage differs beyond exact edge ties"
        both = cov_cl & cov_np & (t_cl == t_np)
        assert both.sum() >= 0.99 * cov_np.sum()
        np.testing.assert_allclose(d_cl[both], d_np[both], rtol=1e-4)
        np.testing.assert_allclose(b_cl[both], b_np[both], atol=1e-3)
        assert np.isinf(d_cl[~cov_cl]).all() and (t_cl[~cov_cl] == -1).all()


def _box_depth(r, view, cull):
    """``MeshRaster.depth_box`` as a whole image of depths (inf: no face)."""
    zb, (x0, y0, w, h) = r.depth_box(view, cull)
    cam = r.cameras[view]
    out = np.full((cam.height, cam.width), np.inf, np.float32)
    box = r.run.read(zb, (h, w), np.uint32)
    out[y0:y0 + h, x0:x0 + w] = np.where(box == 0xFFFFFFFF, np.float32(np.inf), box.view(np.float32))
    return out


def test_depth_box_is_the_zbuffers_depth_and_culling_keeps_it():
    """raster_depth's depths, on the box of the mesh's projection only, are the 64-bit z-buffer's at every pixel
    (none outside the box); skipping the faces turned away keeps every depth on closed outward meshes seen from
    outside (two overlapping spheres with a distorted view, a concave cup), and ``MeshRaster.culls`` allows it
    only there: not for an open mesh, an inside-out one, or a camera inside the mesh's box."""
    from nodes.texture.reuse import Topology

    for m, cams in ((two_spheres(), small_rig(k1=-0.15)), (scenes.build("cup").mesh, small_rig(160, 120))):
        r = raster.MeshRaster(m.vertices, m.faces, cams)
        parts = Topology.of(m.faces, len(m.vertices)).closed_parts
        assert parts is not None and r.culls(parts) == [True] * len(cams)
        for view in range(len(cams)):
            full = r.rasterize(view)[1]
            assert np.isfinite(full).sum() > 500
            for cull in (False, True):
                assert np.array_equal(_box_depth(r, view, cull), full), (view, cull)
            ref = raster.rasterize_reference(m.vertices, m.faces, cams, view)[1]   # and the NumPy reference's
            got = _box_depth(r, view, True)
            both = np.isfinite(ref) & np.isfinite(got)
            assert (np.isfinite(ref) != np.isfinite(got)).sum() <= 3          # exact edge ties only
            np.testing.assert_allclose(got[both], ref[both], rtol=1e-4)
        # where culling is refused, and where it would be wrong
        f = np.asarray(m.faces)
        assert Topology.of(f[1:], len(m.vertices)).closed_parts is None                  # open
        inside_out = Topology.of(f[:, ::-1], len(m.vertices)).closed_parts
        assert inside_out is not None
        flipped = raster.MeshRaster(m.vertices, f[:, ::-1], cams)
        assert flipped.culls(inside_out) == [False] * len(cams)
        assert not np.array_equal(_box_depth(flipped, 0, True), flipped.rasterize(0)[1])   # culled: the far side
    inside = Cameras([look_at((0, 0, 0.3), (1, 0, 0.3), (0, 0, 1), 60, 40, 30, "in"), *small_rig(160, 120)])
    cup = scenes.build("cup").mesh
    r = raster.MeshRaster(cup.vertices, cup.faces, inside)
    assert r.culls(Topology.of(cup.faces, len(cup.vertices)).closed_parts) == [False, True, True, True]
    # a camera with the mesh behind it (faces dropped at the near plane), one whose lens folds back over the mesh
    away = look_at((2.0, 0, 0.3), (3.0, 0, 0.3), (0, 0, 1), 60, 40, 30, "away")
    folded = small_rig(160, 120)[1]
    folded.dist[0] = -40.0
    r = raster.MeshRaster(cup.vertices, cup.faces, Cameras([away, folded, small_rig(160, 120)[0]]))
    assert r.culls(Topology.of(cup.faces, len(cup.vertices)).closed_parts) == [False, False, True]
    # an inside-out sphere touching an outward one at a vertex (every edge still once each way, the volume in all
    # positive): two parts, one inside out, so no culling; an unused vertex changes nothing
    big = trimesh.creation.icosphere(2, radius=1.0)
    small = trimesh.creation.icosphere(2, radius=0.3)
    tip = int(np.argmax(big.vertices[:, 0]))
    sv = small.vertices + (big.vertices[tip] - small.vertices[int(np.argmin(small.vertices[:, 0]))])
    sf = small.faces[:, ::-1] + len(big.vertices)
    sf = np.where(sf == int(np.argmin(small.vertices[:, 0])) + len(big.vertices), tip, sf)
    v = np.vstack([big.vertices, sv, [[9.0, 9.0, 9.0]]])
    f = np.vstack([big.faces, sf])
    parts = Topology.of(f, len(v)).closed_parts
    assert parts is not None and len(np.unique(parts)) == 2
    cams = small_rig()
    assert raster.MeshRaster(v, f, cams).culls(parts) == [False] * len(cams)
    assert raster.MeshRaster(v, big.faces, cams).culls(Topology.of(big.faces, len(v)).closed_parts) == [True] * len(cams)


def test_cover_box_is_the_zbuffers_coverage_and_silhouette_iou_its_counts():
    """raster_cover's coverage on the mesh's box is the z-buffer's (kernel coverage) at every pixel, nothing
    outside the box: two overlapping spheres in a distorted view, the cup, a mesh partly outside the image, one
    partly behind the camera, one wholly behind it, no faces; ``silhouette_iou``'s counts on the box are the
    full-image counts against masks (an empty mask, a mask of soft levels)."""
    cup = scenes.build("cup").mesh
    near = look_at((0.9, 0.0, 0.3), (0.0, 0.0, 0.3), (0, 0, 1), 50, 80, 60, "near")       # the cup fills and leaves it
    through = look_at((0.0, 0.0, 0.3), (1.0, 0.0, 0.3), (0, 0, 1), 70, 80, 60, "through")  # inside: faces behind it
    away = look_at((2.0, 0, 0.3), (3.0, 0, 0.3), (0, 0, 1), 60, 40, 30, "away")
    rng = np.random.default_rng(3)
    cases = [(two_spheres(), small_rig(k1=-0.15)), (cup, Cameras([*small_rig(160, 120), near, through, away])),
             (trimesh.Trimesh(cup.vertices, np.zeros((0, 3), np.int64), process=False), small_rig())]
    checked = 0
    for m, cams in cases:
        r = raster.MeshRaster(m.vertices, m.faces, cams)
        sil = raster.silhouette(m.vertices, m.faces, cams)
        masks = []
        for view in range(len(cams)):
            full = r.coverage(view)
            box, (x0, y0, w, h) = r.cover_box(view)
            assert box.shape == (h, w) and box.dtype == np.uint8
            assert np.array_equal(sil[view], full), view
            outside = full.copy()
            outside[y0:y0 + h, x0:x0 + w] = 0
            assert not outside.any() and np.array_equal(full[y0:y0 + h, x0:x0 + w], box)
            checked += int(full.any())
            ref = raster.rasterize_reference(m.vertices, m.faces, cams, view)[0] >= 0     # the NumPy reference's
            assert (ref != (sil[view] > 0)).sum() <= 3, view                              # exact edge ties only
            mask = np.roll(full, (3, -2), axis=(0, 1)) if view % 3 else rng.integers(0, 256, full.shape, dtype=np.uint8)
            masks.append(np.zeros_like(full) if view == 1 else mask)
        for view, (got, m_) in enumerate(zip(raster.silhouette_iou(m.vertices, m.faces, cams, masks), masks)):
            a, b = sil[view] > 0, m_ > 127
            union = np.logical_or(a, b).sum()
            assert got == {"iou": 1.0 if union == 0 else np.logical_and(a, b).sum() / union,
                           "mesh_outside_mask": int((a & ~b).sum()), "mask_not_covered": int((b & ~a).sum())}, view
    assert checked == 3 + 5          # views with a silhouette: the spheres' three, the cup's five (not "away")
    m, cams = cases[0]
    wrong = [np.zeros((cam.height, cam.width), np.uint8) for cam in cams]
    wrong[1] = np.zeros((cams[1].height + 2, cams[1].width), np.uint8)
    with pytest.raises(NodeError, match="camera 'c1': mask 80x62 is not its image's 80x60"):
        raster.silhouette_iou(m.vertices, m.faces, cams, wrong)


def test_shade_kernel_matches_reference():
    sc = scenes.build("figure", 3)
    cams = small_rig(96, 72, n=2)
    mats = sc.materials.copy()
    mats[0, 9] = 1.0                                # let one material receive the shadow blob too
    args = (sc.mesh.vertices, sc.mesh.faces, sc.mesh.vertex_normals, sc.texcoords, sc.face_material, mats)
    light, shadow = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]), (0.0, 0.0, 0.3, 0.5)
    images, masks = raster.render(*args, cams, n_object=len(sc.mesh.faces) // 2, light=light, ambient=0.3,
                                  shadow=shadow, empty_rgb=(0.1, 0.2, 0.3))
    for view in range(len(cams)):
        tri, _, bary = raster.MeshRaster(sc.mesh.vertices, sc.mesh.faces, cams).rasterize(view)
        rgb, mask = raster.shade_reference(tri, bary, sc.mesh.faces, *args[2:], light, 0.3, shadow,
                                           (0.1, 0.2, 0.3), len(sc.mesh.faces) // 2)
        assert np.array_equal(mask, masks[view])
        assert np.abs(rgb.astype(int) - images[view]).max() <= 2
        assert len(np.unique(rgb.reshape(-1, 3), axis=0)) > 20     # texture and shading, not flat colour


def test_reference_matches_fillpoly_with_distortion():
    m = trimesh.creation.icosphere(3, radius=1.0)
    cams = ring_rig(2, 320, 240, radius=4.0, z=1.0, fov=50, angles=(0.0, 2.0), name="c{i}")
    cams[1].dist[0] = -0.3
    for view in range(2):
        tri, depth, bary = raster.rasterize_reference(m.vertices, m.faces, cams, view)
        assert iou(tri >= 0, fillpoly_silhouette(m.vertices, m.faces, cams, view)) >= 0.999
        hit = tri >= 0
        assert np.allclose(bary[hit].sum(axis=1), 1, atol=1e-5) and (bary[hit] >= -1e-6).all()
        # depth of the nearest surface of a unit sphere seen from 4.12 m: between d - 1 and sqrt(d^2 - 1)
        d = np.linalg.norm(cams[view].center)
        assert depth[hit].min() == pytest.approx(d - 1, abs=0.01) and depth[hit].max() <= np.sqrt(d * d - 1) + 1e-3


def test_nearest_face_wins():
    """Two parallel squares; the one nearer the camera hides the other whatever the face order."""
    quad = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
    v = np.vstack([quad + [0, 0, 0.5], quad * 0.5])           # far (z=0) small square listed second
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    cams = Cameras([look_at([0, 0, 4], [0, 0, 0], [0, 1, 0], 60, 64, 48)])
    tri, depth, _ = raster.rasterize_reference(v, f, cams, 0)
    assert set(np.unique(tri[tri >= 0])) == {0, 1}
    np.testing.assert_allclose(depth[tri >= 0], 3.5, rtol=1e-6)
    tri2, _, _ = raster.rasterize_reference(v, f[::-1], cams, 0)     # reversed order: near faces are 2, 3
    assert set(np.unique(tri2[tri2 >= 0])) == {2, 3}


SMALL = {"cameras": 4, "width": 320, "height": 240}


def test_synth_masks_equal_ground_truth_projection():
    out = run_node("synth", params={"scene": "figure", "background": "plate", "distortion": -0.05, **SMALL},
                   frame=2, roundtrip=True)
    mesh, cams = out["mesh"], out["cameras"]
    assert len(cams) == 4 and out["images"].images[0].shape == (240, 320, 3)
    for view in range(len(cams)):
        truth = fillpoly_silhouette(mesh.vertices, mesh.faces, cams, view)
        assert 0.03 < truth.mean() < 0.5
        assert iou(out["masks"].masks[view] > 127, truth) >= 0.999
    lo, hi = out["bounds"]
    assert (mesh.vertices > lo).all() and (mesh.vertices < hi).all()


def test_plate_is_the_image_without_the_object():
    params = {"scene": "cup", "rig": "dome", "cameras": 2, "width": 160, "height": 120}
    clean = Synth().run(**_params(params, background="plate", shadow=False), frame=0)
    for img, plate, mask in zip(clean["images"].images, clean["background"].images, clean["masks"].masks):
        outside = mask == 0
        assert np.array_equal(img[outside], plate[outside])
        assert (np.abs(img[~outside].astype(int) - plate[~outside]).sum(axis=1) > 30).mean() > 0.5
    shadowed = Synth().run(**_params(params, background="green", shadow=True), frame=0)
    flat = Synth().run(**_params(params, background="green", shadow=False), frame=0)
    assert flat["background"] is None and flat["skeleton"] is None
    for img, ref, mask in zip(shadowed["images"].images, flat["images"].images, shadowed["masks"].masks):
        bg = mask == 0
        darker = bg & (img.sum(axis=2) < ref.sum(axis=2) - 15)
        assert darker.sum() > 100                                    # a visible shadow blob on the floor
        ratio = img[darker].astype(float) / ref[darker]
        assert np.abs(ratio - ratio.mean(axis=1, keepdims=True)).max() < 0.05   # same chromaticity


def _params(over, **more):
    base = {k: p.default for k, p in Synth.params.items()}
    return {**base, **over, **more}


def test_figure_moves_with_constant_topology():
    frames = [scenes.build("figure", f) for f in (0, 4, 8, 16)]
    rest_faces = frames[0].mesh.faces
    for sc in frames:
        assert np.array_equal(sc.mesh.faces, rest_faces) and sc.mesh.is_watertight
        assert np.linalg.norm(sc.mesh.vertices - sc.center, axis=1).max() < sc.radius
    moved = np.linalg.norm(frames[1].mesh.vertices - frames[0].mesh.vertices, axis=1)
    assert moved.max() > 0.15 and np.median(moved) > 0.005
    assert np.abs(frames[1].skeleton.joints - frames[3].skeleton.joints).max() > 0.15   # opposite strides


def winding_number(points, mesh):
    """Generalised winding number of closed ``mesh`` at ``points`` (1 inside, 0 outside)."""
    tri = mesh.vertices[mesh.faces]
    out = []
    for p in points:
        a, b, c = (tri[:, i] - p for i in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
        num = np.einsum("ij,ij->i", a, np.cross(b, c))
        den = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la \
            + np.einsum("ij,ij->i", c, a) * lb
        out.append(np.arctan2(num, den).sum() / (2 * np.pi))
    return np.array(out)


def test_skeleton_joints_inside_the_mesh():
    for frame in (0, 6, 18):
        sc = scenes.build("figure", frame)
        sk = sc.skeleton
        assert len(sk.joints) == len(sk.parents) == len(sk.names) == 16 and sk.parents.count(-1) == 1
        assert sk.weights.shape == (len(sc.mesh.vertices), 16)
        np.testing.assert_allclose(sk.weights.sum(axis=1), 1, atol=1e-9)
        w = winding_number(sk.joints, sc.mesh)
        assert (w > 0.99).all(), f"frame {frame}: joints outside: {[n for n, x in zip(sk.names, w) if x < 0.99]}"
        assert (winding_number(sk.joints + [0, 0, 2.5], sc.mesh) < 0.01).all()


def test_cup_is_watertight_with_a_concavity():
    cup = scenes.build("cup").mesh
    assert cup.is_watertight and cup.is_winding_consistent and cup.volume > 0
    assert cup.volume < 0.4 * cup.convex_hull.volume          # mostly hollow: the hull cannot see inside
    inside_cavity = np.array([[0, 0, 0.3]])
    assert winding_number(inside_cavity, cup)[0] < 0.01


def test_synth_golden(golden):
    out = run_node("synth", params={"scene": "figure", "background": "plate", "cameras": 4, "width": 64,
                                    "height": 48}, frame=1, roundtrip=True)
    golden.check("synth_figure_masks", out["masks"], Masks, iou=0.97)
    assert (len(out["mesh"].vertices), len(out["mesh"].faces)) == (13058, 26112)
    golden.check("synth_figure_vertices", np.asarray(out["mesh"].vertices[::100]), Array, atol=1e-6)
    golden.check("synth_figure_joints", out["skeleton"].joints, Array, atol=1e-6)


def test_surface_truth_is_what_the_renderer_paints():
    """render.surface_truth at the surface points behind a camera's pixels gives those pixels' colours (the truth
    of the texture flicker measure), and its pattern-edge distance is small only where the photo has an edge."""
    from nodes.synth.render import surface_truth

    out = run_node("synth", {}, {"scene": "figure", "cameras": 4, "width": 320, "height": 240, "shadow": True}, frame=3)
    sc = scenes.build("figure", 3)
    cams, img = out["cameras"], out["images"].images[0]
    tri, _, bary = raster.rasterize(sc.mesh.vertices, sc.mesh.faces, cams, 0)
    ys, xs = np.nonzero(tri >= 0)
    pick = np.random.default_rng(1).choice(len(ys), 3000, replace=False)
    ys, xs = ys[pick], xs[pick]
    X = np.einsum("nk,nkc->nc", bary[ys, xs].astype(np.float64), sc.mesh.vertices[sc.mesh.faces[tri[ys, xs]]])
    colour, dist = surface_truth(sc, X)
    diff = np.abs(colour - img[ys, xs].astype(np.float64)).max(axis=1)
    away = dist > 0.005      # off pattern edges: the pixel's colour, to rounding and float32 (measured p99 1.15)
    assert away.mean() > 0.5 and np.percentile(diff[away], 99) <= 1.5 and diff[away].mean() < 0.6, diff[away].mean()
    assert np.median(diff[~away]) < 40 and np.isfinite(dist).all()
