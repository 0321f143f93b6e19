"""Keying nodes: kernels against their NumPy references, synthetic scenes with known silhouettes, golden files,
and (realdata) the green dome, the blue-screen dino and the background-plate room."""
from __future__ import annotations

import json

import numpy as np
import pytest

from nodes.common.cameras import Cameras
import rig
from nodegraph import Table
from nodegraph.errors import NodeError
from nodegraph.testing import run_node
from nodes.common.types import ImageSet, Masks, MaskSet, VoxelGrid
from nodes.key import keying as K

GREEN = (40, 160, 60)


def iou(a, b) -> float:
    a, b = np.asarray(a) > 127, np.asarray(b) > 127
    return float((a & b).sum() / max((a | b).sum(), 1))


def ring_rig(n=4, w=64, h=48, radius=4.0) -> Cameras:
    return rig.ring_rig(n, w, h, radius=radius, z=0.8, fov=40)


def sphere_mask(cameras: Cameras, view: int, centre=(0, 0, 0), r=0.6) -> np.ndarray:
    """Analytic silhouette (0/255) of a sphere: pixels whose ray hits it."""
    cam = cameras[view]
    ys, xs = np.mgrid[: cam.height, : cam.width]
    rays = np.stack([xs, ys, np.ones_like(xs)], -1).reshape(-1, 3) @ np.linalg.inv(cam.K).T @ cam.Rt[:, :3]
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    eye = cam.center
    oc = eye - np.asarray(centre, float)
    b = rays @ oc
    disc = b * b - (oc @ oc - r * r)
    return np.where(disc > 0, 255, 0).astype(np.uint8).reshape(cam.height, cam.width)


def green_scene(mask: np.ndarray, seed=0, colour=(200, 60, 50)) -> np.ndarray:
    """A lit green screen (brightness falls off to the sides) with a coloured object where mask is set."""
    rng = np.random.default_rng(seed)
    h, w = mask.shape
    shade = 0.6 + 0.4 * np.cos(np.linspace(-1.2, 1.2, w))[None, :, None] * np.ones((h, 1, 1))
    img = np.asarray(GREEN, float) * shade
    img = np.where(mask[..., None] > 127, np.asarray(colour, float), img)
    return np.clip(img + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)


def disc(h, w, cy, cx, r):
    ys, xs = np.mgrid[:h, :w]
    return np.where((ys - cy) ** 2 + (xs - cx) ** 2 < r * r, 255, 0).astype(np.uint8)


# ---------------------------------------------------------------- kernels vs references
def test_chroma_kernel_matches_reference():
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, (37, 53, 3), dtype=np.uint8)  # every kind of colour, odd size
    key = K.key_direction_from_rgb(GREEN)
    edges = np.array([[1, 0, -5, 0], [0, 1, -3, 0], [-0.6, -0.8, 40, 0]], np.float32)
    for kw in ({}, {"black": 20.0, "spill": 0.5, "side": 2.0}, {"edges": edges}):
        a_cl, d_cl = K.chroma_key_cl(img, key, **kw)
        a_np, d_np = K.chroma_key_reference(img, key, **kw)
        assert np.abs(a_cl.astype(int) - a_np).max() <= 1
        assert np.abs(d_cl.astype(int) - d_np).max() <= 1
        assert (np.abs(a_cl.astype(int) - a_np) > 0).mean() < 0.002
    a, _ = K.chroma_key_cl(img, key, edges=edges)
    assert np.all(a[~K.matte_reference(edges, img.shape[:2])] == 0)


def test_windowed_chroma_key_is_the_whole_images_despill_inside_the_window():
    """chroma_key_windowed: the alpha of chroma_key_cl, the despill run on the alpha's window alone (the box grown
    by the margin and clipped to the image; widths that are no multiple of 16, a window at the border, an empty
    alpha): inside it byte for byte chroma_key_cl's (and within a level of the NumPy reference), black beyond."""
    rng = np.random.default_rng(3)
    key = K.key_direction_from_rgb(GREEN)
    for h, w, (cy, cx, r), margin in ((61, 83, (30, 40, 9), 5), (40, 70, (5, 66, 12), 16), (33, 47, (0, 0, 0), 4)):
        img = green_scene(disc(h, w, cy, cx, r), seed=int(rng.integers(100)))
        a_full, d_full = K.chroma_key_cl(img, key)
        a, d, win = K.chroma_key_windowed(img, key, margin=margin)
        assert np.array_equal(a, a_full)
        ys, xs = np.nonzero(a)
        want = ([max(0, xs.min() - margin), max(0, ys.min() - margin), min(w, xs.max() + 1 + margin),
                 min(h, ys.max() + 1 + margin)] if len(xs) else [0, 0, 0, 0])
        assert win == want, (win, want)
        x0, y0, x1, y1 = win
        inside = np.zeros((h, w), bool)
        inside[y0:y1, x0:x1] = True
        assert np.array_equal(d[inside], d_full[inside]) and not d[~inside].any()
        _, d_np = K.chroma_key_reference(img, key)
        assert np.abs(d[inside].astype(int) - d_np[inside]).max(initial=0) <= 1
    assert win == [0, 0, 0, 0]                                        # the empty alpha: all black


def test_chroma_key_on_the_mattes_box_is_the_whole_images_alpha():
    """With a garbage matte the windowed key keys the matte's box alone (kernel chroma_key_box): its alpha is
    chroma_key_cl's byte for byte (random colours, widths that are no multiple of 16, a matte reaching the
    border, one cutting a corner, one outside the image), so are the window and the despilled image."""
    rng = np.random.default_rng(5)
    img = rng.integers(0, 256, (45, 71, 3), dtype=np.uint8)
    img[10:30, 20:50] = green_scene(disc(20, 30, 10, 15, 8), seed=4)
    key = K.key_direction_from_rgb(GREEN)
    mattes = (np.array([[1, 0, -5, 0], [0, 1, -3, 0], [-0.6, -0.8, 40, 0]], np.float32),
              np.array([[1, 0, 0, 0]], np.float32),
              np.array([[1, 1, -60, 0]], np.float32),
              np.array([[1, 0, -500, 0]], np.float32))
    for edges in mattes:
        a_full, d_full = K.chroma_key_cl(img, key, edges=edges)
        a_box, ((x0, x1), (y0, y1)) = K.chroma_key_box(img, key, edges)
        assert np.array_equal(a_box, a_full)
        assert np.abs(a_box.astype(int) - K.chroma_key_reference(img, key, edges=edges)[0]).max() <= 1   # NumPy's
        assert not a_full[:y0].any() and not a_full[y1:].any() and not a_full[:, :x0].any() and not a_full[:, x1:].any()
        a, d, win = K.chroma_key_windowed(img, key, margin=3, edges=edges)
        assert np.array_equal(a, a_full) and win == list(K.alpha_window(a_full, 3))
        wx0, wy0, wx1, wy1 = win
        assert np.array_equal(d[wy0:wy1, wx0:wx1], d_full[wy0:wy1, wx0:wx1])
    assert not a_full.any() and win == [0, 0, 0, 0]                  # the matte outside the image: nothing


BOX_BUILDS = """
import json, sys
import numpy as np
sys.path.insert(0, sys.argv[1])
from nodegraph import clrt
from nodes.key import keying as K
seen = {}
launch = clrt.Runner.launch
def record(self, name, global_size, local_size, *args, **kw):
    seen.setdefault(name, set()).add(str(local_size))
    return launch(self, name, global_size, local_size, *args, **kw)
clrt.Runner.launch = record
rng = np.random.default_rng(7)
img = rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)
img[30:90, 50:110] = (40, 200, 60)
for _ in range(6):   # boxes of other sizes each time, as a moving person's
    x0, x1, y0, y1 = (int(v) for v in (rng.integers(0, 40), rng.integers(100, 160), rng.integers(0, 20), rng.integers(90, 120)))
    edges = np.array([[1, 0, -x0, 0], [-1, 0, x1, 0], [0, 1, -y0, 0], [0, -1, y1, 0]], np.float32)
    K.chroma_key_windowed(img, K.key_direction_from_rgb([40, 200, 60]), edges=edges, margin=3)
print(json.dumps({"platform": K.KeyCL.get().queue.device.platform.name, "local": {k: sorted(v) for k, v in seen.items()}}))
"""


