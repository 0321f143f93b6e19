"""The format layers compose: one glTF mesh with NORMAL, TEXCOORD_0, morph targets, a skin and a texture
material together; one USD stage holding a time-sampled, textured and skinned mesh. Read back with
pygltflib / trimesh and usd-core."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from nodes.common.gltf import GltfBuilder, gltf_points, read_accessor, texture_uv, world_points

PNG = bytes.fromhex("89504e470d0a1a0a0000000d49484452000000010000000108020000009077"
                    "53de0000000c4944415408d763f8cfc000000301010018dd8db00000000049454e44ae426082")


@pytest.fixture
def box():
    m = trimesh.creation.box()
    return np.asarray(m.vertices, np.float32), np.asarray(m.faces), np.asarray(m.vertex_normals, np.float32)


def test_gltf_mesh_with_normals_uv_morphs_skin_and_texture(box):
    import pygltflib as G

    v, f, n = box
    uv = (v[:, :2] + 0.5).astype(np.float32)
    targets = [np.full_like(v, 0.1), np.full_like(v, -0.2)]
    b = GltfBuilder("test")
    m = b.mesh(v, f, normals=n, uv=texture_uv(uv), targets=targets, joints=np.zeros((len(v), 4), np.uint16),
               weights=np.tile([1.0, 0, 0, 0], (len(v), 1)))
    b.set_material(m, b.texture_material(PNG))
    body = b.node("body", mesh=m)
    root = b.node("root", translation=[0, 0, 1])
    b.node("tip", parent=root, translation=[0, 0, 0.5])
    b.skin([root], np.linalg.inv(np.diag([1.0, 1, 1, 1])[None]), skeleton=root, node=body)
    times = np.array([0.0, 0.5], np.float32)
    b.animate(body, "weights", times, [[0, 0], [1, 0]], "STEP")
    b.animate(root, "translation", times, [[0, 0, 1], [0, 0, 2]])
    data = b.glb(extras={"fps": 2})

    g = G.GLTF2.load_from_bytes(data)
    blob = g.binary_blob()
    assert all(view.byteOffset % 4 == 0 for view in g.bufferViews)
    prim = g.meshes[0].primitives[0]
    pos = read_accessor(g, blob, prim.attributes.POSITION)
    np.testing.assert_array_equal(pos[:, 1], v[:, 2])                         # glTF is +Y up: world z is its y
    np.testing.assert_array_equal(world_points(pos), v)
    np.testing.assert_array_equal(world_points(read_accessor(g, blob, prim.attributes.NORMAL)), n)
    np.testing.assert_allclose(read_accessor(g, blob, prim.attributes.TEXCOORD_0)[:, 1], 1 - uv[:, 1])
    np.testing.assert_array_equal(read_accessor(g, blob, prim.indices).reshape(-1, 3), f)
    for t, tg in zip(targets, prim.targets):
        acc = g.accessors[tg["POSITION"]]
        tg_ = gltf_points(t).astype(np.float32)
        assert acc.min == tg_.min(0).tolist() and acc.max == tg_.max(0).tolist()  # required by the specification
    acc = g.accessors[prim.attributes.POSITION]
    assert acc.min == pos.min(0).tolist() and acc.max == pos.max(0).tolist()
    assert g.nodes[root].translation == [0, 1, 0] and g.nodes[2].translation == [0, 0.5, 0]   # world +z = glTF +y
    keys = read_accessor(g, blob, g.animations[0].samplers[1].output)
    np.testing.assert_array_equal(keys, [[0, 1, 0], [0, 2, 0]])
    assert g.nodes[body].skin == 0 and g.nodes[root].children == [2] and g.scenes[0].nodes == [body, root]
    anim = g.animations[0]
    assert anim.samplers[0].input == anim.samplers[1].input                   # the same key times, one accessor
    assert g.images[0].mimeType == "image/png" and prim.material == 0 and g.extras == {"fps": 2}
    tm = trimesh.load(trimesh.util.wrap_as_stream(data), file_type="glb", force="mesh", process=False)
    np.testing.assert_allclose(tm.visual.uv, uv, atol=1e-6)                  # another reader: trimesh's UVs again


def test_gltf_mesh_without_a_material_gets_a_plain_one(box):
    """A primitive left without a material (a rig, a dynamic mesh) is written with a plain white, non-metallic one:
    glTF's default material is fully metallic, and three.js with lights and no environment drew child_rope's
    character black; a textured primitive keeps its own."""
    import pygltflib as G

    v, f, _ = box
    b = GltfBuilder("test")
    b.node("bare", mesh=b.mesh(v, f))
    tex = b.mesh(v, f, uv=texture_uv(v[:, :2].astype(np.float32)))
    b.set_material(tex, b.texture_material(PNG))
    b.node("textured", mesh=tex)
    g = G.GLTF2.load_from_bytes(b.glb())
    bare, textured = (g.meshes[i].primitives[0] for i in (0, 1))
    assert textured.material == 0 and g.materials[0].pbrMetallicRoughness.baseColorTexture.index == 0
    plain = g.materials[bare.material].pbrMetallicRoughness
    assert bare.material == 1 and plain.metallicFactor == 0.0 and plain.baseColorFactor == [1.0, 1.0, 1.0, 1.0]


@pytest.mark.parametrize("fps", [24, 25, 30, 50, 60])
def test_gltf_key_times_never_lie_after_their_frame(box, fps):
    """A player sampling a STEP clip at frame k / fps (three.js's mixer.setTime) gets key k: key times are the
    float32 at or below k / fps (the nearest float32 of 10 / 60 lies above it, and three.js showed pose2sim's
    frame 9 at frame 10), increasing, each within one float32 step of its frame."""
    import pygltflib as G

    v, f, _ = box
    b = GltfBuilder("test")
    n = 300
    node = b.node("morphing", mesh=b.mesh(v, f, targets=[{"POSITION": v * 0.1}]))
    b.animate(node, "weights", np.arange(n) / fps, np.linspace(0, 1, n), "STEP")
    g = G.GLTF2.load_from_bytes(b.glb())
    times = read_accessor(g, g.binary_blob(), g.animations[0].samplers[0].input).astype(np.float64)
    exact = np.arange(n) / fps
    assert np.all(times <= exact) and np.all(np.diff(times) > 0)
    assert np.all(exact - times <= np.spacing(exact.astype(np.float32)))
    assert np.array_equal(np.searchsorted(times, exact, side="right") - 1, np.arange(n))


def test_one_usd_stage_holds_a_tracked_textured_skinned_mesh(box, tmp_path):
    from pxr import Usd, UsdGeom, UsdShade, UsdSkel

    from nodes.common.usd import UsdStage, opened

    v, f, n = box
    frames = [10, 11, 12]
    s = UsdStage(up_axis="Z", fps=25.0, frames=(10, 12))
    s.group("/Capture", skel_root=True)
    m = s.mesh("/Capture/Body", f, v, normals=n, uv=v[:, :2] + 0.5)
    for k in frames:
        s.points_at(m, v + (k - 10) * 0.1, k)
    s.visibility(m, {10: True, 12: False})
    s.material(m, "/Capture/Material", texture="body.png")
    bind = np.eye(4)[None]
    skel = s.skeleton("/Capture/Skeleton", ["root"], ["root"], bind, bind)
    s.skeleton_animation(skel, "/Capture/Skeleton/Animation", frames, np.zeros((3, 1, 3)), np.tile([0, 0, 0, 1.0], (3, 1, 1)))
    s.bind_skin(m, skel, np.zeros((len(v), 1), int), np.ones((len(v), 1)))
    for name in ("body.usda", "body.usdc"):
        with opened(s.save(name), "." + name.split(".")[1]) as st:
            assert UsdGeom.GetStageUpAxis(st) == "Z" and UsdGeom.GetStageMetersPerUnit(st) == 1.0
            assert st.GetTimeCodesPerSecond() == 25.0 and (st.GetStartTimeCode(), st.GetEndTimeCode()) == (10, 12)
            assert st.GetDefaultPrim().GetPath() == "/Capture"
            mesh = UsdGeom.Mesh(st.GetPrimAtPath("/Capture/Body"))
            np.testing.assert_allclose(np.array(mesh.GetPointsAttr().Get(Usd.TimeCode(12))), v + 0.2, atol=1e-6)
            assert mesh.ComputeVisibility(Usd.TimeCode(12)) == UsdGeom.Tokens.invisible
            assert len(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st").Get()) == len(v)
            surf = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()[0].ComputeSurfaceSource()[0]
            tex = UsdShade.Shader(surf.GetInput("diffuseColor").GetConnectedSource()[0].GetPrim())
            assert tex.GetInput("file").Get().path == "body.png"
            cache = UsdSkel.Cache()
            cache.Populate(UsdSkel.Root(st.GetPrimAtPath("/Capture")), Usd.TraverseInstanceProxies())
            skin = cache.GetSkinningQuery(mesh.GetPrim())
            xf = cache.GetSkelQuery(UsdSkel.Skeleton(st.GetPrimAtPath("/Capture/Skeleton"))).ComputeSkinningTransforms(Usd.TimeCode(11))
            pts = mesh.GetPointsAttr().Get(Usd.TimeCode(11))
            assert skin.ComputeSkinnedPoints(xf, pts, Usd.TimeCode(11))
            np.testing.assert_allclose(np.array(pts), v + 0.1, atol=1e-6)        # identity skin: the tracked points
    (tmp_path / "b.usdz").write_bytes(s.save("b.usdz", {"body.png": PNG}))
    import zipfile

    names = zipfile.ZipFile(tmp_path / "b.usdz").namelist()                 # the packer files the PNG as 0/body.png
    assert names[0] == "b.usdc" and len(names) == 2 and names[1].endswith("body.png")


@pytest.mark.parametrize("shape", [(1, 1), (7, 1), (1, 9), (64, 64), (333, 517), (1024, 1024)])
def test_png_bytes_decode_to_the_image(shape):
    """png_bytes reads back exactly with OpenCV and PIL (RGB, not BGR),
    and is a valid PNG to libpng (OpenCV) at every size, one pixel wide included."""
    import io

    import cv2
    from PIL import Image

    from nodes.common.gltf import png_bytes

    rng = np.random.default_rng(sum(shape))
    img = rng.integers(0, 256, shape + (3,), dtype=np.uint8)
    img[: shape[0] // 2] //= 64                                            # runs and noise
    data = png_bytes(img)
    np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1], img)
    with Image.open(io.BytesIO(data)) as im:
        im.verify()
    with Image.open(io.BytesIO(data)) as im:
        assert im.mode == "RGB" and np.array_equal(np.asarray(im), img)
    np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(png_bytes(img[:, ::-1]), np.uint8), 1)[:, ::-1, ::-1], img)
