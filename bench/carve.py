"""Space carving speed on the Middlebury temple (16 views, 640x480): full carving to convergence, OpenCL vs
the NumPy reference (the same steps in NumPy, which is what a user without the kernels would run), and how
the cost grows with the resolution.

    python bench/carve.py                    # OpenCL at 64^3 .. 256^3; NumPy reference at 32^3 and 48^3
    python bench/carve.py --res 128 --repeats 3

The time is one carve() call: upload of images and masks, the sweeps and item passes until a pass removes
nothing, the final colour pass and the colour fill (the hull itself, computed beforehand, is not included).
Wall time depends on what else runs on the machine: the load average is printed, and the process's CPU
time (all its threads) is given as well. Baseline: the NumPy reference, run on the same data in the same run
(at small resolutions only: it needs minutes beyond 48^3).
"""
from __future__ import annotations

import argparse
import os
import platform
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from nodegraph import clrt  # noqa: E402
from nodegraph.testing import run_node  # noqa: E402
from nodes.carve.carving import CarveParams, carve  # noqa: E402

BOX = [-0.047606, -0.031878, -0.063887, 0.054817, 0.043303, 0.096277]   # the dataset README's box


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def timed(fn, repeats: int):
    """(best wall seconds, CPU seconds of that run, result)."""
    best = None
    for _ in range(repeats):
        c0, t0 = cpu_seconds(), time.perf_counter()
        out = fn()
        wall, cpu = time.perf_counter() - t0, cpu_seconds() - c0
        if best is None or wall < best[0]:
            best = (wall, cpu, out)
    return best


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=os.environ.get("VOLCAP_DATA", str(Path(__file__).resolve().parents[2] / "shared" / "data")))
    ap.add_argument("--res", type=int, nargs="+", default=[64, 96, 128, 192, 256])
    ap.add_argument("--numpy-res", type=int, nargs="*", default=[32, 48])
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    print(f"OpenCL device: {clrt.device_name()}")
    print(f"CPU: {cpu_model()}, {os.cpu_count()} cores; load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    cap = run_node("capture", {}, {"path": str(Path(args.data) / "middlebury_templeSR")})
    masks = run_node("key.threshold", {"images": cap["images"]}, {"threshold": 0.19, "dilate": 10, "erode": 7})["masks"]
    cams = cap["cameras"]
    print(f"middlebury_templeSR: {len(cams)} views, {cams[0].width}x{cams[0].height}; carve.space_carving defaults")
    print(f"{'res':>5s} {'grid':>14s} {'hull vox':>9s} {'kept':>9s} {'passes':>6s} {'OpenCL s':>9s} {'CPU s':>7s} "
          f"{'NumPy s':>9s} {'ratio':>7s} {'s / Mvox':>9s}")
    p = CarveParams()
    for res in sorted(set(args.res) | set(args.numpy_res)):
        hull = run_node("hull", {"masks": masks, "cameras": cams}, {"resolution": res, "bbox": BOX})["volume"]
        wall, cpu, out = timed(lambda: carve(hull, cap["images"], masks, cams, p), args.repeats)
        ref = ""
        if res in args.numpy_res:
            rw, _, rout = timed(lambda: carve(hull, cap["images"], masks, cams, p, method="numpy"), 1)
            same = np.array_equal(rout.volume.occupancy, out.volume.occupancy)
            ref = f"{rw:9.2f} {rw / wall:6.0f}x" + ("" if same else "  (voxels differ!)")
        dims = "x".join(map(str, hull.occupancy.shape))
        nvox = int(hull.occupancy.sum())
        print(f"{res:5d} {dims:>14s} {nvox:9d} {out.stats['voxels_out']:9d} {len(out.stats['passes']):6d} "
              f"{wall:9.3f} {cpu:7.2f} {ref if ref else f'{chr(45):>9s} {chr(45):>7s}'} {wall / (nvox / 1e6):9.2f}")
    print(f"load average now {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
