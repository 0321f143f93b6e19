"""Speed and mesh health of refine + relax (issue 13), next to today's implementation before the issue (the seed's,
frozen in bench/legacy_surface.py) and the decimation baseline a user would otherwise pick, in the same run.

    python bench/refine_relax.py [--reps 7] [--no-legacy] [--datasets thu_wd_human,inria_dancer]

Scenes, 128^3 hull (nodes.hull) + marching cubes (largest component):
  synth figure   the synth node's walking figure, ring of 24 cameras at 1920x1080 (bench/e2e.py's rig), with the
                 true surface: normal error (eval.mesh, faces within one voxel of the truth)
  crease robot   a procedural mesh with sharp creases and thin parts (crease_robot), rendered by the project's
                 rasterizer into a dome of 24 cameras at 1920x1080; normal error against it
  real data      thu_wd_human (20 x 1024x768), inria_dancer (8 x 780x582), shipped masks
Rows per scene:
  mc 128 / mc 256        plain marching cubes (the grid's own surface)
  new refine+relax       this issue's nodes' work functions with their defaults; speed = median wall time per frame
                         over --reps repetitions on one frame, masks in memory as new arrays each repetition (so
                         they are put on the device again, as for a new frame), with the CPU time of the process
                         (both cores) beside it
  legacy refine+relax    the seed's (distance outline, 2 rounds of splits, Taubin + fit), one repetition
  legacy + QEM 1.5x      the seed's refined mesh decimated to 1.5x mc's faces by fast-simplification and pyfqmr
                         (the decimation baseline: QEM meets a face budget), then the seed's relax
Columns: ms (wall), faces / mc's, folded edges (adjacent normals > 150 deg), % triangles with min angle < 5 deg,
roughness (mean dihedral angle), normal error vs truth (synthetic), mean silhouette IoU.
Prints the OpenCL device, the CPU model and the load average before and after.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import trimesh

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from legacy_surface import legacy_refine, legacy_relax  # noqa: E402
from machine import cpu_model, cpu_seconds  # noqa: E402

from nodegraph import clrt  # noqa: E402
from nodegraph.testing import run_node  # noqa: E402
from nodes.common.meshops import largest_component  # noqa: E402
from nodes.common.types import MaskSet  # noqa: E402
from nodes.eval.health import mesh_health  # noqa: E402
from nodes.eval.silhouette import silhouette_report  # noqa: E402
from nodes.hull.hull import visual_hull  # noqa: E402
from nodes.mesh.hullfit import SilhouetteField  # noqa: E402
from nodes.mesh.mc import marching_cubes  # noqa: E402
from nodes.mesh.refine import refine_vertices  # noqa: E402
from nodes.mesh.relax import relax_vertices  # noqa: E402


def cube_around(bounds: np.ndarray) -> np.ndarray:
    centre, half = bounds.mean(0), (bounds[1] - bounds[0]).max() / 2
    return np.array([centre - half, centre + half])


def mc_mesh(masks, cams, box, resolution):
    vol = visual_hull(masks, cams, box, resolution)
    return vol, trimesh.Trimesh(*largest_component(*marching_cubes(vol)), process=False)


def refine_relax(mesh, vol, masks, cams):
    """The refine and relax nodes' work, with their defaults (what their run() does; in one frame unit relax
    starts from refine's last search, handed over in memory)."""
    origin = 0.5 * (vol.bbox_min + vol.bbox_max)
    field = SilhouetteField.from_inputs(masks, cams, origin)
    v, _, stats = refine_vertices(mesh.vertices, mesh.faces, vol, field)
    v, faces = relax_vertices(v, mesh.faces, field, lines=stats["lines"])
    return trimesh.Trimesh(v, faces, process=False)


def fresh(masks):
    """The same masks as new arrays, as the next frame brings them (nothing cached on the device applies)."""
    return MaskSet([m.copy() for m in masks.masks], None if masks.alpha is None else [a.copy() for a in masks.alpha],
                   list(masks.names))


def crease_robot():
    """A procedural mesh with sharp creases and thin parts (the "rendered third-party mesh" of the issue): a box
    torso and a box turned 30 degrees about two axes, a ball head, limbs of 3 to 6 voxels' diameter at 128^3, a
    fin 1.3 voxels thick and a torus handle, overlapping (one connected object; its silhouettes are the union's)."""
    from trimesh.creation import box, cylinder, icosphere, torus
    from trimesh.transformations import rotation_matrix

    def at(m, xyz, rot=None):
        if rot is not None:
            m.apply_transform(rot)
        m.apply_translation(xyz)
        return m

    parts = [at(box((0.6, 0.36, 0.8)), (0, 0, 1.0)),
             at(box((0.3, 0.3, 0.3)), (0.0, 0.0, 1.45), rotation_matrix(0.52, (1, 1, 0))),
             at(icosphere(3, radius=0.17), (0, 0, 1.72)),
             at(box((0.022, 0.3, 0.45)), (0.0, -0.32, 1.05)),                      # fin
             at(torus(0.22, 0.03), (0.0, 0.0, 0.55), rotation_matrix(np.pi / 2, (1, 0, 0)))]
    for side in (-1, 1):
        parts.append(at(cylinder(radius=0.035, height=0.7, sections=24), (side * 0.5, 0, 1.05),
                        rotation_matrix(side * 0.7, (0, 1, 0))))                    # arms (4 voxels)
        parts.append(at(cylinder(radius=0.055, height=0.62, sections=24), (side * 0.17, 0, 0.31)))  # legs
        parts.append(at(cylinder(radius=0.014, height=0.4, sections=16), (side * 0.1, 0.0, 1.95),
                        rotation_matrix(side * 0.4, (0, 1, 0))))                    # antennae (1.6 voxels)
    return trimesh.util.concatenate(parts)


