"""glTF 2.0 binary (.glb) through pygltflib: one builder every export composes, and one accessor reader.

``GltfBuilder`` appends to a single binary buffer and keeps the rules of the format in one place:

    accessor     a typed view of a NumPy array: componentType from the dtype, type from the trailing shape
                 ((): SCALAR, (2,): VEC2, (3,): VEC3, (4,): VEC4, (4, 4): MAT4), every view 4-byte aligned,
                 min/max where the specification requires them (POSITION, morph-target POSITION, animation input)
    mesh         one triangle primitive: POSITION, indices, and any of NORMAL, TEXCOORD_0, COLOR_0,
                 JOINTS_0/WEIGHTS_0, morph targets; ``material`` may be given now or set later (``set_material``)
    material     metallic-roughness with a base-colour texture embedded as PNG; a primitive without one gets a plain
                 white, non-metallic material when the file is written (glTF's default is fully metallic: black in
                 a viewer with lights and no environment)
    node / skin  scene nodes (roots listed in the scene), joint hierarchies, inverse bind matrices
    animate      channels of named animations; identical key times share one input accessor
    glb          the file, with optional ``extras``

``mesh_glb`` writes a trimesh mesh (its texture or vertex colours) with it, for the mesh exports.

So a textured, morphing or skinned mesh is built by the same calls in any combination, e.g.::

    b = GltfBuilder("volcap")
    m = b.mesh(vertices, faces, uv=uv, targets=[d1, d2])
    b.set_material(m, b.texture_material(png))
    n = b.node("body", mesh=m)
    b.animate(n, "weights", times, weights, "STEP")
    data = b.glb()

Conventions: everything is given in the world frame (+Z up, metres: nodes/capture/world.py) and written in
glTF's (+Y up, metres, +Z forward) by one fixed change of basis, ``GLTF_FROM_WORLD`` (x, y, z) -> (x, z, -y),
applied here to every position, normal, morph displacement, node and key translation, rotation and scale and
inverse bind matrix, so no export does it itself and readers undo it with ``world_points`` (what Blender's
glTF importer does on its side: an asset lands upright in either). UVs are converted from trimesh's origin
(bottom-left) to glTF's (top-left) by ``texture_uv``; matrices are ours (column-vector, row-major arrays) and
written column-major here.
"""
from __future__ import annotations

import numpy as np

_COMPONENTS = {np.dtype(np.float32): 5126, np.dtype(np.uint32): 5125, np.dtype(np.uint16): 5123,
               np.dtype(np.uint8): 5121, np.dtype(np.int16): 5122, np.dtype(np.int8): 5120}
_TYPES = {(): "SCALAR", (2,): "VEC2", (3,): "VEC3", (4,): "VEC4", (3, 3): "MAT3", (4, 4): "MAT4"}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT3": 9, "MAT4": 16}
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
GLTF_FROM_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])   # +Z up -> +Y up (a rotation)


def gltf_points(p) -> np.ndarray:
    """World points or vectors (N, 3) in glTF's frame."""
    return np.asarray(p, np.float64) @ GLTF_FROM_WORLD.T


def world_points(p) -> np.ndarray:
    """glTF points or vectors (N, 3) in the world frame (what a reader does after ``read_accessor``)."""
    return np.asarray(p, np.float64) @ GLTF_FROM_WORLD


def _rotation(q) -> np.ndarray:
    """Quaternions (..., 4) xyzw of world rotations as glTF rotations (B R B^T: the axis turned by B)."""
    q = np.asarray(q, np.float64)
    return np.concatenate([q[..., :3] @ GLTF_FROM_WORLD.T, q[..., 3:]], axis=-1)


def _scale(s) -> np.ndarray:
    return np.asarray(s, np.float64) @ np.abs(GLTF_FROM_WORLD).T      # B is a signed permutation


def _matrix(m) -> np.ndarray:
    """(..., 4, 4) world transforms as glTF's: B4 M B4^T."""
    b4 = np.eye(4)
    b4[:3, :3] = GLTF_FROM_WORLD
    return b4 @ np.asarray(m, np.float64) @ b4.T


def texture_uv(uv) -> np.ndarray:
    """(V, 2) float32 glTF texture coordinates (origin top-left) of trimesh UVs (origin bottom-left)."""
    uv = np.asarray(uv, np.float32)
    return np.column_stack([uv[:, 0], 1.0 - uv[:, 1]]).astype(np.float32)


