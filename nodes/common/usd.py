"""USD through usd-core (pxr): one stage writer every export composes, and one reader of USD bytes.

``UsdStage`` holds an in-memory stage; its constructor is the one place where the stage metadata is written
(``upAxis``, ``metersPerUnit``, ``timeCodesPerSecond`` / ``framesPerSecond`` and the frame range: time codes
are frame numbers). Prims are added step by step, so one stage can carry tracked, textured and skinned data:

    group        an Xform (or a SkelRoot) under the root; the first top-level one is the default prim
    mesh         a UsdGeom.Mesh: faces once; points (+ extent) static or, through ``points_at``, time-sampled;
                 optional normals, ``primvars:st`` (UVs) and ``displayColor``, all vertex-interpolated
    visibility   time-sampled visibility (a segment shown only during its frames)
    material     a UsdPreviewSurface, its diffuseColor read from a texture file (UsdUVTexture through the ``st``
                 primvar) or from ``displayColor``, bound to the mesh (the primvar readers' ``varname`` is a
                 string, as their Sdr definition says since USD 23.11)
    skeleton     UsdSkel: Skeleton (bind / rest transforms), its Animation (time-sampled translations and
                 rotations), and a mesh bound to it with joint indices and weights; ``extent_at`` gives the
                 SkelRoot the bounds of the skinned points per frame (the mesh's own extent is its rest points');
                 ``blend_shapes``: BlendShape prims on the mesh, their weights per frame on the Animation
    save         .usda, .usdc / .usd (crate) or .usdz (the layer packed with its assets), as bytes

``validation_errors`` runs usd-core's validators (the ``UsdValidation`` framework, which replaced
``UsdUtils.ComplianceChecker``) on written files, as a pipeline's checker would.

For example::

    s = UsdStage(up_axis="Z", fps=25, frames=(0, 99))
    s.group("/Capture")
    m = s.mesh("/Capture/Body", faces, uv=uv)
    for f, p in zip(frames, points): s.points_at(m, p, f)
    s.material(m, "/Capture/Material", texture="body.png")
    data = s.save("body.usdz", {"body.png": png})

Matrices are ours (column-vector, row-major arrays) and transposed here to USD's row-vector convention;
quaternions are (x, y, z, w) as SciPy writes them.
"""
from __future__ import annotations

import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np

UP_AXIS = "Z"               # the capture's world frame as every export labels it (textured, track, skeleton)
METERS_PER_UNIT = 1.0


