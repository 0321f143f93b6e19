"""texture.transfer: a mesh's atlas painted from another textured mesh of the same surface (a stream's lower
rung from its full rung)."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from nodegraph import NodeError
from nodegraph.testing import run_node
from nodes.texture.bake import fill_texture
from nodes.texture.reuse import BakeLayout, reference_atlas
from nodes.texture.texturing import textured_trimesh
from nodes.texture.transfer import welded


def colour(p: np.ndarray) -> np.ndarray:
    """A smooth pattern on the unit sphere, 0..255 (a few texels per period at 512²)."""
    return np.clip(128 + 100 * np.stack([np.sin(3 * p[:, 0]), np.cos(2 * p[:, 1] + p[:, 2]), np.sin(4 * p[:, 2])], 1), 0, 255)


def painted(mesh: trimesh.Trimesh, size: int) -> trimesh.Trimesh:
    """``mesh`` with an atlas whose every texel shows ``colour`` at its surface point pushed onto the sphere."""
    atlas = reference_atlas(mesh.vertices, mesh.faces, size, 6)
    layout = BakeLayout.of(atlas, 2)
    p = np.einsum("nc,ncd->nd", layout.bary, np.asarray(mesh.vertices)[np.asarray(mesh.faces)[layout.face]])
    return textured_trimesh(mesh.vertices, mesh.faces, atlas, fill_texture(colour(p / np.linalg.norm(p, axis=1, keepdims=True)), layout))


def texel_colours(mesh: trimesh.Trimesh, textured: trimesh.Trimesh, size: int):
    """(colour the texture of ``textured`` holds, colour of the pattern) at every inner texel of the atlas charted on
    ``mesh`` (``textured`` is that mesh with the atlas, its vertices split at chart seams)."""
    atlas = reference_atlas(mesh.vertices, mesh.faces, size, 6)
    layout = BakeLayout.of(atlas, 2)
    tex = np.asarray(textured.visual.material.baseColorTexture.convert("RGB")).reshape(-1, 3)
    p = np.einsum("nc,ncd->nd", layout.bary, np.asarray(mesh.vertices)[np.asarray(mesh.faces)[layout.face]])
    inner = layout.inner
    return tex[layout.texel[inner]].astype(np.float64), colour(p[inner] / np.linalg.norm(p[inner], axis=1, keepdims=True))


def test_transfer_reproduces_the_source_pattern_on_a_coarser_mesh():
    full = trimesh.creation.icosphere(5)                  # 20k faces
    low = trimesh.creation.icosphere(3)                   # 1280 faces: chords up to ~1 % inside the sphere
    source = painted(full, 1024)
    out = run_node("texture.transfer", {"mesh": low, "source": source}, {"size": 512}, roundtrip=True)
    got, want = texel_colours(low, out["mesh"], 512)
    err = np.abs(got - want).mean()
    assert err < 0.6, err                                  # levels (0..255): 0.3 here, the source's own 0.25
    # the same texels painted with the pattern of a sphere turned by 10 degrees: what a wrong lookup gives
    turn = trimesh.transformations.rotation_matrix(np.radians(10), [0, 0, 1])[:3, :3]
    atlas = reference_atlas(low.vertices, low.faces, 512, 6)
    layout = BakeLayout.of(atlas, 2)
    p = np.einsum("nc,ncd->nd", layout.bary, low.vertices[low.faces[layout.face]])[layout.inner] @ turn.T
    assert np.abs(colour(p / np.linalg.norm(p, axis=1, keepdims=True)) - want).mean() > 8 * err
    assert np.array_equal(out["atlas"].face_uv, atlas.face_uv), "the atlas charted on the mesh itself (no reference)"


def test_transfer_uses_the_reference_layout_and_checks_its_inputs():
    full, low = trimesh.creation.icosphere(4), trimesh.creation.icosphere(2)
    source = painted(full, 512)
    moved = trimesh.Trimesh(low.vertices * 1.001, low.faces, process=False)
    out = run_node("texture.transfer", {"mesh": moved, "reference": low, "source": source}, {"size": 256})
    assert np.array_equal(out["atlas"].face_uv, reference_atlas(low.vertices, low.faces, 256, 6).face_uv)
    with pytest.raises(NodeError, match="input 'source': the source mesh has no texture"):  # vertex colours or none
        run_node("texture.transfer", {"mesh": low, "source": full}, {"size": 256})
    with pytest.raises(NodeError, match="other faces"):
        run_node("texture.transfer", {"mesh": low, "reference": full, "source": source}, {"size": 256})


def test_transfer_refuses_a_mesh_with_vertices_that_are_not_finite():
    """A NaN vertex (track.simplify's replay made two on the demo's stage at 6 cameras) made the closest-point
    kernels index outside their buffers: the worker died of a segmentation fault. Now one clear NodeError."""
    full, low = trimesh.creation.icosphere(4), trimesh.creation.icosphere(2)
    source = painted(full, 256)
    bad = np.array(low.vertices)
    bad[7] = np.nan
    with pytest.raises(NodeError, match="input 'mesh': 1 of its .* vertices are not finite"):
        run_node("texture.transfer", {"mesh": trimesh.Trimesh(bad, low.faces, process=False), "source": source},
                 {"size": 256})


def test_welded_merges_the_vertices_a_texture_splits_at_chart_seams():
    sphere = trimesh.creation.icosphere(3)
    source = painted(sphere, 256)
    assert len(source.vertices) > len(sphere.vertices)     # split at the seams
    v, f = welded(source.vertices, source.faces)
    assert len(v) == len(sphere.vertices)
    np.testing.assert_array_equal(v[f], np.asarray(source.vertices)[np.asarray(source.faces)])


@pytest.mark.slow
@pytest.mark.realdata
def test_real_thu_wd_human_quarter_rung_looks_like_the_full_one(dataset_run):
    """graphs/datasets/thu_wd_human_rungs.yaml: the full rung painted from the 20 photos, the quarter rung (a quarter of
    the faces) by texture.transfer from it; rendered into the cameras, the quarter is as close to the photos as the full
    rung (measured: median 22.77 vs 22.80 dB) and close to the full rung's own render (39-40 dB)."""
    from nodes.common.raster import render_texture

    res = dataset_run("thu_wd_human_rungs")
    out = dataset_run.output
    full, low = out(res, "texture", "mesh"), out(res, "texture_low", "mesh")
    images, cams, masks = out(res, "despill", "images"), out(res, "capture", "cameras"), out(res, "capture", "masks")
    assert 0.2 < len(low.faces) / len(full.faces) < 0.3

    def draw(m, v):
        tex = np.asarray(m.visual.material.baseColorTexture.convert("RGB"))
        return render_texture(np.asarray(m.vertices), np.asarray(m.faces), np.asarray(m.visual.uv)[np.asarray(m.faces)], tex, cams, v)

    def psnr(a, b, sel):
        d = a[sel].astype(np.float64) - b[sel].astype(np.float64)
        return 10 * np.log10(255.0 ** 2 / np.mean(d * d))

    gap, vs_full = [], []
    for v in range(0, len(cams), 5):
        (a, ha), (b, hb) = draw(full, v), draw(low, v)
        sel = masks.masks[v] > 127
        gap.append(psnr(b, images.images[v], hb & sel) - psnr(a, images.images[v], ha & sel))
        vs_full.append(psnr(b, a, ha & hb & sel))
    assert min(gap) > -0.3, gap                     # dB: the quarter rung loses nothing visible against the photos
    assert min(vs_full) > 35, vs_full              # measured 39.3-40.3 dB
