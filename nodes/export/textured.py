"""Export of textured meshes: glTF binary with the texture embedded, OBJ + MTL + PNG, USD with a
UsdPreviewSurface texture (usda, usdc, usdz), PLY with vertex colours; optionally a linear-light EXR of the
texture."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from nodegraph import Files, Node, NodeError, OutPath, Param
from nodes.common.gltf import mesh_glb, png_bytes, texture_image
from nodes.common.types import TexturedMesh

from .nodes import _format

TEXTURED_FORMATS = ("glb", "obj", "usda", "usdc", "usdz", "ply")


class ExportTextured(Node):
    """Write a textured mesh per frame for a production chain, chosen by the file suffix: .glb (binary glTF,
    texture embedded), .obj (+ .mtl + .png beside it), .usda / .usdc (UsdPreviewSurface reading a .png
    beside it) or .usdz (one package), .ply (vertex colours sampled from the texture)."""

    type_name = "export.textured"
    uses_frame = True
    publishes = True
    inputs = {"mesh": TexturedMesh}
    outputs = {"files": Files}
    params = {"path": Param(OutPath, "textured_{frame:04d}.glb", doc="output file pattern, relative to --out"),
              "linear_exr": Param(bool, False, doc="also write the texture as linear-light float EXR (NAME_linear.exr)")}

    def run(self, mesh, *, path, linear_exr, frame):
        rel = _format(path, frame=frame)
        ext = Path(rel).suffix.lstrip(".").lower()
        if ext not in TEXTURED_FORMATS:
            raise NodeError(f"path {path!r}: unknown textured-mesh format '.{ext}' (use one of {', '.join(TEXTURED_FORMATS)})")
        files = textured_files(mesh, rel, ext)
        tex = texture_image(mesh)
        if linear_exr and tex is not None:
            files[str(Path(rel).with_suffix("")) + "_linear.exr"] = linear_exr_bytes(tex)
        return {"files": files}


def linear_exr_bytes(tex: np.ndarray) -> bytes:
    """An sRGB 8-bit texture decoded to linear light, as a half-float RGB EXR file."""
    import tempfile

    import OpenEXR

    c = tex.astype(np.float32) / 255.0
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float16)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "t.exr"
        with OpenEXR.File(header, {"R": np.ascontiguousarray(lin[..., 0]), "G": np.ascontiguousarray(lin[..., 1]),
                                   "B": np.ascontiguousarray(lin[..., 2])}) as f:
            f.write(str(p))
        return p.read_bytes()


def vertex_colours(mesh) -> np.ndarray | None:
    """(V, 3) uint8 colours: the texture sampled at each vertex's UV, or the mesh's vertex colours."""
    from nodes.common.raster import sample_texture

    tex = texture_image(mesh)
    if tex is not None:
        return np.clip(sample_texture(tex, np.asarray(mesh.visual.uv)) + 0.5, 0, 255).astype(np.uint8)
    if getattr(mesh.visual, "kind", None) == "vertex":
        return np.asarray(mesh.visual.vertex_colors)[:, :3].astype(np.uint8)
    return None


def textured_files(mesh, rel: str, ext: str) -> dict[str, bytes]:
    """File name -> bytes for one textured mesh in format ``ext``."""
    import trimesh

    stem = Path(rel).with_suffix("")
    if ext == "glb":
        return {rel: mesh_glb(mesh, "volcap export.textured")}
    if ext == "ply":
        cols = vertex_colours(mesh)
        m = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
        if cols is not None:
            m.visual = trimesh.visual.ColorVisuals(m, vertex_colors=np.hstack([cols, np.full((len(cols), 1), 255, np.uint8)]))
        m.merge_vertices(merge_tex=True, merge_norm=True)       # the atlas split vertices at chart borders
        return {rel: m.export(file_type="ply")}
    tex = texture_image(mesh)
    if ext == "obj":
        from trimesh.exchange.obj import export_obj

        mtl = f"{stem.name}.mtl"
        text, extra = export_obj(mesh, include_texture=tex is not None, return_texture=True, mtl_name=mtl,
                                 include_normals=False)
        files = {rel: text.encode()}
        for name, data in extra.items():
            files[str(stem.parent / name)] = data
        return files
    return usd_files(mesh, tex, rel, ext)


def usd_files(mesh, tex, rel: str, ext: str) -> dict[str, bytes]:
    """A UsdGeom.Mesh with a UsdPreviewSurface material whose diffuseColor reads the texture (UsdUVTexture
    through the ``st`` primvar), or displayColor from vertex colours."""
    from nodes.common.usd import UsdStage

    stem = Path(rel).with_suffix("")
    png_name = f"{stem.name}.png"
    cols = vertex_colours(mesh) if tex is None else None
    stage = UsdStage()                      # upAxis Z, metres: the world frame (nodes/capture/world.py), as every export
    stage.group("/Capture")
    geom = stage.mesh("/Capture/Mesh", mesh.faces, mesh.vertices, uv=mesh.visual.uv if tex is not None else None,
                      colours=None if cols is None else cols / 255.0)
    stage.material(geom, "/Capture/Material", texture=png_name if tex is not None else None,
                   display_colour=cols is not None)
    assets = {png_name: png_bytes(tex)} if tex is not None else {}
    try:
        data = stage.save(f"{stem.name}.{ext}", assets)
    except OSError as exc:
        raise NodeError(f"{rel}: {exc}") from None
    if ext == "usdz":
        return {rel: data}
    return {rel: data, **{str(stem.parent / name): png for name, png in assets.items()}}
