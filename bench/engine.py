"""Engine overhead and start-up: a 100-frame, 6-node graph of trivial nodes, the demo graph over 100 frames,
and the CLI's start-up.

Prints: first run (every item computed) in-process and with a 2-process pool, per-item scheduling overhead,
the fully cached re-run (goal <= 2 s) through the API and as a CLI process, the same for graphs/demo.yaml at 100
frames (small images), and `volcap --help` / `validate` wall times (goals 0.3 s / 0.5 s), best of 5.
Usage: python bench/engine.py [--frames 100] [--no-demo]
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "bench")]

import trivial_nodes  # noqa: E402,F401

from nodegraph.cache import Cache  # noqa: E402
from nodegraph.executors import LocalExecutor  # noqa: E402
from nodegraph.graphfile import load_graph  # noqa: E402
from nodegraph.run import run_graph  # noqa: E402
from machine import describe  # noqa: E402

GRAPH = """\
frames: 0:{frames}
nodes:
  a: {{type: bench.make}}
  b: {{type: bench.step, in: {{x: a.out}}}}
  c: {{type: bench.step, in: {{x: b.out}}}}
  d: {{type: bench.step, in: {{x: c.out}}}}
  e: {{type: bench.step, in: {{x: d.out}}}}
  f: {{type: bench.step, in: {{x: e.out}}}}
"""


def timed(fn):
    t = time.perf_counter()
    out = fn()
    return time.perf_counter() - t, out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--no-demo", action="store_true", help="skip the demo graph (it renders 100 small frames first)")
    args = ap.parse_args()
    print(describe())
    rows = []
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        g = d / "g.yaml"
        g.write_text(GRAPH.format(frames=args.frames))
        graph = load_graph(g)
        n = len(graph.nodes) * args.frames
        for jobs in (1, 2):
            cache = Cache(d / f"cache{jobs}")
            t, res = timed(lambda: run_graph(graph, cache, d / "out", LocalExecutor(jobs), progress=False))
            assert res.ok and res.counts() == {"done": n}
            rows.append((f"first run, {n} items, jobs={jobs}", t, t / n * 1000))
        t, res = timed(lambda: run_graph(load_graph(g), Cache(d / "cache1"), d / "out", LocalExecutor(1), progress=False))
        assert res.counts() == {"cached": n}
        rows.append(("cached re-run (API, incl. load+plan)", t, t / n * 1000))
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(ROOT / "bench")]))
        code = ("import sys, trivial_nodes; from nodegraph.cli import main; sys.exit(main(sys.argv[1:]))")
        cmd = [sys.executable, "-c", code, "--cache", str(d / "cache1"), "run", str(g), "--out", str(d / "out"), "-q"]
        t, proc = timed(lambda: subprocess.run(cmd, env=env, capture_output=True, text=True))
        assert proc.returncode == 0, proc.stderr
        rows.append(("cached re-run (CLI process, incl. start-up)", t, t / n * 1000))
        volcap = [sys.executable, str(ROOT / "app.py")]
        demo = ROOT / "graphs" / "demo.yaml"
        small = ["--set", "stage.width=160", "--set", "stage.height=120", "--set", "hull.resolution=64",
                 "--frames", f"0:{args.frames}"]
        if not args.no_demo:
            run = volcap + ["--cache", str(d / "demo"), "run", str(demo), "--out", str(d / "demo_out"), "-q", *small]
            subprocess.run(run, check=True, capture_output=True)
            n_demo = len(load_graph(demo).nodes) * args.frames
            t = min(timed(lambda: subprocess.run(run, check=True, capture_output=True))[0] for _ in range(3))
            rows.append((f"demo graph, {args.frames} frames: cached re-run (CLI)", t, t / n_demo * 1000))
        for label, cmd in (("volcap --help", volcap + ["--help"]), ("volcap validate graphs/demo.yaml", volcap + ["validate", str(demo)])):
            t = min(timed(lambda: subprocess.run(cmd, check=True, capture_output=True))[0] for _ in range(5))
            rows.append((label, t, float("nan")))
    print(f"{'engine: ' + str(args.frames) + ' frames x 6 nodes':52s} {'wall s':>8s} {'ms/item':>8s}")
    for name, t, per in rows:
        print(f"{name:52s} {t:8.3f} {per:8.3f}")
    print("goals: cached re-run <= 2 s; --help <= 0.3 s; validate <= 0.5 s")
    print(describe().splitlines()[-1])


if __name__ == "__main__":
    main()
