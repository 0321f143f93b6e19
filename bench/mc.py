"""Marching cubes speed on the hull volume of bench/hull.py: skimage, VTK Flying Edges (pyvista), ours.

    python bench/mc.py            # 128^3 and 256^3 occupancy (the figure's hull from 24 cameras)
Times are ms per call, min of repeats, all taken in the same run (rounds interleaved).
  vtk FE      pv.ImageData(...).contour([0.5], method="flying_edges") on a grid built beforehand (the padded
              occupancy as point data): the contour call alone; u8 = uint8 scalars, f32 = float32 scalars
  vtk+wrap    the same plus what a user's call costs around it: pad by one voxel, x-fastest copy
              (ravel(order="F")), pv.ImageData, point data, contour (uint8)
  ours        nodes.mc.marching_cubes(VoxelGrid): everything from the numpy occupancy to the numpy
              vertices/faces (upload, three kernels, prefix sum, read-back)
All give the same surface (same vertex and face counts: checked). This machine's VTK runs Flying Edges on
one thread; `POCL_MAX_PTHREAD_COUNT=1 python bench/mc.py` gives ours one thread too (same times here).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from hull import BOX, best_ms, figure_masks, ring_rig  # noqa: E402

from nodes.hull.hull import visual_hull  # noqa: E402
from nodes.mesh.mc import marching_cubes  # noqa: E402


def vtk_grid(occ: np.ndarray, spacing, dtype):
    import pyvista as pv

    padded = np.pad(occ, 1).astype(dtype, copy=False)
    grid = pv.ImageData(dimensions=padded.shape, spacing=tuple(spacing))
    grid.point_data["occ"] = padded.ravel(order="F")
    return grid


def main(repeats=9, rounds=3):
    from nodegraph import clrt
    from skimage.measure import marching_cubes as sk_mc

    print(f"OpenCL device: {clrt.device_name()}; VTK Flying Edges: ", end="")
    import vtk
    smp = vtk.vtkSMPTools()
    print(f"VTK {vtk.vtkVersion.GetVTKVersion()}, SMP backend {smp.GetBackend()}, {smp.GetEstimatedNumberOfThreads()} thread(s)")
    cams = ring_rig(24)
    masks = figure_masks(cams)
    print(f"{'grid':>12} {'faces':>7} {'skimage':>8} {'vtk FE u8':>10} {'vtk FE f32':>10} {'vtk+wrap':>9} {'ours':>6} {'ours/vtk':>8}")
    for res in (128, 256):
        vol = visual_hull(masks, cams, BOX, res)
        occ = vol.occupancy
        g8, g32 = vtk_grid(occ, vol.voxel_size, np.uint8), vtk_grid(occ, vol.voxel_size, np.float32)
        fe = lambda g: g.contour([0.5], scalars="occ", method="flying_edges")  # noqa: E731
        v, f = marching_cubes(vol)
        for g in (g8, g32):
            m = fe(g)
            assert (m.n_points, m.n_cells) == (len(v), len(f)), "VTK and ours disagree"
        t = {}
        for _ in range(rounds):  # interleave so that load from other processes hits every method alike
            for name, fn in [("fe8", lambda: fe(g8)), ("fe32", lambda: fe(g32)),
                             ("wrap", lambda: fe(vtk_grid(occ, vol.voxel_size, np.uint8))),
                             ("ours", lambda: marching_cubes(vol))]:
                t[name] = min(t.get(name, np.inf), best_ms(fn, repeats))
        padded = np.pad(occ, 1).astype(np.float32)
        t_sk = best_ms(lambda: sk_mc(padded, 0.5, gradient_direction="ascent"), 3)
        best_vtk = min(t["fe8"], t["fe32"])
        print(f"{'x'.join(map(str, occ.shape)):>12} {len(f):>7} {t_sk:8.1f} {t['fe8']:10.2f} {t['fe32']:10.2f} "
              f"{t['wrap']:9.2f} {t['ours']:6.2f} {t['ours'] / best_vtk:8.2f}", flush=True)
    print("ours/vtk: ours against the faster VTK contour call without wrapping (< 1: ours is faster)")


if __name__ == "__main__":
    main()