class UsdStage:
    """An in-memory USD stage being written (see the module docstring).

    Parameters
    ----------
    up_axis : "Y", "Z", or None to leave ``upAxis`` unauthored (readers then assume Y).
    meters_per_unit : scene units.
    fps : time codes (frames) per second; None for a stage without time samples.
    frames : (first, last) frame, the stage's time code range.
    """

    def __init__(self, up_axis: str | None = UP_AXIS, meters_per_unit: float = METERS_PER_UNIT,
                 fps: float | None = None, frames: tuple[int, int] | None = None):
        from pxr import Usd, UsdGeom

        self.stage = Usd.Stage.CreateInMemory()
        if up_axis is not None:
            UsdGeom.SetStageUpAxis(self.stage, getattr(UsdGeom.Tokens, up_axis.lower()))
        UsdGeom.SetStageMetersPerUnit(self.stage, meters_per_unit)
        if fps is not None:
            self.stage.SetTimeCodesPerSecond(fps)
            self.stage.SetFramesPerSecond(fps)
        if frames is not None:
            self.stage.SetStartTimeCode(float(frames[0]))
            self.stage.SetEndTimeCode(float(frames[1]))

    # ------------------------------------------------------------ geometry
    def group(self, path: str, skel_root: bool = False):
        """An Xform (or a UsdSkel.Root) at ``path``; the first top-level group becomes the default prim."""
        from pxr import UsdGeom, UsdSkel

        prim = (UsdSkel.Root if skel_root else UsdGeom.Xform).Define(self.stage, path)
        if not self.stage.HasDefaultPrim() and prim.GetPath().GetParentPath().IsAbsoluteRootPath():
            self.stage.SetDefaultPrim(prim.GetPrim())
        return prim

    def mesh(self, path: str, faces, points=None, *, normals=None, uv=None, colours=None):
        """A triangle UsdGeom.Mesh (no subdivision, right-handed); its schema object.

        Parameters
        ----------
        faces : (F, 3) vertex indices.
        points : (V, 3) static points (with their extent), or None to give them per frame (``points_at``).
        normals : (V, 3) vertex normals.  uv : (V, 2) texture coordinates (``primvars:st``, trimesh's origin:
            bottom-left, as USD's).  colours : (V, 3) float 0..1 (``primvars:displayColor``).
        """
        from pxr import Sdf, UsdGeom, Vt

        faces = np.asarray(faces, np.int32)
        geom = UsdGeom.Mesh.Define(self.stage, path)
        geom.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
        geom.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(faces.ravel())))
        geom.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        geom.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        if points is not None:
            self.points_at(geom, points, None)
        if normals is not None:
            geom.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(normals, np.float32)))
            geom.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
        if uv is not None:
            st = UsdGeom.PrimvarsAPI(geom).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
            st.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(uv, np.float32)))
        if colours is not None:
            geom.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex).Set(
                Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(colours, np.float32)))
        return geom

    def points_at(self, geom, points, frame: float | None) -> None:
        """Set the mesh's points and extent at ``frame`` (a time sample), or statically when None."""
        from pxr import Usd, Vt

        p = np.ascontiguousarray(points, np.float32)
        t = Usd.TimeCode.Default() if frame is None else Usd.TimeCode(float(frame))
        geom.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(p), t)
        self.extent_at(geom, p, frame)

    def extent_at(self, boundable, points, frame: float | None) -> None:
        """Set the ``extent`` of a boundable prim (a mesh, a SkelRoot) to the bounds of ``points`` at ``frame``
        (a time sample), or statically when None."""
        from pxr import Usd, Vt

        p = np.asarray(points, np.float32)
        lo, hi = (p.min(axis=0), p.max(axis=0)) if len(p) else (np.zeros(3, np.float32), np.zeros(3, np.float32))
        t = Usd.TimeCode.Default() if frame is None else Usd.TimeCode(float(frame))
        boundable.CreateExtentAttr().Set(Vt.Vec3fArray.FromNumpy(np.array([lo, hi], np.float32)), t)

    def visibility(self, geom, keys: dict) -> None:
        """Time-sampled visibility: ``keys`` maps frame -> visible (held until the next key)."""
        from pxr import Usd, UsdGeom

        attr = geom.CreateVisibilityAttr()
        for frame, visible in keys.items():
            attr.Set(UsdGeom.Tokens.inherited if visible else UsdGeom.Tokens.invisible, Usd.TimeCode(float(frame)))

    # ------------------------------------------------------------ materials
    def material(self, geom, path: str, *, texture: str | None = None, display_colour: bool = False,
                 roughness: float = 1.0, metallic: float = 0.0):
        """A UsdPreviewSurface material at ``path``, bound to ``geom``. Its diffuseColor reads ``texture`` (a file
        path relative to the layer, or {frame: path} time samples: a texture per frame; the mesh needs ``uv``)
        or, with ``display_colour``, the displayColor primvar."""
        from pxr import Sdf, Usd, UsdShade

        mat = UsdShade.Material.Define(self.stage, path)
        surf = UsdShade.Shader.Define(self.stage, f"{path}/PreviewSurface")
        surf.CreateIdAttr("UsdPreviewSurface")
        surf.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(float(roughness))
        surf.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(float(metallic))
        mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
        diffuse = surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f) if texture or display_colour else None
        if texture is not None:
            reader = UsdShade.Shader.Define(self.stage, f"{path}/STReader")
            reader.CreateIdAttr("UsdPrimvarReader_float2")
            reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
            image = UsdShade.Shader.Define(self.stage, f"{path}/Texture")
            image.CreateIdAttr("UsdUVTexture")
            file = image.CreateInput("file", Sdf.ValueTypeNames.Asset)
            if isinstance(texture, dict):
                for frame, name in sorted(texture.items()):
                    file.Set(Sdf.AssetPath(name), Usd.TimeCode(float(frame)))
                file.Set(Sdf.AssetPath(texture[min(texture)]))      # the default: a reader without time sees one
            else:
                file.Set(texture)
            image.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("sRGB")
            image.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
            image.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
            diffuse.ConnectToSource(image.ConnectableAPI(), "rgb")
        elif display_colour:
            reader = UsdShade.Shader.Define(self.stage, f"{path}/ColorReader")
            reader.CreateIdAttr("UsdPrimvarReader_float3")
            reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("displayColor")
            reader.CreateOutput("result", Sdf.ValueTypeNames.Float3)
            diffuse.ConnectToSource(reader.ConnectableAPI(), "result")
        UsdShade.MaterialBindingAPI.Apply(geom.GetPrim()).Bind(mat)
        return mat

    # ------------------------------------------------------------ UsdSkel
    def skeleton(self, path: str, joint_paths: list[str], names: list[str], bind, rest):
        """A UsdSkel.Skeleton: joints (paths ``a/b/c``), names, (J, 4, 4) world bind and parent-relative rest
        transforms (ours); its schema object."""
        from pxr import UsdSkel, Vt

        skel = UsdSkel.Skeleton.Define(self.stage, path)
        skel.CreateJointsAttr(Vt.TokenArray(joint_paths))
        skel.CreateJointNamesAttr(Vt.TokenArray(names))
        skel.CreateBindTransformsAttr(_matrices(bind))
        skel.CreateRestTransformsAttr(_matrices(rest))
        return skel

    def skeleton_animation(self, skel, path: str, frames, translations, rotations):
        """A UsdSkel.Animation at ``path``, the animation source of ``skel``: per frame the joints' local
        (F, J, 3) translations and (F, J, 4) rotations (x, y, z, w); scales 1."""
        from pxr import Gf, Usd, UsdSkel, Vt

        anim = UsdSkel.Animation.Define(self.stage, path)
        anim.CreateJointsAttr(skel.GetJointsAttr().Get())
        t_attr, r_attr, s_attr = anim.CreateTranslationsAttr(), anim.CreateRotationsAttr(), anim.CreateScalesAttr()
        s_attr.Set(Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)] * len(skel.GetJointsAttr().Get())))
        for k, fr in enumerate(frames):
            code = Usd.TimeCode(float(fr))
            t_attr.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(translations[k], np.float32)), code)
            r_attr.Set(Vt.QuatfArray([Gf.Quatf(float(q[3]), float(q[0]), float(q[1]), float(q[2]))
                                      for q in rotations[k]]), code)
        UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])
        return anim

    def bind_skin(self, geom, skel, indices, weights) -> None:
        """Bind ``geom`` to ``skel``: (V, k) joint indices and weights per vertex (constant geomBindTransform)."""
        from pxr import Gf, UsdSkel, Vt

        indices, weights = np.asarray(indices), np.asarray(weights)
        binding = UsdSkel.BindingAPI.Apply(geom.GetPrim())
        binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
        k = indices.shape[1]
        binding.CreateJointIndicesPrimvar(False, k).Set(Vt.IntArray.FromNumpy(indices.astype(np.int32).ravel()))
        binding.CreateJointWeightsPrimvar(False, k).Set(Vt.FloatArray.FromNumpy(weights.astype(np.float32).ravel()))
        binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))

    def blend_shapes(self, geom, anim, names: list[str], offsets, frames, weights) -> None:
        """UsdSkel BlendShape prims ``names`` under ``geom`` (each (V, 3) rest-space point ``offsets``, on every
        point), bound to it (``skel:blendShapes`` / ``skel:blendShapeTargets``), and their (F, K) ``weights``
        per frame on the Animation ``anim`` (``blendShapes`` / ``blendShapeWeights`` time samples)."""
        from pxr import Usd, UsdSkel, Vt

        targets = []
        for name, off in zip(names, offsets):
            shape = UsdSkel.BlendShape.Define(self.stage, geom.GetPath().AppendChild(name))
            shape.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(off, np.float32)))
            targets.append(shape.GetPath())
        binding = UsdSkel.BindingAPI(geom.GetPrim())
        binding.CreateBlendShapesAttr(Vt.TokenArray(names))
        binding.CreateBlendShapeTargetsRel().SetTargets(targets)
        anim.CreateBlendShapesAttr(Vt.TokenArray(names))
        attr = anim.CreateBlendShapeWeightsAttr()
        for k, fr in enumerate(frames):
            attr.Set(Vt.FloatArray.FromNumpy(np.ascontiguousarray(weights[k], np.float32)), Usd.TimeCode(float(fr)))

    # ------------------------------------------------------------ file
    def save(self, filename: str, assets: dict[str, bytes] | None = None) -> bytes:
        """The stage as the bytes of ``filename`` (its suffix: .usda text, .usdc / .usd crate, .usdz a package
        of the crate layer and ``assets``, name -> bytes, which the layer refers to by those relative names)."""
        from pxr import Sdf, UsdUtils

        name = Path(filename).name
        with tempfile.TemporaryDirectory() as d:
            d = Path(d)
            for asset, data in (assets or {}).items():
                (d / asset).write_bytes(data)
            layer = d / (Path(name).stem + ".usdc" if name.endswith(".usdz") else name)
            if not self.stage.GetRootLayer().Export(str(layer)):
                raise OSError(f"{filename}: USD could not write the layer")
            if not name.endswith(".usdz"):
                return layer.read_bytes()
            package = d / name
            if not UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(layer)), str(package)):
                raise OSError(f"{filename}: USD could not write the usdz package")
            return package.read_bytes()


