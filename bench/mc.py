"""Marching cubes speed on the hull volume of bench/hull.py: skimage, VTK Flying Edges (pyvista), ours.

    python bench/mc.py            # 128^3 and 256^3 occupancy (the figure's hull from 24 cameras)
Times are ms per call, min of repeats; ours includes padding, upload, both passes and the read-back.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from hull import BOX, best_ms, figure_masks, ring_rig  # noqa: E402

from nodes.hull import visual_hull  # noqa: E402
from nodes.mc import marching_cubes  # noqa: E402


def main(repeats=7):
    import pyvista as pv
    from skimage.measure import marching_cubes as sk_mc

    cams = ring_rig(24)
    masks = figure_masks(cams)
    print(f"{'grid':>12} {'faces':>8} {'skimage ms':>10} {'vtk FE ms':>10} {'ours ms':>8}")
    for res in (128, 256):
        vol = visual_hull(masks, cams, BOX, res)
        occ = vol.occupancy
        padded = np.pad(occ, 1).astype(np.float32)
        grid = pv.ImageData(dimensions=padded.shape, spacing=tuple(vol.voxel_size))
        grid.point_data["occ"] = padded.ravel(order="F")
        t_sk = best_ms(lambda: sk_mc(padded, 0.5, gradient_direction="ascent"), repeats)
        t_fe = best_ms(lambda: grid.contour([0.5], scalars="occ", method="flying_edges"), repeats)
        marching_cubes(vol)
        t_ours = best_ms(lambda: marching_cubes(vol), repeats)
        faces = len(marching_cubes(vol)[1])
        print(f"{'x'.join(map(str, occ.shape)):>12} {faces:>8} {t_sk:10.1f} {t_fe:10.1f} {t_ours:8.1f}", flush=True)


if __name__ == "__main__":
    main()