def test_box_kernels_are_built_once_whatever_the_boxes_size(tmp_path):
    """The key's box kernels (the matte's box, the despill window) change size every frame. Launched with PoCL's own
    work-group, each new size got a work-group of its own, and PoCL compiles a kernel per work-group (0.1-0.25 s
    each, the key item 0.3-1.2 s a frame until its cache had seen every size). They name their work-group: over six
    boxes each is launched with one, and on PoCL (a fresh kernel cache) each is compiled once."""
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[3]
    env = dict(os.environ, POCL_CACHE_DIR=str(tmp_path / "pocl"))
    out = subprocess.run([sys.executable, "-c", BOX_BUILDS, str(root)], env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    for kernel in ("chroma_key_box", "despill_box"):
        assert got["local"][kernel] == [str(K.BOX_GROUP)], got["local"]
        if "Portable Computing Language" in got["platform"]:
            built = [d for d in (tmp_path / "pocl").glob(f"*/*/{kernel}/*") if d.is_dir()]
            assert len(built) == 1, [d.name for d in built]


def test_difference_kernel_matches_reference():
    rng = np.random.default_rng(2)
    plate = plate_scene(h=29, w=41)[0]
    img = plate * rng.uniform(0.3, 1.4, (29, 41, 1))  # shadows, highlights and beyond
    recolour = rng.random((29, 41)) < 0.3
    img[recolour] = rng.uniform(0, 255, (recolour.sum(), 3))  # and foreground
    img = np.clip(img + rng.normal(0, 2, plate.shape), 0, 255).astype(np.uint8)
    mean, inv_var = K.plate_model(plate, 4.0)
    a_cl, l_cl = K.difference_key_cl(img, mean, inv_var)
    a_np, l_np = K.difference_key_reference(img, mean, inv_var)
    assert np.abs(a_cl.astype(int) - a_np).max() <= 1
    assert (l_cl != l_np).mean() < 0.002
    assert set(np.unique(l_np)) == {0, 1, 2}  # the random scene has all three classes


def test_threshold_kernel_matches_reference():
    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, (31, 47, 3), dtype=np.uint8)
    for t, use_max in ((48.45, False), (127.0, True)):
        assert np.array_equal(K.grey_threshold_cl(img, t, use_max), K.grey_threshold_reference(img, t, use_max))


# ---------------------------------------------------------------- chroma key
def test_chroma_key_recovers_ball_and_despills():
    h, w = 48, 64
    ball = disc(h, w, 24, 30, 12)
    img = green_scene(ball)
    # a white patch lit by green spill: kept, and its green cast removed
    patch = np.zeros((h, w), np.uint8)
    patch[5:12, 45:58] = 255
    img[patch > 0] = (200, 225, 200)
    out = run_node("key.chroma", {"images": ImageSet([img])}, roundtrip=True)
    truth = np.maximum(ball, patch)
    assert iou(out["masks"].masks[0], truth) > 0.97
    alpha = out["masks"].alpha[0]
    assert alpha.dtype == np.float32 and alpha[truth == 0].max() < 0.5 and alpha[truth > 0].min() > 0.5
    desp = out["images"].images[0][patch > 0].astype(int)
    assert np.all(desp[:, 1] <= np.maximum(desp[:, 0], desp[:, 2]) + 2)  # no green excess left
    assert np.abs(desp.mean(0) - 0.299 * 200 - 0.587 * 225 - 0.114 * 200).max() < 10  # luma kept: grey-white


def test_key_colour_estimate_equals_its_reference():
    """estimate_key_direction (the strip's channels as rows) gives rgb_to_ycc's result bit for bit."""
    rng = np.random.default_rng(3)
    images = [green_scene(disc(48, 64, 24, 30, 12), seed=1)] + [
        rng.integers(0, 256, (int(h), int(w), 3), dtype=np.uint8) for h, w in rng.integers(10, 120, (40, 2))]
    for im in images:
        got, want = K.estimate_key_direction(im), K.estimate_key_direction_reference(im)
        assert got.dtype == np.float32 and np.array_equal(got, want)
    # its chroma length (float32 of the double root) is np.hypot's (checked here on a million colours; all 2^24 agree)
    ycc = K.rgb_to_ycc(rng.integers(0, 256, (1 << 20, 3), dtype=np.uint8))
    cb, cr = ycc[:, 1], ycc[:, 2]
    fast = np.sqrt(np.square(cb, dtype=np.float64) + np.square(cr, dtype=np.float64)).astype(np.float32)
    assert np.array_equal(fast, np.hypot(cb, cr))


def test_chroma_key_colour_param_and_blue_screen():
    h, w = 40, 50
    obj = disc(h, w, 20, 25, 9)
    img = np.where(obj[..., None] > 0, np.uint8([190, 120, 40]), np.uint8([40, 50, 170]))
    auto = run_node("key.chroma", {"images": ImageSet([img])})
    given = run_node("key.chroma", {"images": ImageSet([img])}, {"key_color": [40, 50, 170]})
    assert iou(auto["masks"].masks[0], obj) == 1.0
    assert iou(given["masks"].masks[0], obj) == 1.0


def test_garbage_matte_removes_what_lies_outside_the_capture_box():
    cams = ring_rig(3)
    bounds = np.array([[-0.7, -0.7, -0.7], [0.7, 0.7, 0.7]])
    masks = [sphere_mask(cams, v) for v in range(3)]
    images = []
    for v, m in enumerate(masks):
        img = green_scene(m, seed=v)
        img[:6, :6] = (220, 40, 40)  # a red light in the corner, far outside the box
        images.append(img)
    plain = run_node("key.chroma", {"images": ImageSet(images)})
    matted = run_node("key.chroma", {"images": ImageSet(images), "cameras": cams, "bounds": bounds},
                      {"matte_margin": 2.0})
    for v in range(3):
        assert plain["masks"].masks[v][:6, :6].min() == 255
        assert matted["masks"].masks[v][:6, :6].max() == 0
        assert iou(matted["masks"].masks[v], masks[v]) > 0.95


def test_matte_edges_contain_projected_box():
    cams = ring_rig(2)
    bounds = np.array([[-0.5, -0.3, -0.4], [0.6, 0.5, 0.3]])
    edges = K.matte_edges(cams, 1, bounds, margin=0.0)
    pts = np.random.default_rng(4).uniform(bounds[0], bounds[1], (500, 3))
    uv, _ = cams.project(pts, 1)
    assert np.all(uv @ edges[:, :2].T + edges[:, 2] >= -1e-3)
    assert 3 <= len(edges) <= 20