def _matrices(mats):
    """A Vt.Matrix4dArray of (N, 4, 4) column-vector matrices (USD's are row-vector: transposed)."""
    from pxr import Gf, Vt

    return Vt.Matrix4dArray([Gf.Matrix4d(*np.asarray(m, np.float64).T.ravel().tolist()) for m in mats])


def validation_errors(files: dict[str, bytes], name: str) -> list[str]:
    """Every error usd-core's registered validators (all of them: core, geometry, shading, skeleton, usdz
    package rules) report on the layer ``name`` of ``files`` (file name -> bytes, as published together: a
    .usda and the texture beside it), as "validator error: message" lines; [] when it passes."""
    from pxr import Usd, UsdValidation

    context = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
    with tempfile.TemporaryDirectory() as d:
        for rel, data in files.items():
            (Path(d) / rel).parent.mkdir(parents=True, exist_ok=True)
            (Path(d) / rel).write_bytes(data)
        stage = Usd.Stage.Open(str(Path(d) / name))
        return [f"{e.GetName()}: {e.GetMessage()}" for e in context.Validate(stage) if not e.HasNoError()]


@contextmanager
def opened(data: bytes, suffix: str = ".usdc"):
    """The USD stage of file bytes ``data`` (a temporary file of that suffix while the stage is open)."""
    from pxr import Usd

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / f"read{suffix}"
        path.write_bytes(data)
        yield Usd.Stage.Open(str(path))
