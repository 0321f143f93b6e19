"""Dask executor scaling: frames/s of the demo graph (small stage, the whole chain with its sequence nodes)
on 1, 2 and 4 local processes and Dask workers, the scaling efficiency (frames/s with n / (n x frames/s with
1)), and the per-item overhead of the Dask executor vs the local one (trivial nodes).

Usage: python bench/cluster.py [--frames 20] [--workers 1 2 4] [--windows 0 5] [--kinds local dask]
``--windows``: track's window (graph key ``window:``; 0 = one track item over every frame): with a window the
tracking runs per window in parallel and a frame's texture waits only on its own window (a segment per window at
least: the segment count is printed). Each configuration starts from an empty cache; the cluster start-up is included in the wall time and
also reported alone. Prints the OpenCL device, the CPU and the load average (workers beyond the cores share
them: on a 2-core machine 4 workers measure oversubscription, not scaling).
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "bench")]

import trivial_nodes  # noqa: E402,F401
from machine import describe, load_average  # noqa: E402

from nodegraph.cache import Cache  # noqa: E402
from nodegraph.dask_executor import DaskExecutor  # noqa: E402
from nodegraph.executors import LocalExecutor  # noqa: E402
from nodegraph.graphfile import load_graph  # noqa: E402
from nodegraph.run import run_graph  # noqa: E402

SMALL = ["stage.width=320", "stage.height=240", "stage.cameras=8", "hull.resolution=64"]
TRIVIAL = "frames: 0:{n}\nnodes:\n  a: {{type: bench.make}}\n  b: {{type: bench.step, in: {{x: a.out}}}}\n  c: {{type: bench.step, in: {{x: b.out}}}}\n"


def timed_run(graph, executor, cache_dir, out_dir):
    t = time.perf_counter()
    res = run_graph(graph, Cache(cache_dir), out_dir, executor, progress=False)
    assert res.ok, res.failures
    return time.perf_counter() - t, res


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--windows", type=int, nargs="+", default=[0], help="track windows in frames (0: none)")
    ap.add_argument("--kinds", nargs="+", default=["local", "dask"], choices=["local", "dask"])
    args = ap.parse_args()
    print(describe())
    rows = []
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        for w in args.windows:
            g = load_graph(ROOT / "graphs/demo.yaml", overrides=SMALL + ([f"track.window={w}"] if w else []),
                           frames=f"0:{args.frames}")
            configs = [(f"local, {n} process{'es' if n > 1 else ''}", "local", n, LocalExecutor(n)) for n in args.workers]
            configs += [(f"dask, {n} worker{'s' if n > 1 else ''}", "dask", n, DaskExecutor(workers=n)) for n in args.workers]
            for name, kind, k, ex in configs:
                if kind not in args.kinds:
                    continue
                name = f"{name}, track {'window ' + str(w) if w else 'whole'}"
                t, res = timed_run(g, ex, d / name.replace(" ", "_").replace(",", ""), d / "out")
                seq = sum(r["seconds"] for r in res.records if r["frame"] is None or "frames" in r)
                segments = json.loads((d / "out/tables/dynamic/all.json").read_text())["segments"]
                rows.append((f"demo (small), {name}", f"{kind}{w}", k, t, args.frames / t))
                print(f"  {name}: {t:.1f} s, sequence items {seq:.1f} s summed, {segments} segments, "
                      f"load {load_average()}", flush=True)
        startup = t_local = t_dask = None
        n = 200
        if "dask" in args.kinds:
            from distributed import LocalCluster

            t0 = time.perf_counter()
            LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None).close()
            startup = time.perf_counter() - t0
            tg = d / "trivial.yaml"
            tg.write_text(TRIVIAL.format(n=n))
            tr = load_graph(tg)
            t_local, _ = timed_run(tr, LocalExecutor(2), d / "tl", d / "out2")
            t_dask, _ = timed_run(tr, DaskExecutor(workers=2), d / "td", d / "out3")
    print(f"{'configuration':62s} {'wall s':>8s} {'s/frame':>8s} {'frames/s':>9s} {'speed-up':>9s} {'efficiency':>10s}")
    for name, kind, k, t, fps in rows:
        one = next((r[4] for r in rows if r[1] == kind and r[2] == min(args.workers)), fps)
        base = min(args.workers)
        print(f"{name:62s} {t:8.2f} {t / args.frames:8.2f} {fps:9.2f} {fps / one:8.2f}x {fps / one * base / k:10.2f}")
    if startup is not None:
        print(f"LocalCluster start-up (2 workers): {startup:.2f} s")
        print(f"per-item overhead, {3 * n} trivial items: local pool {t_local / (3 * n) * 1000:.2f} ms, "
              f"dask {t_dask / (3 * n) * 1000:.2f} ms (cluster start-up included)")
    print(f"load average at the end: {load_average()}")


if __name__ == "__main__":
    main()