def test_matte_edges_are_kept_per_camera_box_and_margin():
    """A static rig's garbage matte is made once per process: the kept edges equal fresh ones for the same camera,
    box and margin (a caller changing its copy changes nothing kept); a camera moved, another box or margin
    give their own matte."""
    from nodes.common.cameras import Camera, Cameras

    cams = ring_rig(3)
    bounds = np.array([[-0.5, -0.3, -0.4], [0.6, 0.5, 0.3]])
    first = K.matte_edges(cams, 1, bounds, 2.0)
    first[:] = 0
    again = K.matte_edges(cams, 1, bounds, 2.0)
    np.testing.assert_array_equal(again, K._matte_edges(cams, 1, bounds, 2.0))
    assert not np.array_equal(again, first)
    c = cams.cameras[1]
    moved = Cameras([cams.cameras[0], Camera(c.name, c.width, c.height, c.K, c.Rt + [[0, 0, 0, 0.05], [0] * 4, [0] * 4],
                                              c.dist, c.metric, c.zsign)])
    for edges, want in ((K.matte_edges(moved, 1, bounds, 2.0), K._matte_edges(moved, 1, bounds, 2.0)),
                        (K.matte_edges(cams, 1, bounds * 0.9, 2.0), K._matte_edges(cams, 1, bounds * 0.9, 2.0)),
                        (K.matte_edges(cams, 1, bounds, 5.0), K._matte_edges(cams, 1, bounds, 5.0))):
        np.testing.assert_array_equal(edges, want)
        assert not np.array_equal(edges, again)


# ---------------------------------------------------------------- chroma key straight into hull silhouettes
def test_matte_spans_equal_the_per_pixel_matte():
    """chroma_key_bits finds each row's matte span by bisection: on an all-foreground image its bits are the
    matte itself, which must equal matte_reference exactly (steep, shallow, horizontal and vertical edges)."""
    h, w = 45, 77
    img = np.zeros((h, w, 3), np.uint8)
    img[:] = (200, 60, 50)  # foreground everywhere
    rng = np.random.default_rng(7)
    mattes = [np.array([[1, 0, -5, 0], [0, 1, -3, 0], [-0.6, -0.8, 40, 0]], np.float32),
              np.array([[1e-4, -1, 30.3, 0], [0, 1, -0.5, 0], [-1, 0, 70.5, 0], [-2e-5, 1, -1.0, 0]], np.float32),
              np.array([[0, -1, -1, 0]], np.float32),  # nothing inside
              tangents_of_disc(rng, (40.0, 20.0), 15.0, 12)]
    sil = K.chroma_key_bits([img] * len(mattes), K.key_direction_from_rgb(GREEN), edges=mattes)
    for m, edges in zip(sil.masks(), mattes):
        assert np.array_equal(m > 0, K.matte_reference(edges, (h, w)))
    assert sil.masks()[0].any() and not sil.masks()[2].any() and 0.1 < (sil.masks()[3] > 0).mean() < 0.3
    for edges in mattes:  # the key.chroma kernel reads the same spans (matte_rows)
        alpha, _ = K.chroma_key_cl(img, K.key_direction_from_rgb(GREEN), edges=edges, despill=False)
        assert np.array_equal(alpha > 0, K.matte_reference(edges, (h, w)))
    narrow = np.ascontiguousarray(img[:9, :5])  # narrower than the kernel's 16 pixels per work item
    edges = np.array([[1, 0, -1.5, 0], [-0.3, 1, -1, 0], [-1, -0.2, 4, 0]], np.float32)
    alpha, _ = K.chroma_key_cl(narrow, K.key_direction_from_rgb(GREEN), edges=edges, despill=False)
    assert np.array_equal(alpha > 0, K.matte_reference(edges, (9, 5))) and 0 < (alpha > 0).mean() < 0.5


def tangents_of_disc(rng, centre, r, n) -> np.ndarray:
    """n matte edges in random directions, each at distance r from centre (a polygon around a disc)."""
    t = rng.uniform(0, 2 * np.pi, n)
    a, b = np.cos(t), np.sin(t)
    return np.stack([a, b, r - a * centre[0] - b * centre[1], 0 * t], -1).astype(np.float32)


def test_chroma_key_bits_round_the_tie_like_the_alpha():
    """alpha exactly 127.5 / 255 rounds to 128 (half to even): foreground in the node's masks and in the bits.
    Grey pixels with black = luma - 2 give a = 0.5 exactly (luma ramp (Y - black) / 4)."""
    f = np.float32
    img = np.full((8, 16, 3), 100, np.uint8)
    img[:, 8:] = 90  # and some pixels below the tie
    luma = f(0.299) * f(100) + f(0.587) * f(100) + f(0.114) * f(100)
    key = K.key_direction_from_rgb(GREEN)
    alpha, _ = K.chroma_key_cl(img, key, black=float(luma - f(2)), despill=False)
    assert np.all(alpha[:, :8] == 128) and np.all(alpha[:, 8:] == 0)
    bits = K.chroma_key_bits([img], key, black=float(luma - f(2))).masks()[0]
    assert np.array_equal(bits, np.where(alpha >= 128, 255, 0))


def test_chroma_key_bits_equal_the_node_masks_and_give_the_same_hull():
    """Fused path (key -> device bits -> hull) == key.chroma node masks -> hull node, bit for bit."""
    from nodes.common.silhouettes import block_table_reference
    from nodes.hull.hull import visual_hull

    cams = ring_rig(5, w=53, h=37)  # width not a multiple of 16, odd number of bit bytes per row
    bounds = np.array([[-0.7, -0.7, -0.7], [0.7, 0.7, 0.7]])
    images = []
    for v in range(len(cams)):
        img = green_scene(sphere_mask(cams, v), seed=v)
        img[:5, :7] = (220, 40, 40)  # outside the capture box: the matte removes it
        images.append(img)
    node = run_node("key.chroma", {"images": ImageSet(images), "cameras": cams, "bounds": bounds},
                    {"key_color": list(GREEN), "spill": 0.0, "matte_margin": 1.0})["masks"]
    key = K.key_direction_from_rgb(GREEN)
    edges = [K.matte_edges(cams, v, bounds, 1.0) for v in range(len(cams))]
    sil = K.chroma_key_bits(images, key, edges=edges)
    for v, (bits, table) in enumerate(zip(sil.masks(), sil.block_tables())):
        alpha, _ = K.chroma_key_cl(images[v], key, edges=edges[v], despill=False)
        assert np.array_equal(bits, np.where(alpha >= 128, 255, 0)), f"view {v}"
        assert np.array_equal(bits, node.masks[v]), f"view {v}"
        assert np.array_equal(table, block_table_reference(bits))
        assert 0.05 < (bits > 0).mean() < 0.6 and bits[:5, :7].max() == 0
    params = {"resolution": 24, "bbox": bounds.ravel().tolist()}
    want = run_node("hull", {"masks": node, "cameras": cams}, params)["volume"].occupancy
    got = visual_hull(sil, cams, bounds, 24).occupancy
    assert want.sum() > 500 and np.array_equal(got, want)
    assert np.array_equal(visual_hull(sil, cams, bounds, 24, method="numpy").occupancy, want)


def test_chroma_key_bits_reuses_its_buffers_and_checks_input():
    from nodes.hull.hull import visual_hull

    cams = ring_rig(2, w=40, h=24)
    masks = [sphere_mask(cams, v) for v in range(2)]
    key = K.key_direction_from_rgb(GREEN)
    first = K.chroma_key_bits([green_scene(m) for m in masks], key)
    empty = np.zeros((24, 40), np.uint8)
    again = K.chroma_key_bits([green_scene(empty)] * 2, key, out=first)
    assert again is first and not any(m.any() for m in again.masks())  # overwritten, nothing left over
    other = K.chroma_key_bits([green_scene(np.zeros((20, 40), np.uint8))] * 2, key, out=first)
    assert other is not first and other.sizes == [(40, 20)] * 2
    with pytest.raises(NodeError, match="image 1 must be"):
        K.chroma_key_bits([green_scene(masks[0]), masks[1]], key)
    with pytest.raises(NodeError, match="2 images but 1 garbage"):
        K.chroma_key_bits([green_scene(m) for m in masks], key, edges=[None])
    with pytest.raises(NodeError, match="camera 'cam0' is 40x20"):
        visual_hull(other, cams, np.array([[-1, -1, -1], [1, 1, 1]]), 8)