def texture_image(mesh) -> np.ndarray | None:
    """The base-colour texture of a trimesh mesh as (H, W, 3) uint8, or None."""
    visual = mesh.visual
    if getattr(visual, "kind", None) != "texture" or visual.uv is None:
        return None
    mat = visual.material
    image = getattr(mat, "baseColorTexture", None) or getattr(mat, "image", None)
    return None if image is None else np.asarray(image.convert("RGB"))


def textured_visual(uv: np.ndarray, texture: np.ndarray):
    """trimesh TextureVisuals of per-vertex ``uv`` and an (H, W, 3) uint8 ``texture`` as the PBR base colour
    (matte, single-sided): what texture makes and the TexturedMesh cache gives back."""
    import trimesh
    from PIL import Image

    mat = trimesh.visual.material.PBRMaterial(baseColorTexture=Image.fromarray(texture), metallicFactor=0.0,
                                              roughnessFactor=1.0, doubleSided=False)
    return trimesh.visual.TextureVisuals(uv=uv, material=mat)


def png_bytes(img: np.ndarray) -> bytes:
    """An (H, W, 3) RGB uint8 image as PNG file bytes."""
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img[:, :, ::-1]))
    if not ok:
        raise ValueError("could not encode the texture as PNG")
    return buf.tobytes()


def mesh_glb(mesh, generator: str = "volcap") -> bytes:
    """A trimesh mesh as a .glb of one mesh node: POSITION, NORMAL (smooth: ``meshops.smooth_vertex_normals``)
    and indices, and TEXCOORD_0 with the texture embedded as PNG in a metallic-roughness material (metallic 0,
    roughness 1, as trimesh writes it), else the vertex colours (COLOR_0) if it has any."""
    from .meshops import smooth_vertex_normals

    tex = texture_image(mesh)
    b = GltfBuilder(generator)
    normals = smooth_vertex_normals(mesh.vertices, mesh.faces)
    if tex is not None:
        m = b.mesh(mesh.vertices, mesh.faces, normals=normals, uv=texture_uv(mesh.visual.uv))
        b.set_material(m, b.texture_material(png_bytes(tex)))
    else:
        coloured = getattr(mesh.visual, "kind", None) in ("vertex", "face")
        m = b.mesh(mesh.vertices, mesh.faces, normals=normals,
                   colours=np.asarray(mesh.visual.vertex_colors) if coloured else None)
    b.node("geometry_0", mesh=m)
    return b.glb()