def scene(name: str):
    if name == "crease robot":
        from nodes.common import raster
        from nodes.synth.render import ring_rig

        truth = crease_robot()
        lo, hi = truth.bounds
        centre, radius = 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))
        cams = ring_rig(24, centre, radius, 40.0, 1920, 1080, dome=True)
        masks = MaskSet(raster.silhouette(np.asarray(truth.vertices), np.asarray(truth.faces), cams), None, cams.names)
        return masks, cams, cube_around(np.array([lo - 0.05, hi + 0.05])), truth
    if name == "synth figure":
        st = run_node("synth", {}, {"scene": "figure", "rig": "ring", "cameras": 24, "width": 1920, "height": 1080,
                                    "background": "green", "shadow": False})
        return st["masks"], st["cameras"], cube_around(st["bounds"]), st["mesh"]
    from nodes.capture.load import load_capture
    from nodes.common.bounds import auto_bounds

    data = Path(os.environ.get("VOLCAP_DATA", ROOT.parent / "shared" / "data"))
    cap = load_capture(data / name)
    return cap["masks"], cap["cameras"], auto_bounds(cap["masks"].masks, cap["cameras"]), None


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=7, help="timed repetitions of the new refine + relax")
    ap.add_argument("--no-legacy", action="store_true", help="skip the seed's implementation (about 20 s a scene)")
    ap.add_argument("--datasets", default="thu_wd_human,inria_dancer", help="real data sets under $VOLCAP_DATA")
    args = ap.parse_args()
    import fast_simplification
    import pyfqmr

    print(f"OpenCL device: {clrt.device_name()}; CPU: {cpu_model()}, {os.cpu_count()} cores; "
          f"load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f}")
    names = ["synth figure", "crease robot"] + [n for n in args.datasets.split(",") if n]
    for name in names:
        masks, cams, box, truth = scene(name)
        vol, mesh = mc_mesh(masks, cams, box, 128)
        _, mesh256 = mc_mesh(masks, cams, box, 256)
        voxel = float(vol.voxel_size[0])
        rows = []

        def row(label, ms, m, cpu_ms=None):
            h = mesh_health(m, truth, voxel)
            r = silhouette_report(m.vertices, m.faces, cams, masks)
            rows.append((label, ms, cpu_ms, len(m.faces) / len(mesh.faces), h["folded_edges"],
                         100 * h["min_angle_below_5"], h["roughness_deg"], h.get("normal_error_mean_deg", float("nan")),
                         r["mean_iou"]))

        row("mc 128^3", float("nan"), mesh)
        row("mc 256^3", float("nan"), mesh256)
        refine_relax(mesh, vol, masks, cams)  # kernels built, buffers allocated
        walls, cpus, out = [], [], None
        for _ in range(args.reps):
            frame = fresh(masks)
            c0, t0 = cpu_seconds(), time.perf_counter()
            out = refine_relax(mesh, vol, frame, cams)
            walls.append(time.perf_counter() - t0)
            cpus.append(cpu_seconds() - c0)
        row("new refine+relax", 1e3 * float(np.median(walls)), out, 1e3 * float(np.median(cpus)))
        if not args.no_legacy:
            c0, t0 = cpu_seconds(), time.perf_counter()
            ref = legacy_refine(mesh, vol, masks, cams)
            t1 = time.perf_counter()
            rel = legacy_relax(ref, masks, cams)
            t2 = time.perf_counter()
            row("legacy refine", 1e3 * (t1 - t0), ref)
            row("legacy refine+relax", 1e3 * (t2 - t0), rel, 1e3 * (cpu_seconds() - c0))
            target = int(1.5 * len(mesh.faces))
            t0 = time.perf_counter()
            v, f = fast_simplification.simplify(np.asarray(ref.vertices), np.asarray(ref.faces), target_count=target)
            t1 = time.perf_counter()
            dec = trimesh.Trimesh(v, f, process=False)
            row("legacy + fast-simpl. 1.5x", 1e3 * (t1 - t0), dec)
            row("  + legacy relax", float("nan"), legacy_relax(dec, masks, cams))
            s = pyfqmr.Simplify()
            s.setMesh(np.asarray(ref.vertices), np.asarray(ref.faces))
            t0 = time.perf_counter()
            s.simplify_mesh(target_count=target, aggressiveness=7, preserve_border=True, verbose=False)
            t1 = time.perf_counter()
            v, f, _ = s.getMesh()
            row("legacy + pyfqmr 1.5x", 1e3 * (t1 - t0), trimesh.Trimesh(v, f, process=False))
        print(f"\n{name}: {len(cams)} views {cams[0].width}x{cams[0].height}, 128^3 mc {len(mesh.vertices)} vertices "
              f"{len(mesh.faces)} faces; new refine+relax over {args.reps} repetitions: wall min {1e3 * min(walls):.0f} ms")
        print(f"{'':27s} {'ms':>8s} {'cpu ms':>7s} {'faces/mc':>8s} {'folded':>6s} {'<5deg%':>7s} {'rough':>6s} "
              f"{'n.err':>6s} {'IoU':>7s}")
        for r in rows:
            cpu = "" if r[2] is None else f"{r[2]:7.0f}"
            print(f"{r[0]:27s} {r[1]:8.0f} {cpu:>7s} {r[3]:8.2f} {r[4]:6d} {r[5]:7.2f} {r[6]:6.2f} {r[7]:6.2f} {r[8]:7.4f}")
    print(f"\nload average after: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f}")


if __name__ == "__main__":
    main()