# ---------------------------------------------------------------- difference key
def plate_scene(seed=5, h=48, w=64):
    """A textured clean plate; the frame adds a ball and a soft shadow (plate darkened, same chromaticity)."""
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[:h, :w] / 10.0
    plate = np.stack([110 + 50 * np.sin(xs), 120 + 40 * np.cos(ys), 90 + 30 * np.sin(xs + ys)], -1)
    ball = disc(h, w, 20, 24, 10)
    shadow = np.exp(-(((np.mgrid[:h, :w][0] - 36) / 5.0) ** 2 + ((np.mgrid[:h, :w][1] - 40) / 12.0) ** 2))
    frame = plate * (1 - 0.45 * shadow[..., None])
    frame = np.where(ball[..., None] > 0, np.array([60.0, 170.0, 210.0]), frame)
    noisy = lambda im: np.clip(im + rng.normal(0, 2.0, im.shape), 0, 255).astype(np.uint8)  # noqa: E731
    return noisy(plate), noisy(frame), ball, shadow > 0.3


def test_difference_key_keeps_object_drops_shadow_and_beats_mog2():
    import cv2

    plate, frame, ball, shadow = plate_scene()
    out = run_node("key.difference", {"images": ImageSet([frame]), "background": ImageSet([plate])}, roundtrip=True)
    m = out["masks"].masks[0]
    assert iou(m, ball) > 0.95
    assert (m[shadow & (ball == 0)] > 0).mean() < 0.02
    mog = cv2.createBackgroundSubtractorMOG2(detectShadows=True)
    for _ in range(20):
        mog.apply(plate[:, :, ::-1], learningRate=-1)
    baseline = np.where(mog.apply(frame[:, :, ::-1], learningRate=0) == 255, 255, 0)  # 127 = shadow
    assert iou(m, ball) >= iou(baseline, ball)


def test_difference_key_rejects_mismatched_plates():
    plate, frame, _, _ = plate_scene()
    with pytest.raises(NodeError, match="background plates"):
        run_node("key.difference", {"images": ImageSet([frame, frame]), "background": ImageSet([plate])})
    with pytest.raises(NodeError, match="cam000"):
        run_node("key.difference", {"images": ImageSet([frame]), "background": ImageSet([plate[:-1]])})


# ---------------------------------------------------------------- threshold and clean-up
def test_threshold_node_with_dilate_erode():
    img = np.zeros((40, 40, 3), np.uint8)
    img[10:30, 10:30] = 60  # grey 60 > 0.19 * 255
    img[19:21, 19:21] = 0  # a dark speck inside: closed by dilate then erode
    out = run_node("key.threshold", {"images": ImageSet([img])}, {"threshold": 0.19, "dilate": 3, "erode": 3})
    m = out["masks"].masks[0]
    expect = np.zeros((40, 40), np.uint8)
    expect[10:30, 10:30] = 255
    assert iou(m, expect) > 0.97 and m[19:21, 19:21].min() == 255


def test_cleanup_keeps_largest_fills_holes_drops_specks():
    m = np.maximum(disc(60, 80, 30, 25, 15), disc(60, 80, 30, 65, 8))
    hole = disc(60, 80, 30, 25, 4)
    m[hole > 0] = 0
    m[2, 2] = 255  # a speck
    out = run_node("key.cleanup", {"masks": MaskSet([m], [m.astype(np.float32) / 255])},
                   {"open": 1, "close": 0, "keep": 1})
    c = out["masks"].masks[0]
    big = disc(60, 80, 30, 25, 15)
    assert iou(c, big) > 0.98
    assert c[hole > 0].min() == 255 and c[2, 2] == 0 and c[30, 65] == 0
    assert out["masks"].alpha[0][hole > 0].min() == 1.0  # filled holes are opaque
    two = run_node("key.cleanup", {"masks": MaskSet([m])}, {"keep": 2, "fill_holes": False})["masks"].masks[0]
    assert two[30, 65] == 255 and two[30, 25] == 0


def test_cleanup_on_the_foreground_box_equals_the_whole_image():
    """clean_mask works on the foreground's bounding box (plus a margin): the result is the whole image's
    (clean_mask_reference), also with specks at the borders, equal-sized components (ties at the ``keep`` cut) and
    soft values around the 127 threshold."""
    import cv2

    rng = np.random.default_rng(1)
    for trial in range(300):
        h, w = (int(v) for v in rng.integers(5, 90, 2))
        kind = trial % 4
        if kind == 0:   # noise of any density
            m = (rng.random((h, w)) < rng.uniform(0.01, 0.9)).astype(np.uint8) * 255
        elif kind == 1:   # blobs (some cut by the border) with specks and pinholes
            m = np.zeros((h, w), np.uint8)
            for _ in range(int(rng.integers(1, 6))):
                cv2.circle(m, (int(rng.integers(-5, w + 5)), int(rng.integers(-5, h + 5))), int(rng.integers(1, 20)), 255, -1)
            m[rng.random((h, w)) < 0.02] = 255
            m[rng.random((h, w)) < 0.02] = 0
        elif kind == 2:   # single-pixel specks: ties everywhere
            m = np.zeros((h, w), np.uint8)
            m[rng.integers(0, h, 8), rng.integers(0, w, 8)] = 255
        else:   # soft values around the threshold
            m = rng.integers(120, 135, (h, w)).astype(np.uint8)
        # a hint: a box the mask is 0 outside of (its non-zero box grown by 0-3 pixels, as a key's window)
        x, y, bw, bh = cv2.boundingRect(m)
        g = int(rng.integers(0, 4))
        hint = (max(x - g, 0), max(y - g, 0), min(x + bw + g, w), min(y + bh + g, h)) if bw else (0, 0, 0, 0)
        for op, cl, keep, fill in ((1, 2, 1, True), (0, 0, 2, True), (2, 3, 0, False), (0, 1, 3, True), (3, 0, 1, False)):
            got = K.clean_mask(m, open_px=op, close_px=cl, keep=keep, fill_holes=fill)
            want = K.clean_mask_reference(m, open_px=op, close_px=cl, keep=keep, fill_holes=fill)
            assert got.dtype == np.uint8 and np.array_equal(got, want), (trial, op, cl, keep, fill)
            hinted, box = K.clean_mask_box(m, open_px=op, close_px=cl, keep=keep, fill_holes=fill, hint=hint)
            assert np.array_equal(hinted, want), (trial, op, cl, keep, fill, hint)
            if box is not None:      # the result is 0 outside its box
                inside = np.zeros((h, w), bool)
                inside[box[1]:box[3], box[0]:box[2]] = True
                assert not hinted[~inside].any(), (trial, box)
        alpha = rng.random((h, w)).astype(np.float32)
        a = K.cleaned_alpha(got, m, alpha)
        assert a.dtype == np.float32 and np.array_equal(a, K.cleaned_alpha_reference(got, m, alpha))
        assert np.array_equal(K.cleaned_alpha(got, m, alpha, hint=box), a)
        levels = rng.integers(0, 256, (h, w)).astype(np.uint8)             # 8-bit alpha: by bitwise operations
        a8 = K.cleaned_alpha(got, m, levels)
        assert a8.dtype == np.uint8 and np.array_equal(a8, K.cleaned_alpha_reference(got, m, levels))
    assert not K.clean_mask(np.zeros((7, 9), np.uint8)).any()


