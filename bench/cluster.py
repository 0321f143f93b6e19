"""Dask executor scaling: frames/s of a 20-frame synthetic graph on 1 vs 2 workers, and the per-item
overhead of the Dask executor vs the local one (trivial nodes).

Usage: python bench/cluster.py [--frames 20]
Each configuration starts from an empty cache; the cluster start-up is included in the wall time and
also reported alone.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "bench")]

import trivial_nodes  # noqa: E402,F401

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
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        g = load_graph(ROOT / "graphs/demo.yaml", overrides=SMALL, frames=f"0:{args.frames}")
        for name, ex in (("local, 1 process", LocalExecutor(1)), ("local, 2 processes", LocalExecutor(2)),
                         ("dask, 1 worker", DaskExecutor(workers=1)), ("dask, 2 workers", DaskExecutor(workers=2))):
            t, res = timed_run(g, ex, d / name.replace(" ", "_").replace(",", ""), d / "out")
            rows.append((f"demo graph (small), {name}", t, args.frames / t))
        from distributed import LocalCluster

        t0 = time.perf_counter()
        LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None).close()
        startup = time.perf_counter() - t0
        n = 200
        tg = d / "trivial.yaml"
        tg.write_text(TRIVIAL.format(n=n))
        tr = load_graph(tg)
        t_local, _ = timed_run(tr, LocalExecutor(2), d / "tl", d / "out2")
        t_dask, _ = timed_run(tr, DaskExecutor(workers=2), d / "td", d / "out3")
    print(f"{'configuration':48s} {'wall s':>8s} {'frames/s':>9s}")
    for name, t, fps in rows:
        print(f"{name:48s} {t:8.2f} {fps:9.2f}")
    base = {r[0].rsplit(", ", 1)[1]: r[2] for r in rows}
    print(f"scaling dask 2 workers / 1 worker: {base['2 workers'] / base['1 worker']:.2f}x; "
          f"local 2 / 1: {base['2 processes'] / base['1 process']:.2f}x")
    print(f"LocalCluster start-up (2 workers): {startup:.2f} s")
    print(f"per-item overhead, {3 * n} trivial items: local pool {t_local / (3 * n) * 1000:.2f} ms, "
          f"dask {t_dask / (3 * n) * 1000:.2f} ms (cluster start-up included)")


if __name__ == "__main__":
    main()
