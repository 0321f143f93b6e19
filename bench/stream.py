"""The deliverable's sizes: the stream ladder (export.stream) against what a user would otherwise ship, per-frame
textured GLBs and per-frame Draco meshes, from one run of the demo graph (graphs/demo.yaml: the synthetic walking
figure, ~24k faces at 128^3), measured in the same run.

    python bench/stream.py [--frames 0:25] [--atlas 2048] [--low-atlas 1024] [--cache DIR]

Per rung: faces, atlas, Mbit/s at 30 fps (all files of the rung over the clip), atlas PSNR of the decoded H.264
against the lossless atlas (mean, worst frame), geometry error of the decoded positions against the tracked mesh
(mm, mean and max). The goal (issue 23): <= 10 Mbit/s at 30 fps for ~20k triangles and a 2048^2 atlas, PSNR >= 38 dB,
geometry error <= 0.5 mm mean.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from nodegraph import Table  # noqa: E402

from machine import describe, load_average  # noqa: E402
from track import outputs, run  # noqa: E402


def mbit(nbytes: int, frames: int, fps: float = 30.0) -> float:
    return nbytes * 8 / (frames / fps) / 1e6


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", default="0:25")
    ap.add_argument("--atlas", type=int, default=2048)
    ap.add_argument("--low-atlas", type=int, default=1024)
    ap.add_argument("--bits", type=int, default=None, help="position bits of both rungs (default: the graph's)")
    ap.add_argument("--crf", type=int, default=None, help="H.264 CRF of both rungs (default: the graph's)")
    ap.add_argument("--cache", default=str(ROOT / ".volcap-cache"))
    a = ap.parse_args()
    print(describe())
    sets = [f"texture.size={a.atlas}", f"texture_low.size={a.low_atlas}"]
    for node in ("stream", "stream_low"):
        sets += [f"{node}.bits={a.bits}"] * (a.bits is not None) + [f"{node}.crf={a.crf}"] * (a.crf is not None)
    records = run(ROOT / "graphs/demo.yaml", Path(a.cache), a.frames, overrides=sets)
    rows = []
    for node in ("stream", "stream_low"):
        (rep,), _ = outputs(records, node, "report", Table)
        rows.append((f"stream {rep['rung']}", rep["faces"], f"{rep['atlas'][0]}²", mbit(rep["geometry_bytes"] + rep["video_bytes"],
                     rep["frames"]), rep["atlas_psnr_db_mean"], rep["atlas_psnr_db_min"], rep["geometry_error_mm_mean"],
                     rep["geometry_error_mm_max"]))
        n = rep["frames"]
        print(f"{node}: at 30 fps over {n} frames: connectivity + UVs (Draco, once per segment) "
              f"{mbit(rep['connectivity_bytes'], n):.2f} Mbit/s, positions {mbit(rep['geometry_bytes'] - rep['connectivity_bytes'], n):.2f}, "
              f"atlas video {mbit(rep['video_bytes'], n):.2f}; without the once-per-segment part "
              f"{rep['mbit_s_motion_at_30fps']:.2f} Mbit/s (what a long segment tends to)")
    glb = [Path(p) for r in records if r["node"] == "textured" for p in r["published"]]
    rows.append(("per-frame textured GLB (PNG atlas)", rows[0][1], rows[0][2], mbit(sum(p.stat().st_size for p in glb), n),
                 float("inf"), float("inf"), 0.0, 0.0))
    (sizes,), _ = outputs(records, "dynamic", "sizes", Table)
    rows.append(("per-frame Draco reconstructions (geometry only)", "-", "-", mbit(sizes["reconstruction_draco_bytes"], n),
                 float("nan"), float("nan"), float("nan"), float("nan")))
    rows.append(("dynamic mesh Draco (track.export, geometry only)", rows[0][1], "-", mbit(sizes["dynamic_draco_bytes"], n),
                 float("nan"), float("nan"), float("nan"), float("nan")))
    vol = [Path(p) for r in records if r["node"] == "volumetric" for p in r["published"]]
    vol_bytes = sum(p.stat().st_size for p in vol if p.suffix in (".glb", ".mp4"))
    rows.append(("export.volumetric GLB + atlas H.264", rows[0][1], rows[0][2], mbit(vol_bytes, n), float("nan"),
                 float("nan"), 0.0, 0.0))
    print(f"\n{n} frames of the demo figure; Mbit/s at 30 fps")
    print(f"{'form':50s} {'faces':>6s} {'atlas':>6s} {'Mbit/s':>8s} {'PSNR dB':>8s} {'worst':>6s} {'geo mm':>7s} {'max':>6s}")
    for name, faces, atlas, rate, psnr, worst, err, emax in rows:
        print(f"{name:50s} {faces!s:>6s} {atlas:>6s} {rate:8.2f} {psnr:8.2f} {worst:6.2f} {err:7.3f} {emax:6.3f}")
    print(f"ratio per-frame GLB / stream full: {rows[2][3] / rows[0][3]:.1f}x")
    print(f"load average at the end: {load_average()}")


if __name__ == "__main__":
    main()