def test_mask_boxes_from_the_key_and_the_cleanup_change_no_stored_byte(tmp_path):
    """key.chroma's masks carry their alpha window as ``MaskSet.boxes`` (0 outside it), key.cleanup works there and
    hands on its own working box; the cache's writer looks for each plane's non-zero box inside them: the files are
    byte for byte those of the same masks without boxes, the clean-up's masks and alpha those of a clean-up
    without the key's boxes. A box that is not one is refused by the type's check. Read back, a set carries its
    stored planes' boxes."""
    import cv2

    from nodes.common.types import Masks

    h, w = 120, 160
    img = green_scene(np.maximum(disc(h, w, 60, 70, 15), disc(h, w, 20, 130, 4)))
    views = [img, img[::-1].copy(),
             green_scene(np.zeros((h, w), bool)),                                  # nothing keyed: an empty box
             green_scene(disc(h, w, 5, 150, 20)),                                  # a figure cut by the border
             green_scene(np.maximum(disc(h, w, 40, 40, 9), disc(h, w, 80, 120, 9)))]   # equal parts: the ties path
    key = run_node("key.chroma", {"images": ImageSet(views)})["masks"]
    assert key.boxes is not None and len(key.boxes) == 5 and key.boxes[2] == (0, 0, 0, 0)
    for m, a, (x0, y0, x1, y1) in zip(key.masks, key.alpha8, key.boxes):
        inside = np.zeros((h, w), bool)
        inside[y0:y1, x0:x1] = True
        assert not a[~inside].any() and not m[~inside].any()
    plain = MaskSet(key.masks, None, key.names, alpha8=key.alpha8)
    clean = run_node("key.cleanup", {"masks": key})["masks"]
    clean_plain = run_node("key.cleanup", {"masks": plain})["masks"]
    assert clean.boxes is not None
    assert all(np.array_equal(a, b) for a, b in zip(clean.masks, clean_plain.masks))
    assert all(np.array_equal(a, b) for a, b in zip(clean.alpha8, clean_plain.alpha8))
    for name, (with_boxes, without) in {"key": (key, plain), "clean": (clean, clean_plain)}.items():
        (tmp_path / name / "a").mkdir(parents=True)
        (tmp_path / name / "b").mkdir()
        Masks.save(with_boxes, tmp_path / name / "a")
        Masks.save(MaskSet(without.masks, None, without.names, alpha8=without.alpha8), tmp_path / name / "b")
        files = sorted(p.name for p in (tmp_path / name / "b").iterdir())
        assert files == sorted(p.name for p in (tmp_path / name / "a").iterdir())
        for f in files:
            assert (tmp_path / name / "a" / f).read_bytes() == (tmp_path / name / "b" / f).read_bytes(), (name, f)
    assert clean.boxes[2] == (0, 0, 0, 0) and clean.boxes[4] is None     # the ties fall back to the whole image
    # read back, a set's boxes are its stored planes' (the tests check every box promised), its masks the same
    for name, sets in {"key": key, "clean": clean}.items():
        back = Masks.load(tmp_path / name / "a")
        assert back.boxes is not None and all(np.array_equal(a, b) for a, b in zip(back.masks, sets.masks))
        if name == "key":          # masks that are their levels' threshold: whole-frame levels made only when read
            assert back._alpha8 is None and back._alpha8_make is not None
        assert all(np.array_equal(a, b) for a, b in zip(back.alpha8, sets.alpha8))
        assert back.boxes[2] == (0, 0, 0, 0)
    plain_back = MaskSet(key.masks, None, key.names)                     # masks without alpha: their own boxes
    (tmp_path / "plain").mkdir()
    Masks.save(plain_back, tmp_path / "plain")
    assert Masks.load(tmp_path / "plain").boxes[0] == tuple(cv2.boundingRect(key.masks[0])[:2]) + tuple(
        np.add(cv2.boundingRect(key.masks[0])[:2], cv2.boundingRect(key.masks[0])[2:]))
    bad = MaskSet(key.masks[:2], None, key.names[:2], alpha8=key.alpha8[:2], boxes=[[0, 0, w + 1, h], None])
    assert "box" in Masks.check(bad)
    assert "box" in Masks.check(MaskSet(key.masks[:1], None, key.names[:1], alpha8=key.alpha8[:1], boxes=[[0, 0, 10.5, h]]))
    with pytest.raises(AssertionError, match="not 0 outside its box"):      # the tests verify every promise made
        MaskSet(key.masks[:1], None, key.names[:1], alpha8=key.alpha8[:1], boxes=[(0, 0, 5, 5)])


def test_writers_find_the_same_boxes_with_hints():
    """The cache's writers with a box a plane is 0 outside of (``_nonzero_box``, ``_is_mask_of_levels``) find what
    they find without it: random uint8 and float planes (-0.0 included), hints grown 0-3 pixels, at the edges,
    empty."""
    from nodes.common.types import _is_mask_of_levels, _mask_of_levels, _nonzero_box

    rng = np.random.default_rng(4)
    for trial in range(400):
        h, w = (int(v) for v in rng.integers(1, 40, 2))
        a = np.zeros((h, w), np.float32 if trial % 3 == 0 else np.uint8)
        if trial % 5:
            y0, x0 = int(rng.integers(0, h)), int(rng.integers(0, w))
            y1, x1 = int(rng.integers(y0, h)) + 1, int(rng.integers(x0, w)) + 1
            a[y0:y1, x0:x1] = rng.integers(0, 256, (y1 - y0, x1 - x0))
            if a.dtype == np.float32:
                a[y0, x0] = -0.0 if trial % 2 else a[y0, x0]
            ys, xs = np.nonzero(a.view(np.uint32) if a.dtype == np.float32 else a)
        else:
            ys = xs = np.zeros(0, int)
        g = int(rng.integers(0, 4))
        hint = ((max(int(xs.min()) - g, 0), max(int(ys.min()) - g, 0), min(int(xs.max()) + 1 + g, w),
                 min(int(ys.max()) + 1 + g, h)) if len(xs) else (0, 0, 0, 0))
        cut, box = _nonzero_box(a)
        hcut, hbox = _nonzero_box(a, hint)
        assert hbox == box and hcut.shape == cut.shape and np.array_equal(hcut.view(np.uint8), cut.view(np.uint8)), (trial, hint)
        if a.dtype == np.uint8:
            mask = _mask_of_levels(a)
            assert _is_mask_of_levels(mask, cut, box) and _is_mask_of_levels(mask, cut, box, hint)
            if len(xs):   # a mask that differs inside the hint is not the levels' with or without it
                other = mask.copy()
                other[int(ys[0]), int(xs[0])] ^= 255
                assert not _is_mask_of_levels(other, cut, box) and not _is_mask_of_levels(other, cut, box, hint)


