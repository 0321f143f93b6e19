"""The deliverables as a pipeline checks them: every USD / USDZ export passes usd-core's validators, every GLB
shades smooth (NORMAL), the timed exports share one frame rate and loop cleanly, the skinned mesh's bounds cover
its animation. Small synthetic inputs: a textured and a vertex-coloured ball, a two-segment tracked sequence,
a two-bone rig."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from nodegraph.testing import run_node
from nodes.common.types import FPS, SkeletonData
from rig import two_segments


@pytest.fixture(scope="module")
def textured():
    from PIL import Image

    ball = trimesh.creation.icosphere(2)
    v = np.asarray(ball.vertices)
    uv = np.column_stack([np.arctan2(v[:, 1], v[:, 0]) / (2 * np.pi) + 0.5, np.arccos(np.clip(v[:, 2], -1, 1)) / np.pi])
    checker = (np.indices((16, 16)).sum(0) % 2 * 200 + 30).astype(np.uint8)
    image = Image.fromarray(np.dstack([checker] * 3))
    return trimesh.Trimesh(v, ball.faces, visual=trimesh.visual.TextureVisuals(uv=uv, image=image), process=False)


@pytest.fixture(scope="module")
def coloured():
    ball = trimesh.creation.icosphere(2)
    return trimesh.Trimesh(ball.vertices, ball.faces, vertex_colors=[200, 100, 50, 255], process=False)


@pytest.fixture(scope="module")
def sequence():
    """Five frames (10..14) in two segments: a growing ball, then a moving box."""
    return two_segments()


@pytest.fixture(scope="module")
def rig():
    """A vertical bar (z 0..2) on two joints (0, 0, 0) -> (0, 0, 1); the upper bone bends about x over 6 frames
    (to 90 degrees), so the bar's tip sweeps out of the rest pose's bounds."""
    from scipy.spatial.transform import Rotation

    bar = trimesh.creation.box(extents=[0.2, 0.2, 2.0])
    bar = trimesh.Trimesh(bar.vertices + [0, 0, 1.0], bar.faces, process=False).subdivide().subdivide()
    v = np.asarray(bar.vertices)
    upper = np.clip(v[:, 2] - 0.5, 0, 1)
    weights = np.column_stack([1 - upper, upper])
    joints = np.array([[0, 0, 0], [0, 0, 1.0]])
    n = 6
    rot = np.tile(np.eye(3), (n, 2, 1, 1))
    trans = np.zeros((n, 2, 3))
    for f in range(n):
        r = Rotation.from_euler("x", 90 * f / (n - 1), degrees=True).as_matrix()
        rot[f, 1] = r
        trans[f, 1] = joints[1] - r @ joints[1]               # about the upper joint's pivot
    sk = SkeletonData(joints, [-1, 0], ["root", "upper"], weights, rot, trans, list(range(3, 3 + n)))
    return sk, bar


def usd_exports(textured, coloured, sequence, rig) -> dict[str, bytes]:
    """Every USD file the export nodes write for these inputs, by name."""
    files = {}
    for ext in ("usda", "usdc", "usdz"):
        files.update(run_node("export.textured", {"mesh": textured}, {"path": f"t.{ext}"})["files"])
    files.update(run_node("export.textured", {"mesh": coloured}, {"path": "v.usda"})["files"])
    files.update(run_node("track.export", {"sequence": sequence}, {"name": "dyn", "formats": ["usd"]})["files"])
    sk, rest = rig
    files.update(run_node("skeleton.export", {"skeleton": sk, "rest": rest}, {"name": "rig", "formats": "usd"})["files"])
    return files


def test_every_usd_export_passes_the_usd_validators(textured, coloured, sequence, rig):
    from nodes.common.usd import validation_errors

    files = usd_exports(textured, coloured, sequence, rig)
    layers = [n for n in files if n.rsplit(".", 1)[-1] in ("usda", "usdc", "usdz", "usd")]
    assert sorted(layers) == ["dyn.usdc", "rig.usd", "t.usda", "t.usdc", "t.usdz", "v.usda"]
    for name in layers:
        assert validation_errors(files, name) == [], name


def test_the_validators_catch_what_they_are_run_for():
    from nodes.common.usd import UsdStage, validation_errors

    errors = validation_errors({"bare.usda": UsdStage(up_axis=None).save("bare.usda")}, "bare.usda")
    assert any(e.startswith("MissingUpAxisMetadata") for e in errors)
    assert any(e.startswith("MissingDefaultPrim") for e in errors)


def test_the_dynamic_mesh_and_the_rig_keep_one_clock(sequence, rig):
    import pygltflib as G

    from nodes.common.usd import opened

    from nodegraph import node_class

    assert node_class("track.export").params["fps"] is node_class("skeleton.export").params["fps"]    # one parameter
    sk, rest = rig
    dyn = run_node("track.export", {"sequence": sequence}, {"name": "dyn", "formats": ["usd", "gltf"]})["files"]
    rig_files = run_node("skeleton.export", {"skeleton": sk, "rest": rest}, {"name": "rig"})["files"]
    for name, data in (("dyn.usdc", dyn["dyn.usdc"]), ("rig.usd", rig_files["rig.usd"])):
        with opened(data, "." + name.split(".")[-1]) as stage:
            assert stage.GetTimeCodesPerSecond() == FPS and stage.GetFramesPerSecond() == FPS, name
    assert G.GLTF2.load_from_bytes(dyn["dyn.glb"]).extras["fps"] == FPS
    from nodes.skeleton import formats

    times = formats.read_gltf(rig_files["rig.glb"])["times"]
    np.testing.assert_allclose(times[1] - times[0], 1 / FPS, rtol=1e-6)


def _normals(glb: bytes):
    """Per mesh of a GLB: (POSITION, NORMAL, [NORMAL morph-target displacements]), in the world frame."""
    import pygltflib as G

    from nodes.common.gltf import read_accessor, world_points

    g = G.GLTF2.load_from_bytes(glb)
    blob = g.binary_blob()
    read = lambda i: world_points(read_accessor(g, blob, i))  # noqa: E731
    out = []
    for mesh in g.meshes:
        prim = mesh.primitives[0]
        assert prim.attributes.NORMAL is not None, "a GLB without NORMAL shades flat"
        out.append((read(prim.attributes.POSITION), read(prim.attributes.NORMAL),
                    [read(t["NORMAL"]) for t in prim.targets or []]))
    return out


def test_every_glb_carries_smooth_unit_normals(textured, coloured, sequence, rig):
    from nodes.common.meshops import smooth_vertex_normals

    glbs = {"textured": run_node("export.textured", {"mesh": textured}, {"path": "t.glb"})["files"]["t.glb"],
            "coloured": run_node("export.mesh", {"mesh": coloured}, {"path": "v.glb"})["files"]["v.glb"],
            "dynamic": run_node("track.export", {"sequence": sequence}, {"name": "d", "formats": ["gltf"]})["files"]["d.glb"]}
    sk, rest = rig
    glbs["rig"] = run_node("skeleton.export", {"skeleton": sk, "rest": rest}, {"name": "r", "formats": "gltf"})["files"]["r.glb"]
    for name, glb in glbs.items():
        for pos, nrm, _ in _normals(glb):
            np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1, atol=1e-5, err_msg=name)
            assert (nrm * (pos - pos.mean(0))).sum(1).min() > 0, name       # convex inputs: every normal points out
    for mesh, (_, nrm, _) in ((textured, _normals(glbs["textured"])[0]), (rest, _normals(glbs["rig"])[0])):
        np.testing.assert_allclose(nrm, smooth_vertex_normals(mesh.vertices, mesh.faces), atol=1e-6)
    # the dynamic mesh: each frame's normals are its segment's base plus that frame's NORMAL morph target
    (_, n0, d0), (_, n1, d1) = _normals(glbs["dynamic"])
    frames = [n0] + [n0 + d for d in d0] + [n1] + [n1 + d for d in d1]
    for m, n in zip(sequence, frames):
        np.testing.assert_allclose(n, smooth_vertex_normals(m.vertices, m.faces), atol=1e-6)


def _clip(glb: bytes):
    """(duration: the last key time over all samplers, [(input times, output values, interpolation)])."""
    import pygltflib as G

    from nodes.common.gltf import read_accessor

    g = G.GLTF2.load_from_bytes(glb)
    blob = g.binary_blob()
    (anim,) = g.animations
    samplers = [(read_accessor(g, blob, s.input), read_accessor(g, blob, s.output), s.interpolation)
                for s in anim.samplers]
    return max(float(t[-1]) for t, _, _ in samplers), samplers


def test_animations_loop_every_frame_for_one_frame_period(sequence, rig):
    """A looping viewer plays [0, duration) again and again: the clip lasts n / fps, so the last frame shows for
    1 / fps like every other (were its key the clip's end it would show for 0 s)."""
    from nodes.skeleton import formats as rig_formats
    from nodes.track import formats

    fps = 10.0
    glb = run_node("track.export", {"sequence": sequence}, {"name": "d", "formats": ["gltf"], "fps": fps})["files"]["d.glb"]
    n = len(sequence)
    duration, samplers = _clip(glb)
    assert duration == pytest.approx(n / fps) and formats.clip_duration([10, 11, 12, 13, 14], fps) == n / fps
    for times, values, interpolation in samplers:
        assert interpolation == "STEP" and times[-1] == pytest.approx(n / fps)     # every channel spans the clip
        last = values.reshape(len(times), -1)
        np.testing.assert_array_equal(last[-1], last[-2])                           # the end key repeats the last
    last_weights = samplers[-2][0]                      # the last segment's weights: frames 13, 14, then the end
    np.testing.assert_allclose(last_weights, np.array([3, 4, 5]) / fps, atol=1e-6)
    np.testing.assert_allclose(formats.gltf_frame(glb, n - 1), sequence[-1].vertices, atol=1e-6)

    sk, rest = rig
    files = run_node("skeleton.export", {"skeleton": sk, "rest": rest}, {"name": "r", "fps": fps})["files"]
    duration, samplers = _clip(files["r.glb"])
    frames = len(sk.frames)
    assert duration == pytest.approx(frames / fps)
    for times, values, _ in samplers:
        np.testing.assert_allclose(times, np.arange(frames + 1) / fps, atol=1e-6)
        np.testing.assert_array_equal(values[-1], values[-2])
    gl = rig_formats.read_gltf(files["r.glb"])
    np.testing.assert_array_equal(gl["skinned"][-1], gl["skinned"][-2])


def test_the_rig_extent_covers_the_skinned_mesh_over_the_animation(rig, tmp_path):
    from pxr import Usd, UsdGeom

    from nodes.skeleton import formats

    sk, rest = rig
    (tmp_path / "r.usd").write_bytes(run_node("skeleton.export", {"skeleton": sk, "rest": rest},
                                              {"name": "r", "formats": "usd"})["files"]["r.usd"])
    skinned = formats.read_usd(tmp_path / "r.usd")["skinned"]             # UsdSkel's own skinning, per frame
    stage = Usd.Stage.Open(str(tmp_path / "r.usd"))
    extent = UsdGeom.Boundable(stage.GetPrimAtPath("/Rig")).GetExtentAttr()
    assert extent.GetTimeSamples() == [float(f) for f in sk.frames]
    rest_extent = np.array(UsdGeom.Mesh(stage.GetPrimAtPath("/Rig/Mesh")).GetExtentAttr().Get())
    np.testing.assert_allclose(rest_extent, [rest.vertices.min(0), rest.vertices.max(0)], atol=1e-6)
    cache = UsdGeom.BBoxCache(Usd.TimeCode(0), [UsdGeom.Tokens.default_])
    for frame, points in zip(sk.frames, skinned):
        lo, hi = np.array(extent.Get(Usd.TimeCode(frame)))
        np.testing.assert_allclose([lo, hi], [points.min(0), points.max(0)], atol=1e-5)    # tight, every frame
        cache.SetTime(Usd.TimeCode(frame))
        box = cache.ComputeWorldBound(stage.GetPrimAtPath("/Rig")).ComputeAlignedRange()
        assert np.all(np.array(box.GetMin()) <= points.min(0) + 1e-5) and np.all(np.array(box.GetMax()) >= points.max(0) - 1e-5)
    assert skinned[-1][:, 1].min() < rest_extent[0, 1] - 0.5            # the bent bar leaves the rest bounds


def _y_up(stage, points) -> np.ndarray:
    """USD points as a +Y-up, metres tool places them (what Blender or a glTF scene does with a stage's
    upAxis and metersPerUnit)."""
    from pxr import UsdGeom

    p = np.asarray(points, np.float64) * UsdGeom.GetStageMetersPerUnit(stage)
    return p if UsdGeom.GetStageUpAxis(stage) == "Y" else p @ np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]).T