class GltfBuilder:
    """A glTF document being built (see the module docstring); every ``add``-style method returns an index."""

    def __init__(self, generator: str = "volcap"):
        import pygltflib as G

        self._G = G
        self.gltf = G.GLTF2(asset=G.Asset(version="2.0", generator=generator), scene=0, scenes=[G.Scene(nodes=[])])
        self._blob = bytearray()
        self._animations: dict[str, object] = {}
        self._times: dict[bytes, int] = {}

    # ------------------------------------------------------------ buffer
    def view(self, data: bytes, target: int | None = None) -> int:
        """A buffer view of ``data`` appended 4-byte aligned; its index."""
        self._blob.extend(b"\0" * (-len(self._blob) % 4))
        self.gltf.bufferViews.append(self._G.BufferView(buffer=0, byteOffset=len(self._blob), byteLength=len(data),
                                                        target=target))
        self._blob.extend(data)
        return len(self.gltf.bufferViews) - 1

    def accessor(self, array, target: int | None = None, minmax: bool = False, normalized: bool = False) -> int:
        """An accessor over ``array`` (N, *element shape), in its own buffer view; its index. ``normalized``:
        integers read as 0..1 (colours)."""
        data = np.ascontiguousarray(array)
        kind = _TYPES[data.shape[1:]]
        acc = self._G.Accessor(bufferView=self.view(data.tobytes(), target), componentType=_COMPONENTS[data.dtype],
                               count=len(data), type=kind, normalized=normalized)
        if minmax and len(data):
            flat = data.reshape(len(data), -1)
            acc.min, acc.max = flat.min(0).tolist(), flat.max(0).tolist()
        self.gltf.accessors.append(acc)
        return len(self.gltf.accessors) - 1

    # ------------------------------------------------------------ meshes and materials
    def mesh(self, vertices, faces, *, normals=None, uv=None, colours=None, joints=None, weights=None, targets=(),
             material: int | None = None, name: str | None = None) -> int:
        """A mesh of one triangle primitive; its index.

        Parameters
        ----------
        vertices, faces : (V, 3) positions, (F, 3) vertex indices.
        normals : (V, 3) unit vertex normals (NORMAL), optional.
        uv : (V, 2) glTF texture coordinates (TEXCOORD_0; see ``texture_uv``), optional.
        colours : (V, 3 or 4) uint8 vertex colours (COLOR_0, normalised), optional.
        joints, weights : (V, 4) joint indices (into the skin's joints) and weights (JOINTS_0, WEIGHTS_0).
        targets : morph targets, each (V, 3) position displacements (or a dict of attribute -> (V, 3):
            POSITION and NORMAL displacements).
        material : a material index (or set later with ``set_material``).
        """
        G = self._G
        vec = lambda a: gltf_points(a).astype(np.float32)  # noqa: E731
        attrs = G.Attributes(POSITION=self.accessor(vec(vertices), ARRAY_BUFFER, minmax=True))
        indices = self.accessor(np.asarray(faces, np.uint32).ravel(), ELEMENT_ARRAY_BUFFER)
        if normals is not None:
            attrs.NORMAL = self.accessor(vec(normals), ARRAY_BUFFER)
        if uv is not None:
            attrs.TEXCOORD_0 = self.accessor(np.asarray(uv, np.float32), ARRAY_BUFFER)
        if colours is not None:
            attrs.COLOR_0 = self.accessor(np.asarray(colours, np.uint8), ARRAY_BUFFER, normalized=True)
        if joints is not None:
            attrs.JOINTS_0 = self.accessor(np.asarray(joints, np.uint16), ARRAY_BUFFER)
            attrs.WEIGHTS_0 = self.accessor(np.asarray(weights, np.float32), ARRAY_BUFFER)
        morphs = []
        for t in targets:
            t = t if isinstance(t, dict) else {"POSITION": t}
            morphs.append({k: self.accessor(vec(v), ARRAY_BUFFER, minmax=k == "POSITION")
                           for k, v in t.items()})
        prim = G.Primitive(attributes=attrs, indices=indices, mode=G.TRIANGLES, material=material,
                           targets=morphs or None)
        self.gltf.meshes.append(G.Mesh(name=name, primitives=[prim], weights=[0.0] * len(morphs) or None))
        return len(self.gltf.meshes) - 1

    def texture_material(self, png: bytes, name: str | None = None, roughness: float = 1.0,
                         metallic: float = 0.0) -> int:
        """A metallic-roughness material whose base colour is the PNG ``png``, embedded; its index."""
        G = self._G
        self.gltf.images.append(G.Image(bufferView=self.view(png), mimeType="image/png"))
        self.gltf.textures.append(G.Texture(source=len(self.gltf.images) - 1))
        pbr = G.PbrMetallicRoughness(baseColorFactor=[1.0, 1.0, 1.0, 1.0], metallicFactor=metallic,
                                     roughnessFactor=roughness,
                                     baseColorTexture=G.TextureInfo(index=len(self.gltf.textures) - 1))
        self.gltf.materials.append(G.Material(name=name, pbrMetallicRoughness=pbr))
        return len(self.gltf.materials) - 1

    def set_material(self, mesh: int, material: int) -> None:
        for prim in self.gltf.meshes[mesh].primitives:
            prim.material = material

    # ------------------------------------------------------------ scene, skins, animation
    def node(self, name: str | None = None, *, mesh: int | None = None, skin: int | None = None,
             parent: int | None = None, translation=None, rotation=None, scale=None) -> int:
        """A node (a child of ``parent``, else a root of the scene) with a world-frame transform; its index."""
        f = lambda v, conv: None if v is None else [float(x) for x in conv(np.asarray(v, np.float64))]  # noqa: E731
        self.gltf.nodes.append(self._G.Node(name=name, mesh=mesh, skin=skin, translation=f(translation, gltf_points),
                                            rotation=f(rotation, _rotation), scale=f(scale, _scale)))
        i = len(self.gltf.nodes) - 1
        if parent is None:
            self.gltf.scenes[0].nodes.append(i)
        else:
            self.gltf.nodes[parent].children.append(i)
        return i

    def skin(self, joints: list[int], inverse_bind, skeleton: int | None = None, node: int | None = None) -> int:
        """A skin over joint nodes ``joints`` with (J, 4, 4) inverse bind matrices (ours, column-vector),
        applied to the mesh of ``node`` when given; its index."""
        ibm = _matrix(inverse_bind).transpose(0, 2, 1).astype(np.float32)    # column-major
        self.gltf.skins.append(self._G.Skin(inverseBindMatrices=self.accessor(ibm), joints=list(joints),
                                            skeleton=skeleton))
        if node is not None:
            self.gltf.nodes[node].skin = len(self.gltf.skins) - 1
        return len(self.gltf.skins) - 1

    def animate(self, node: int, path: str, times, values, interpolation: str = "LINEAR",
                animation: str = "animation") -> None:
        """A channel animating ``path`` (translation, rotation, scale, weights) of ``node``: key ``times`` in
        seconds, ``values`` one row per key (weights: all targets' weights of a key, flattened). Key times are
        the float32 at or below each time: a player sampling at frame k / fps (three.js's ``mixer.setTime``) gets
        key k, where the nearest float32 lies above it for some k (10 / 60) and a STEP clip showed frame k - 1."""
        G = self._G
        exact = np.asarray(times, np.float64).ravel()
        t = exact.astype(np.float32)
        above = t.astype(np.float64) > exact
        t[above] = np.nextafter(t[above], np.float32(-np.inf))
        t = np.ascontiguousarray(t)
        if t.tobytes() not in self._times:
            self._times[t.tobytes()] = self.accessor(t, minmax=True)
        anim = self._animations.get(animation)
        if anim is None:
            anim = self._animations[animation] = G.Animation(name=animation, samplers=[], channels=[])
            self.gltf.animations.append(anim)
        conv = {"translation": gltf_points, "rotation": _rotation, "scale": _scale}.get(path)
        out = np.asarray(values if conv is None else conv(values), np.float32)
        out = out.ravel() if path == "weights" else out
        anim.samplers.append(G.AnimationSampler(input=self._times[t.tobytes()], output=self.accessor(out),
                                                interpolation=interpolation))
        anim.channels.append(G.AnimationChannel(sampler=len(anim.samplers) - 1,
                                                target=G.AnimationChannelTarget(node=node, path=path)))

    # ------------------------------------------------------------ file
    def glb(self, extras: dict | None = None) -> bytes:
        """The binary glTF file. A primitive left without a material gets a plain one (white, metallic 0, roughness
        1): glTF's default material is fully metallic, which a viewer without an environment map (three.js with
        its lights alone) draws black; white keeps vertex colours as they are."""
        bare = [p for m in self.gltf.meshes for p in m.primitives if p.material is None]
        if bare:
            G = self._G
            pbr = G.PbrMetallicRoughness(baseColorFactor=[1.0, 1.0, 1.0, 1.0], metallicFactor=0.0, roughnessFactor=1.0)
            self.gltf.materials.append(G.Material(name="plain", pbrMetallicRoughness=pbr))
            for p in bare:
                p.material = len(self.gltf.materials) - 1
        self.gltf.buffers = [self._G.Buffer(byteLength=len(self._blob))]
        self.gltf.set_binary_blob(bytes(self._blob))
        if extras is not None:
            self.gltf.extras = extras
        out = self.gltf.save_to_bytes()
        return b"".join(out) if isinstance(out, list) else bytes(out)


def read_accessor(gltf, blob: bytes, index: int) -> np.ndarray:
    """The array an accessor of a loaded glTF (pygltflib) holds: (count,) or (count, width)."""
    acc = gltf.accessors[index]
    view = gltf.bufferViews[acc.bufferView]
    dtype = next(d for d, c in _COMPONENTS.items() if c == acc.componentType)
    width = _WIDTH[acc.type]
    arr = np.frombuffer(blob, dtype, acc.count * width, (view.byteOffset or 0) + (acc.byteOffset or 0))
    return arr.reshape(acc.count, width) if width > 1 else arr
