"""Cache purity: "same key = same result" across units. A frame's items run together and hand values over in
memory; the value a node computes there must equal what it computes alone from its cached inputs, or the
cache returns one thing under a key and a rerun another (refine once hung its last search on the mesh object
and relax read it: all 8066 vertices of a 64^3 figure differed by up to 0.23 voxel under one key)."""
from __future__ import annotations

import textwrap

import trimesh

import enginenodes  # noqa: F401  (registers the t.* nodes)
from nodegraph.graphfile import load_graph
from nodegraph.testing import unit_purity
from pathlib import Path

GRAPHS = Path(__file__).resolve().parents[2] / "graphs"


def test_purity_check_catches_a_value_handed_over_in_memory(tmp_path):
    (tmp_path / "g.yaml").write_text(textwrap.dedent("""
        frames: 0:2
        nodes:
          src:  {type: t.source, params: {value: 1.0}}
          tag:  {type: t.handsover, in: {x: src.out}}
          use:  {type: t.useshint, in: {x: tag.out}}
          fine: {type: t.scale, in: {x: tag.out}}
    """))
    problems = unit_purity(load_graph(tmp_path / "g.yaml"), tmp_path / "w")
    assert problems == [f"use@{f} (t.useshint) output 'out': differs when the node runs alone from its cached inputs"
                        for f in (0, 1)]


def test_demo_graph_is_pure(tmp_path):
    """Every node type of the demo graph that shares a frame unit (synth, the keys, hull, mc, refine, relax,
    exports, evals, skeletonize, track.frame, texture, carve) computes the same alone as in its unit."""
    graph = load_graph(GRAPHS / "demo.yaml", ["stage.width=320", "stage.height=240", "hull.resolution=64",
                                              "texture.size=256"], "0:2")
    assert unit_purity(graph, tmp_path) == []


def test_other_frame_node_types_are_pure(tmp_path):
    """The per-frame node types the demo does not use: plate difference key, grey threshold, GrabCut, consensus,
    automatic bounds, voxel colouring, volume export, crop, a mesh read from a file."""
    trimesh.creation.icosphere(2, radius=0.4).export(tmp_path / "ref.ply")
    (tmp_path / "g.yaml").write_text(textwrap.dedent(f"""
        frames: 0:2
        nodes:
          stage:  {{type: synth, params: {{scene: figure, rig: dome, cameras: 8, width: 200, height: 150, background: plate}}}}
          diff:   {{type: key.difference, in: {{images: stage.images, background: stage.background}}}}
          grey:   {{type: key.threshold, in: {{images: stage.images}}, params: {{threshold: 0.3}}}}
          cut:    {{type: key.grabcut, in: {{masks: diff.masks, images: stage.images}}}}
          bounds: {{type: bounds, in: {{masks: cut.masks, cameras: stage.cameras}}}}
          hull:   {{type: hull, in: {{masks: cut.masks, cameras: stage.cameras, bounds: bounds.bounds}}, params: {{resolution: 40}}}}
          agree:  {{type: key.consensus, in: {{masks: cut.masks, cameras: stage.cameras, volume: hull.volume}}}}
          crop:   {{type: track.crop, in: {{masks: agree.masks, cameras: stage.cameras}}}}
          colour: {{type: carve.voxel_coloring, in: {{volume: hull.volume, images: stage.images, masks: agree.masks, cameras: stage.cameras}}}}
          vol:    {{type: export.volume, in: {{volume: colour.volume}}, params: {{path: "v_{{frame:04d}}.npz"}}}}
          mesh:   {{type: mc, in: {{volume: hull.volume}}}}
          ref:    {{type: load.mesh, params: {{path: "{tmp_path / 'ref.ply'}"}}}}
          dist:   {{type: eval.surface, in: {{mesh: mesh.mesh, reference: ref.mesh}}}}
          sil:    {{type: eval.silhouette, in: {{mesh: mesh.mesh, masks: crop.masks, cameras: crop.cameras}}}}
          greys:  {{type: eval.silhouette, in: {{mesh: mesh.mesh, masks: grey.masks, cameras: stage.cameras}}}}
    """))
    assert unit_purity(load_graph(tmp_path / "g.yaml"), tmp_path / "w") == []