def test_eight_bit_alpha_is_stored_as_levels_and_reads_back_as_the_same_floats(tmp_path):
    """The keys' alpha travels as its 8-bit levels (MaskSet.alpha8): the masks and the float alpha equal the
    float path's (maskset_reference), the cache stores .alpha8.npy (uint8) and gives the same floats back, and the
    clean-up of the levels gives the float clean-up's alpha; the device silhouettes are made only when read."""
    h, w = 48, 64
    img = green_scene(np.maximum(disc(h, w, 24, 30, 12), disc(h, w, 5, 5, 3)))
    out = run_node("key.chroma", {"images": ImageSet([img, img[::-1].copy()])})
    ms = out["masks"]
    assert ms._make_device is not None, "the device silhouettes wait for a reader"
    levels = ms.alpha8
    ref = K.maskset_reference(levels, ms.names)
    assert all(np.array_equal(a, b) for a, b in zip(ms.masks, ref.masks))
    assert all(a.dtype == np.float32 and np.array_equal(a, b) for a, b in zip(ms.alpha, ref.alpha))
    Masks.save(ms, tmp_path)   # the masks are the levels' alpha >= 128: only the levels are stored
    assert sorted(p.name for p in tmp_path.glob("*.npy")) == ["0000.alpha8.npy", "0001.alpha8.npy"]
    ys, xs = np.nonzero(levels[0])   # of the levels, their box of non-zero pixels only
    assert np.load(tmp_path / "0000.alpha8.npy").shape == (ys.max() + 1 - ys.min(), xs.max() + 1 - xs.min())
    back = Masks.load(tmp_path)
    assert all(np.array_equal(a, b) for a, b in zip(back.alpha, ref.alpha)) and back.alpha8[0].dtype == np.uint8
    assert all(np.array_equal(a, b) for a, b in zip(back.alpha8, levels))
    empty = tmp_path / "empty"       # nothing keyed in: an empty box, the zeros come back
    empty.mkdir()
    Masks.save(MaskSet([np.zeros((h, w), np.uint8)], None, ["a"], alpha8=[np.zeros((h, w), np.uint8)]), empty)
    none = Masks.load(empty)
    assert none.alpha8[0].shape == (h, w) and not none.alpha8[0].any() and not none.masks[0].any()
    assert not (empty / "0000.npy").exists()   # an empty mask is its empty levels' threshold: not stored either
    assert all(a.dtype == np.uint8 and np.array_equal(a, b) for a, b in zip(back.masks, ref.masks))
    other = tmp_path / "other"   # masks that are not their levels' threshold are stored as they are
    other.mkdir()
    edited = [m.copy() for m in ms.masks]
    edited[1][0, 0] = 255 - edited[1][0, 0]
    Masks.save(MaskSet(edited, None, ms.names, alpha8=levels), other)
    again = Masks.load(other)
    assert (other / "0001.npy").is_file() and all(np.array_equal(a, b) for a, b in zip(again.masks, edited))
    assert all(np.array_equal(a, b) for a, b in zip(again.alpha, ref.alpha))
    ys, xs = np.nonzero(levels[1])   # an edit inside the levels' box (the check reads the boxes only) is found too
    for y, x in ((ys.min(), xs.min()), (ys.max(), xs.max()), ((ys.min() + ys.max()) // 2, (xs.min() + xs.max()) // 2)):
        inside = [m.copy() for m in ms.masks]
        inside[1][y, x] = 255 - inside[1][y, x]
        folder = tmp_path / f"inside_{y}_{x}"
        folder.mkdir()
        Masks.save(MaskSet(inside, None, ms.names, alpha8=levels), folder)
        assert np.array_equal(Masks.load(folder).masks[1], inside[1])
    as_levels = run_node("key.cleanup", {"masks": back})["masks"]
    as_floats = run_node("key.cleanup", {"masks": ref})["masks"]
    assert as_levels.alpha8 is not None and as_floats.alpha8 is None
    assert all(np.array_equal(a, b) for a, b in zip(as_levels.masks, as_floats.masks))
    assert all(np.array_equal(a, b) for a, b in zip(as_levels.alpha, as_floats.alpha))
    assert ms.device is not None and ms._make_device is None


def test_masks_and_float_alpha_are_stored_as_their_boxes_and_read_back_bit_for_bit(tmp_path):
    """A float alpha (key.person's, zero outside the hull's footprint after key.consensus) and binary masks are
    stored as the boxes of their non-zero pixels: the same arrays come back (dtype, every bit), an empty plane is an
    empty box (a -0.0 is kept in the box), entries written before as whole images still load, an alpha not the
    shape of its mask is refused, and a box that does not fit its file is a DataError naming the file."""
    from nodegraph.errors import DataError

    h, w = 60, 80
    rng = np.random.default_rng(3)
    alpha = np.zeros((h, w), np.float32)
    alpha[10:31, 25:52] = rng.random((21, 27), np.float32)            # soft values, some exactly 0 inside
    alpha[12, 30] = 0.0
    alpha[55, 2] = -0.0                                              # outside the soft box: its sign comes back too
    mask = np.where(alpha > 0.5, 255, 0).astype(np.uint8)
    ms = MaskSet([mask, np.zeros((h, w), np.uint8)], [alpha, np.zeros((h, w), np.float32)], ["a", "b"])
    Masks.save(ms, tmp_path)
    ys, xs = np.nonzero(mask)
    assert np.load(tmp_path / "0000.npy").shape == (ys.max() + 1 - ys.min(), xs.max() + 1 - xs.min())
    assert np.load(tmp_path / "0000.alpha.npy").shape == (46, 50) and np.load(tmp_path / "0001.alpha.npy").size == 0
    back = Masks.load(tmp_path)
    for got, want in zip(back.masks + back.alpha, [mask, ms.masks[1], alpha, ms.alpha[1]]):
        assert got.dtype == want.dtype and got.shape == want.shape and got.tobytes() == want.tobytes()
    old = tmp_path / "old"            # the former layout: whole images, no boxes in names.json
    old.mkdir()
    for i in range(2):
        np.save(old / f"{i:04d}.npy", ms.masks[i])
        np.save(old / f"{i:04d}.alpha.npy", ms.alpha[i])
    (old / "names.json").write_text(json.dumps({"names": ["a", "b"], "alpha": True, "alpha8": False,
                                                "masks_from_alpha8": False}))
    again = Masks.load(old)
    assert all(np.array_equal(a, b) for a, b in zip(again.masks + again.alpha, ms.masks + ms.alpha))
    assert "alpha 0 must be an array the shape of its mask" in Masks.check(MaskSet([mask], [alpha[..., None]], ["a"]))
    meta = json.loads((tmp_path / "names.json").read_text())
    meta["alpha_boxes"][0][4] += 1    # the box one pixel wider than its file
    (tmp_path / "names.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match="0000.alpha.npy"):
        Masks.load(tmp_path)


# ---------------------------------------------------------------- GrabCut at the boundary
def dark_cap_scene():
    """A red body with a dark cap (hair) on a dark greenish wall; a rough mask with a halo and a bite."""
    import cv2

    h, w = 96, 96
    body = disc(h, w, 58, 48, 26)
    cap = disc(h, w, 34, 48, 18) & ~body
    truth = np.maximum(body, cap)
    img = np.empty((h, w, 3))
    img[:] = (12, 16, 11)
    img[body > 0] = (190, 40, 40)
    img[cap > 0] = (30, 20, 16)
    img = np.clip(img + np.random.default_rng(9).normal(0, 2.5, img.shape), 0, 255).astype(np.uint8)
    rough = cv2.dilate(truth, np.ones((7, 7), np.uint8))
    rough[10:24, 40:60] = 0
    return img, rough, truth


def test_grabcut_removes_halo_and_restores_dark_cap():
    img, rough, truth = dark_cap_scene()
    assert iou(rough, truth) < 0.8
    out = run_node("key.grabcut", {"images": ImageSet([img]), "masks": MaskSet([rough])}, roundtrip=True)
    m = out["masks"].masks[0]
    assert iou(m, truth) > 0.97
    assert m[10:24, 40:60][truth[10:24, 40:60] > 0].min() == 255  # the bite is back
    again = run_node("key.grabcut", {"images": ImageSet([img]), "masks": MaskSet([rough])})["masks"].masks[0]
    assert np.array_equal(again, m)  # seeded: repeatable
    empty = run_node("key.grabcut", {"images": ImageSet([img]), "masks": MaskSet([np.zeros_like(rough)])})
    assert empty["masks"].masks[0].max() == 0


def test_grabcut_checks_sizes():
    img, rough, _ = dark_cap_scene()
    with pytest.raises(NodeError, match="camera 'cam000': mask 95x96"):
        run_node("key.grabcut", {"images": ImageSet([img]), "masks": MaskSet([rough[:, :-1]])})
    with pytest.raises(NodeError, match="1 images but 2 masks"):
        run_node("key.grabcut", {"images": ImageSet([img]), "masks": MaskSet([rough, rough])})


# ---------------------------------------------------------------- consensus
def numpy_hull(masks, cameras, bounds, res, max_miss) -> VoxelGrid:
    """Voxels whose centre falls inside all but ``max_miss`` silhouettes (test reference, not the hull node)."""
    lo, hi = bounds
    grid = VoxelGrid(np.zeros((res,) * 3, np.uint8), lo, hi)
    c = grid.centers().reshape(-1, 3)
    miss = np.zeros(len(c), int)
    for v, m in enumerate(masks):
        uv, z = cameras.project(c, v)
        px = np.rint(uv).astype(int)
        ok = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < m.shape[1]) & (px[:, 1] >= 0) & (px[:, 1] < m.shape[0])
        inside = np.zeros(len(c), bool)
        inside[ok] = m[px[ok, 1], px[ok, 0]] > 127
        miss += ~inside
    grid.occupancy = (miss <= max_miss).reshape((res,) * 3).astype(np.uint8)
    return grid


def consensus_scene():
    cams = ring_rig(6)
    truth = [sphere_mask(cams, v) for v in range(6)]
    keyed = [t.copy() for t in truth]
    keyed[2][2:10, 2:12] = 255  # a false blob only camera 2 believes in
    keyed[4][40:46, 50:60] = 255  # and another in camera 4
    bounds = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    volume = numpy_hull(keyed, cams, bounds, 32, max_miss=1)
    return cams, truth, keyed, volume


def test_consensus_rejects_single_view_foreground():
    cams, truth, keyed, volume = consensus_scene()
    out = run_node("key.consensus", {"masks": MaskSet(keyed), "cameras": cams, "volume": volume}, roundtrip=True)
    for v in range(6):
        assert iou(out["masks"].masks[v], truth[v]) > 0.99
    assert out["masks"].masks[2][2:10, 2:12].max() == 0 and out["masks"].masks[4][40:46, 50:60].max() == 0


def test_consensus_keeps_masks_and_alpha_inside_the_footprint_bit_for_bit():
    """key.consensus's masks and float alpha are the inputs where the hull's footprint is, 0 elsewhere: the
    np.where form's bytes (a soft alpha's -0.0 inside kept, +0.0 outside)."""
    from nodes.key.keying import hull_footprint

    cams, _, keyed, volume = consensus_scene()
    rng = np.random.default_rng(8)
    alpha = [np.where(rng.random(m.shape) < 0.2, -0.0, rng.random(m.shape) * (m > 0)).astype(np.float32) for m in keyed]
    out = run_node("key.consensus", {"masks": MaskSet(keyed, alpha), "cameras": cams, "volume": volume})["masks"]
    for v, (m, a) in enumerate(zip(keyed, alpha)):
        keep = hull_footprint(volume, cams, v, 2) > 0
        assert 0 < keep.sum() < keep.size
        assert out.masks[v].dtype == np.uint8 and np.array_equal(out.masks[v], np.where(keep, m, 0).astype(np.uint8))
        assert out.alpha[v].dtype == np.float32 and out.alpha[v].tobytes() == np.where(keep, a, 0).astype(np.float32).tobytes()


def test_hull_footprint_equals_the_whole_image_reference():
    """The footprint dilated and filled on the splat's box equals the whole image's, also where it runs off the
    image (a hull shifted half out of view) and for a hollow hull; no voxel gives no footprint."""
    from nodes.key.keying import hull_footprint, hull_footprint_reference, surface_centres

    cams, _, keyed, volume = consensus_scene()
    shifted = VoxelGrid(volume.occupancy, volume.bbox_min + [0.9, 0.0, 0.3], volume.bbox_max + [0.9, 0.0, 0.3])
    hollow = VoxelGrid(volume.occupancy.copy(), volume.bbox_min, volume.bbox_max)
    hollow.occupancy[12:20, 12:20, 12:20] = 0
    empty = VoxelGrid(np.zeros_like(volume.occupancy), volume.bbox_min, volume.bbox_max)
    edge = 0
    for vol in (volume, shifted, hollow, empty):
        centres = surface_centres(vol)
        for v in range(len(cams)):
            for d in (0, 1, 3):
                ref = hull_footprint_reference(vol, cams, v, d)
                assert np.array_equal(hull_footprint(vol, cams, v, d), ref)
                assert np.array_equal(hull_footprint(vol, cams, v, d, centres), ref)
                edge += int(ref[:, 0].any() or ref[:, -1].any() or ref[0].any() or ref[-1].any())
    assert edge > 0 and not hull_footprint(empty, cams, 0).any()


def test_consensus_checks_cameras():
    cams, _, keyed, volume = consensus_scene()
    with pytest.raises(NodeError, match="6 masks for 5 cameras"):
        run_node("key.consensus", {"masks": MaskSet(keyed), "cameras": Cameras(cams.cameras[:5]), "volume": volume})


def test_bad_params_are_named():
    img = np.zeros((8, 8, 3), np.uint8)
    img[:] = GREEN
    with pytest.raises(NodeError, match="'outer'"):
        run_node("key.chroma", {"images": ImageSet([img])}, {"inner": 0.3, "outer": 0.2})
    with pytest.raises(NodeError, match="'cameras' and 'bounds'"):
        run_node("key.chroma", {"images": ImageSet([img]), "cameras": ring_rig(1)})
    with pytest.raises(NodeError, match="image of camera 'cam0' is 8x8 but the camera is 64x48"):
        run_node("key.chroma", {"images": ImageSet([img]), "cameras": ring_rig(1), "bounds": np.array([[0.0, 0, 0], [1, 1, 1]])})


# ---------------------------------------------------------------- golden files (small synthetic scenes)
def test_golden_key_nodes(golden):
    h, w = 24, 32
    ball = disc(h, w, 12, 15, 7)
    chroma = run_node("key.chroma", {"images": ImageSet([green_scene(ball, seed=7)])})
    golden.check("key_chroma", chroma["masks"], Masks)
    plate, frame, _, _ = plate_scene(seed=8, h=h, w=w)
    diff = run_node("key.difference", {"images": ImageSet([frame]), "background": ImageSet([plate])})
    golden.check("key_difference", diff["masks"], Masks)
    grey = run_node("key.threshold", {"images": ImageSet([frame])}, {"threshold": 0.45})
    golden.check("key_threshold", grey["masks"], Masks)
    cleaned = run_node("key.cleanup", {"masks": grey["masks"]}, {"keep": 1})
    golden.check("key_cleanup", cleaned["masks"], Masks)
    cams, _, keyed, volume = consensus_scene()
    cons = run_node("key.consensus", {"masks": MaskSet(keyed[:2]), "cameras": Cameras(cams.cameras[:2]), "volume": volume})
    golden.check("key_consensus", cons["masks"], Masks)


def test_grabcut_golden(small_stage, golden):
    # start from a dilated (too fat) silhouette: GrabCut must pull it back towards the truth
    import cv2

    fat = [cv2.dilate(m, np.ones((5, 5), np.uint8)) for m in small_stage["masks"].masks]
    out = run_node("key.grabcut", {"images": small_stage["images"], "masks": MaskSet(fat)})
    def iou(a, b):
        return np.logical_and(a > 127, b > 127).sum() / np.logical_or(a > 127, b > 127).sum()
    before = np.mean([iou(f, t) for f, t in zip(fat, small_stage["masks"].masks)])
    after = np.mean([iou(m, t) for m, t in zip(out["masks"].masks, small_stage["masks"].masks)])
    assert before < 0.75 and after > 0.95, (before, after)
    golden.check("key_grabcut_figure", out["masks"], Masks, iou=0.99)


def test_plate_from_footage_where_the_subject_moves_away():
    """key.plate: a textured background and a square that crosses it over 12 frames (every pixel covered in fewer
    than half): the median plate is the background exactly, the difference key against it finds the square; a
    second square that never moves is reported (stable, so it ends up in the plate: only motion shows background)."""
    from nodes.common.types import ImageSet

    rng = np.random.default_rng(0)
    h, w = 60, 90
    yy, xx = np.mgrid[0:h, 0:w]
    bg = [np.clip(np.dstack([60 + xx, 80 + yy, 120 + 0 * xx + 20 * v]) + rng.integers(-3, 4, (h, w, 3)), 0, 255)
          .astype(np.uint8) for v in range(2)]                    # a shaded wall with sensor noise
    frames, truth = [], []
    for k in range(12):
        ims, ms = [], []
        for v in range(2):
            im, m = bg[v].copy(), np.zeros((h, w), bool)
            x = 5 + 7 * k
            m[20:35, x:x + 12] = True
            im[m] = (250, 30, 30)
            if v == 1:
                im[45:55, 5:15] = (10, 220, 10)                      # never moves
            ims.append(im)
            ms.append(m)
        frames.append(ImageSet(ims, ["a", "b"]))
        truth.append(ms)
    out = run_node("key.plate", {"images": frames}, {}, frames=list(range(12)))
    assert np.array_equal(out["background"].images[0], bg[0])
    rep = out["report"]["cameras"]
    assert rep["a"]["stable"] == 1.0 and rep["b"]["unstable_pixels"] == 0        # the still square is stable...
    assert np.all(out["background"].images[1][45:55, 5:15] == (10, 220, 10))      # ...and in the plate
    keyed = run_node("key.difference", {"images": frames[6], "background": out["background"]})["masks"]
    got = keyed.masks[0] > 127
    assert (got & truth[6][0]).sum() / (got | truth[6][0]).sum() > 0.95
    with pytest.raises(Exception, match="at least 3"):
        run_node("key.plate", {"images": frames[:2]}, {}, frames=[0, 1])


def test_plate_golden(golden):
    """key.plate's report on a slowly crossing square whose colour changes (its middle covered in most frames, by
    other colours: unstable), a still patch (stable) and a one-frame glitch (every count exact: uint8 medians)."""
    rng = np.random.default_rng(1)
    bg = rng.integers(60, 70, (40, 50, 3)).astype(np.uint8)
    frames = []
    for k in range(8):
        im = bg.copy()
        im[10:20, 2 * k:2 * k + 12] = 100 + 18 * k                     # slow, changing colour: its middle unstable
        im[30:36, 2:8] = 5                                            # still: stable, in the plate
        frames.append(ImageSet([im], ["a"]))
    frames[3].images[0][0:40, 45:50] = 255                            # one frame's glitch: not in the plate
    rep = run_node("key.plate", {"images": frames}, {}, frames=list(range(8)))["report"]
    golden.check("key_plate_square", rep, Table)


def test_chroma_key_images_black_outside_the_alpha_window_and_stored_as_the_window(tmp_path):
    """key.chroma's despilled images are black beyond `window_margin` pixels around the box of the alpha, and say
    so (ImageSet.windows); Images stores the windows' pixels only and gives the same images back. -1 keeps the
    whole images (the despill inside the box is the same). The key holds the windows' pixels alone
    (``ImageSet.crops``) until a reader asks for whole images; stored, they are the same files as the whole images'
    windows."""
    from nodes.common.types import Images

    h, w = 120, 160
    ball = disc(h, w, 60, 70, 15)
    img = green_scene(ball)
    out = run_node("key.chroma", {"images": ImageSet([img, img[:, ::-1].copy()])}, params={"window_margin": 8})
    whole = run_node("key.chroma", {"images": ImageSet([img, img[:, ::-1].copy()])}, params={"window_margin": -1})
    s = out["images"]
    assert whole["images"].windows is None and whole["images"].crops is None
    crops, shapes = s.crops
    assert s._images is None and shapes == [(h, w, 3)] * 2          # no whole image made yet
    assert [c.shape for c in crops] == [(y1 - y0, x1 - x0, 3) for x0, y0, x1, y1 in s.windows]
    (tmp_path / "crops").mkdir()
    Images.save(s, tmp_path / "crops")
    assert s._images is None                                         # saving does not make them either
    assert Images.check(ImageSet.cropped([crops[0][1:], crops[1]], shapes, s.windows, s.names)).startswith("image 0")
    # a camera without a window (its crop: the whole image) and an empty window: the same as the whole images
    mixed = ImageSet.cropped([img, np.zeros((0, 0, 3), np.uint8)], [(h, w, 3)] * 2, [None, [0, 0, 0, 0]], ["a", "b"])
    assert Images.check(mixed) is None and mixed.images[0] is img and not mixed.images[1].any()
    (tmp_path / "mixed").mkdir()
    Images.save(mixed, tmp_path / "mixed")
    back = Images.load(tmp_path / "mixed")
    assert np.array_equal(back.images[0], img) and not back.images[1].any() and back.windows == [None, [0, 0, 0, 0]]
    for k, (im, win, full, alpha) in enumerate(zip(s.images, s.windows, whole["images"].images, out["masks"].alpha8)):
        ys, xs = np.nonzero(alpha)
        assert win == [xs.min() - 8, ys.min() - 8, xs.max() + 1 + 8, ys.max() + 1 + 8], (k, win)
        x0, y0, x1, y1 = win
        inside = np.zeros((h, w), bool)
        inside[y0:y1, x0:x1] = True
        assert not im[~inside].any() and full[~inside].any()          # black outside; the whole image is not
        assert np.array_equal(im[inside], full[inside])
    Images.save(ImageSet(s.images, s.names, s.windows), tmp_path)   # the same images given whole
    for f in ("0000.npy", "0001.npy", "names.json", "windows.json"):
        assert (tmp_path / f).read_bytes() == (tmp_path / "crops" / f).read_bytes(), f
    assert sum(p.stat().st_size for p in tmp_path.glob("*.npy")) < 0.25 * 2 * img.nbytes
    back = Images.load(tmp_path)
    assert back.windows == s.windows and all(np.array_equal(a, b) for a, b in zip(back.images, s.images))
    assert Images.check(back) is None
    assert "window" in Images.check(ImageSet(s.images, s.names, [[0, 0, w + 1, h], None]))


def test_matte_edges_equal_their_loop_reference():
    """The garbage matte's edges (vectorised) against the plain loop version: the same float32 rows for random
    rigs, boxes (float64 and float32) and margins, distorted lenses and boxes partly behind a camera included."""
    from nodes.common.cameras import Cameras, look_at

    rng = np.random.default_rng(5)
    empty = 0
    for t in range(300):
        eye = rng.normal(size=3) * 3
        eye[2] = abs(eye[2]) + 0.5
        cam = look_at(eye, rng.normal(size=3) * 0.2, [0, 0, 1], rng.uniform(30, 70), 1920, 1080)
        if t % 2:
            cam.dist = rng.normal(size=5) * 0.02
        cams = Cameras([cam])
        lo = rng.normal(size=3) * (3.0 if t % 7 == 0 else 0.3) - 1
        box = np.array([lo, lo + rng.uniform(0.3, 2, 3)], np.float32 if t % 3 == 0 else np.float64)
        margin = float(rng.uniform(0, 10))
        got, want = K._matte_edges(cams, 0, box, margin), K._matte_edges_reference(cams, 0, box, margin)
        empty += len(want) == 0
        assert got.dtype == want.dtype == np.float32 and got.shape == want.shape
        np.testing.assert_array_equal(got, want)
    assert 0 < empty < 100           # some boxes reach behind the camera (no matte), most do not
