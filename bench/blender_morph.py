"""Blender plays a rig's GLB as the file means it: its glTF importer (skin + morph targets as shape keys, the
morph weights animation), the evaluated mesh at every ``--step``-th frame against the same frame skinned by our
reader (formats.read_gltf: morph targets, then joints), as the distance from each of Blender's vertices to the
nearest of ours (the importer may reorder vertices), median and max in mm; the shape keys' slider ranges.
Blender as a Python module (PyPI `bpy` 4.5, Python 3.11; a benchmark's peer, not the suite's):

    python3 -m venv /tmp/bpyenv && /tmp/bpyenv/bin/pip install "bpy==4.5.*" scipy pygltflib
    /tmp/bpyenv/bin/python bench/blender_morph.py out/child_rope_humanoid/child_rope_character_0.glb [--step 10]

Why: Blender 4.5's importer clamps a shape key's value to [slider_min, slider_max] and widens that range from the
first key of the weights animation only, so negative weights later in a clip came out clamped (skeleton.export's
corrective weights are now all in [0, 1]).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main():
    import bpy
    from scipy.spatial import cKDTree

    from nodes.skeleton import formats

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("glb", nargs="+", type=Path)
    ap.add_argument("--step", type=int, default=10)
    ap.add_argument("--fps", type=float, default=25.0, help="the rig's fps (skeleton.export's)")
    a = ap.parse_args()
    print(f"Blender {bpy.app.version_string}")
    for path in a.glb:
        ours = formats.read_gltf(path.read_bytes())["skinned"]
        bpy.ops.wm.read_factory_settings(use_empty=True)
        bpy.context.scene.render.fps = int(round(a.fps))
        bpy.ops.import_scene.gltf(filepath=str(path))
        mesh = max((o for o in bpy.data.objects if o.type == "MESH"), key=lambda o: len(o.data.vertices))
        keys = mesh.data.shape_keys
        blocks = list(keys.key_blocks)[1:] if keys else []
        lo = min((k.slider_min for k in blocks), default=0.0)
        hi = max((k.slider_max for k in blocks), default=1.0)
        worst = []
        for f in range(0, len(ours) - 1, a.step):       # the last key holds the last frame (not a frame of its own)
            bpy.context.scene.frame_set(f)
            ob = mesh.evaluated_get(bpy.context.evaluated_depsgraph_get())
            m = ob.to_mesh()
            v = np.array([ob.matrix_world @ p.co for p in m.vertices])
            ob.to_mesh_clear()
            d = cKDTree(ours[f]).query(v)[0]
            worst.append((1000 * float(np.median(d)), 1000 * float(d.max()), f))
        med = np.array([w[0] for w in worst])
        top = max(worst)
        print(f"{path.name}: {len(blocks)} shape keys (sliders {lo:.3g}..{hi:.3g}), {len(worst)} frames: Blender vs our "
              f"reader, nearest-vertex median {np.median(med):.3f} mm (worst frame {top[2]}: median {top[0]:.3f}, "
              f"max {top[1]:.3f} mm)")


if __name__ == "__main__":
    main()
