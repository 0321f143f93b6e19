"""Blender opens the deliverables as a user's import does: glTF (its importer, +Y up converted to Blender's +Z)
and USD (upAxis and metersPerUnit honoured), each object's evaluated mesh (shape keys and skins applied) at the
first frame, in Blender's world (+Z up, metres). Prints per file the bounds, the height and the lowest point,
and for each GLB/USD pair of one asset how far apart their bounds are. A .bvh (the character's motion) is
imported with Blender's BVH importer, once with its defaults (forward -Z, up Y) and once with forward +Z, and
every bone's head is compared, every frame, with the joints by our own forward kinematics (read_bvh). A rig's
rest (edit-mode) pose: for the humanoid template, the arms' angle from horizontal and the legs' from vertical. Blender as a Python module (PyPI `bpy`
4.5, Python 3.11; ~1 GB: a benchmark's peer, not the suite's):

    python3 -m venv /tmp/bpyenv && /tmp/bpyenv/bin/pip install "bpy==4.5.*" pyopencl pyyaml networkx   # (+ the device line)
    /tmp/bpyenv/bin/python bench/blender_import.py out/demo/demo_volumetric_0000.glb out/demo/demo_volumetric.usdc \
        out/demo/demo_dynamic.glb out/demo/demo_dynamic.usdc out/demo/demo_character.glb out/demo/demo_character.usd \
        out/demo/demo_character.bvh
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))   # the project, for the OpenCL device line


def bounds(path: Path) -> tuple[list, list, int]:
    """(min, max) over the evaluated meshes of the file imported into an empty scene, and the mesh count."""
    import bpy
    import numpy as np

    bpy.ops.wm.read_factory_settings(use_empty=True)
    if path.suffix.lower() in (".glb", ".gltf"):
        bpy.ops.import_scene.gltf(filepath=str(path))
    else:
        bpy.ops.wm.usd_import(filepath=str(path))
    scene = bpy.context.scene
    # the first key: glTF's time 0 (the importer keeps the scene at 24 fps and frame range 1..250; USD's range is
    # the stage's time codes): the same capture frame in both
    starts = [a.frame_range[0] for a in bpy.data.actions]
    scene.frame_set(int(round(min(starts))) if starts else scene.frame_start)
    deps = bpy.context.evaluated_depsgraph_get()
    pts = []
    for ob in scene.objects:
        if ob.type != "MESH" or any(c.name == "glTF_not_exported" for c in ob.users_collection):
            continue                                      # (the importer's bone-shape helper)
        ev = ob.evaluated_get(deps)
        m = np.array(ev.matrix_world)
        if ev.hide_render or abs(np.linalg.det(m[:3, :3])) < 1e-12:     # hidden (USD visibility, glTF scale 0)
            continue
        me = ev.to_mesh()
        co = np.empty(len(me.vertices) * 3)
        me.vertices.foreach_get("co", co)
        co = co.reshape(-1, 3) @ m[:3, :3].T + m[:3, 3]
        pts.append(co)
        ev.to_mesh_clear()
    allp = np.concatenate(pts) if pts else np.zeros((1, 3))
    return allp.min(0).tolist(), allp.max(0).tolist(), len(pts)


def bvh_check(path: Path) -> None:
    """The BVH through Blender's importer against read_bvh's joints (our world: +Z up, metres), every frame."""
    import bpy
    import numpy as np

    from nodes.skeleton.formats import read_bvh

    ours = read_bvh(path.read_text())
    names, ref = ours["names"], ours["positions"]                       # (F, J, 3)
    for forward, turn in (("-Z", np.eye(3)), ("Z", np.diag([-1.0, -1.0, 1.0]))):
        bpy.ops.wm.read_factory_settings(use_empty=True)
        bpy.ops.import_anim.bvh(filepath=str(path), axis_forward=forward, axis_up="Y", global_scale=1.0,
                                use_fps_scale=False, frame_start=1, rotate_mode="NATIVE")
        arm = next(o for o in bpy.context.scene.objects if o.type == "ARMATURE")
        missing = [n for n in names if n not in arm.pose.bones]
        worst = 0.0
        for f in range(len(ref)):
            bpy.context.scene.frame_set(1 + f)
            m = np.array(arm.matrix_world)
            got = np.array([(m @ np.append(np.array(arm.pose.bones[n].head), 1.0))[:3] for n in names if n not in missing])
            want = ref[f][[i for i, n in enumerate(names) if n not in missing]] @ turn.T
            worst = max(worst, float(np.abs(got - want).max()))
        lo = float(np.min(ref[:, :, 2]))
        print(f"{path.name} (Blender BVH import, forward {forward}, up Y): {len(arm.pose.bones)} bones, "
              f"{len(missing)} of our {len(names)} joints missing; {len(ref)} frames; max |Blender head - ours"
              f"{' turned 180 deg about Z' if forward == 'Z' else ''}| = {1000 * worst:.3f} mm; lowest joint z "
              f"{lo:.3f} m")


def rest_pose(path: Path) -> None:
    """A rig's rest (edit-mode) pose as Blender builds it from the file: for a humanoid template rig, how far the
    arms are from horizontal and the legs from vertical (a T pose: 0 and 0)."""
    import bpy
    import numpy as np

    bpy.ops.wm.read_factory_settings(use_empty=True)
    if path.suffix.lower() in (".glb", ".gltf"):
        bpy.ops.import_scene.gltf(filepath=str(path))
    else:
        bpy.ops.wm.usd_import(filepath=str(path))
    arms = [o for o in bpy.data.objects if o.type == "ARMATURE"]
    if not arms:
        return
    head = {b.name: np.array(arms[0].matrix_world @ b.head_local) for b in arms[0].data.bones}
    if not {"shoulder_l", "wrist_l", "hip_r", "ankle_r"} <= set(head):
        return
    def tilt(a, b, vertical):   # degrees from vertical (legs) or horizontal (arms)
        d = head[b] - head[a]
        return float(np.degrees(np.arccos(abs(d[2]) / np.linalg.norm(d)) if vertical else np.arcsin(abs(d[2]) / np.linalg.norm(d))))
    arm = max(tilt(f"shoulder_{s}", f"wrist_{s}", False) for s in "lr")
    leg = max(tilt(f"hip_{s}", f"ankle_{s}", True) for s in "lr")
    print(f"{path.name}: rest pose in Blender: arms {arm:.2f} deg from horizontal, legs {leg:.2f} deg from vertical, "
          f"{len(head)} bones")


def main():
    from machine import describe

    print(describe())
    import bpy

    print(f"Blender {bpy.app.version_string} (bpy)")
    found = {}
    print(f"{'file':40s} {'meshes':>6s} {'min (x, y, z) m':>28s} {'max (x, y, z) m':>28s} {'height':>7s} {'lowest':>7s}")
    for arg in sys.argv[1:]:
        p = Path(arg)
        if p.suffix.lower() == ".bvh":
            bvh_check(p)
            continue
        rest_pose(p)
        lo, hi, n = bounds(p)
        found[p] = (lo, hi)
        fmt = lambda v: "(" + ", ".join(f"{x:7.3f}" for x in v) + ")"  # noqa: E731
        print(f"{p.name:40s} {n:6d} {fmt(lo):>28s} {fmt(hi):>28s} {hi[2] - lo[2]:7.3f} {lo[2]:7.3f}")
    stems = {}
    for p in found:
        stems.setdefault(p.stem.rsplit("_0000", 1)[0], []).append(p)
    for stem, ps in stems.items():
        if len(ps) == 2:
            (a, b) = ps
            d = max(max(abs(x - y) for x, y in zip(found[a][0], found[b][0])),
                    max(abs(x - y) for x, y in zip(found[a][1], found[b][1])))
            print(f"{a.name} vs {b.name}: bounds {1000 * d:.2f} mm apart")


if __name__ == "__main__":
    main()