def test_glb_and_usd_of_one_asset_stand_upright_and_coincide(rig):
    """The world frame is +Z up, metres; a glTF reader (raw accessors: +Y up) and a USD reader (points + upAxis +
    metersPerUnit) see the same upright bar, feet on the floor, within 1 mm: static textured, dynamic and rigged."""
    import pygltflib as G
    from PIL import Image
    from pxr import Usd, UsdGeom

    from nodes.common.gltf import gltf_points, read_accessor
    from nodes.common.usd import opened
    from nodes.track.formats import gltf_frame

    _, bar = rig                                                  # 0.2 x 0.2 x 2 m, z 0..2
    tex = trimesh.Trimesh(bar.vertices, bar.faces, visual=trimesh.visual.TextureVisuals(
        uv=np.asarray(bar.vertices)[:, :2] + 0.5, image=Image.new("RGB", (8, 8))), process=False)
    files = run_node("export.textured", {"mesh": tex}, {"path": "bar.glb"})["files"]
    files.update(run_node("export.textured", {"mesh": tex}, {"path": "bar.usda"})["files"])
    g = G.GLTF2.load_from_bytes(files["bar.glb"])
    glb = read_accessor(g, g.binary_blob(), g.meshes[0].primitives[0].attributes.POSITION).astype(np.float64)
    assert abs(glb[:, 1].min()) < 1e-6 and abs(glb[:, 1].max() - 2.0) < 1e-6       # +Y up, on the floor, 2 m tall
    with opened(files["bar.usda"], ".usda") as stage:
        mesh = next(UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
        usd = _y_up(stage, mesh.GetPointsAttr().Get())
    assert np.abs(np.sort(usd, axis=0) - np.sort(glb, axis=0)).max() < 1e-3

    # a moving, tracked bar: every frame alike in both files
    seq = [trimesh.Trimesh(bar.vertices + [0.1 * k, 0, 0.05 * k], bar.faces, process=False, metadata={"frame": k})
           for k in range(3)]
    dyn = run_node("track.export", {"sequence": seq}, {"name": "dyn", "formats": ["usd", "gltf"]})["files"]
    with opened(dyn["dyn.usdc"]) as stage:
        meshes = [UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
        for k in range(3):
            raw = gltf_points(gltf_frame(dyn["dyn.glb"], k))        # the reader gives the world frame: glTF's axes again
            usd = _y_up(stage, meshes[0].GetPointsAttr().Get(Usd.TimeCode(k)))
            assert np.abs(usd - raw).max() < 1e-3, k
            assert abs(raw[:, 1].min() - 0.05 * k) < 1e-5                            # it rises along glTF's +Y
