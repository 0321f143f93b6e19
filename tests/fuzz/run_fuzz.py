"""The long fuzz run (issue 12): the catalogue of hostile graph files, --set values and options in
tests/fuzz/hostile.py (about a thousand) plus N hypothesis-generated cases, each run through the command line
(`validate`, then `explain` when valid; `run` for catalogue cases marked RUN and for valid graphs of engine
test nodes) in a worker process. A case that does not answer within the hang limit is a hang: the worker is
killed and replaced. Prints the counted table: cases tried / ok / clean errors (exit 2) / node failed (run exit 1, one message) /
tracebacks / hangs / slow.

    python3 tests/fuzz/run_fuzz.py [--generated 3000] [--hang 20] [--seed 1] [--show 5]
"""
from __future__ import annotations

import argparse
import importlib
import multiprocessing as mp
import os
import shutil
import sys
import tempfile
import time
from collections import Counter, defaultdict
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
sys.path[:0] = [str(ROOT), str(HERE.parent), str(HERE)]


def _worker(conn, tmp: str):
    sys.path[:0] = [str(ROOT), str(HERE.parent), str(HERE)]
    importlib.import_module("enginenodes")  # registers the t.* nodes
    from hostile import attempt, write_case
    from nodegraph.graphfile import load_graph

    base = Path(tmp)
    while True:
        msg = conn.recv()
        if msg is None:
            return
        idx, text, extra = msg
        case = base / f"case{idx}"
        case.mkdir()
        graph = case / "g.yaml"
        write_case(graph, text)
        common = ["--cache", str(case / "cache")]
        if extra[:1] == ["RUN"]:
            args = [*common, "run", str(graph), "--out", str(case / "out"), "-q", "-j", "1", *extra[1:]]
            result = attempt(args, limit=60)
        else:
            result = attempt([*common, "validate", str(graph), *extra])
            if result[0] == "ok":
                try:
                    g = load_graph(graph, [a for a in extra if a != "--set"])
                except Exception:  # noqa: BLE001 - validate said OK: this cannot fail
                    g = None
                if g is not None and len(g.nodes) * len(g.frames) <= 1000:  # planning a million items is slow, not hostile
                    result = attempt([*common, "explain", str(graph), *extra])
                    if result[0] == "ok" and all(s.type_name.startswith("t.") for s in g.nodes.values()) and len(g.frames) <= 50:
                        result = attempt([*common, "run", str(graph), "--out", str(case / "out"), "-q", "-j", "1", *extra], 60)
        shutil.rmtree(case, ignore_errors=True)
        conn.send(result)


def generated(n: int, seed: int) -> list:
    from hypothesis import HealthCheck, given, settings
    from hostile import strategies

    graphs, sets = strategies()
    out = []

    @settings(max_examples=n, database=None, deadline=None, suppress_health_check=list(HealthCheck))
    @given(text=graphs, extra=sets)
    def collect(text, extra):
        out.append(("generated", text, [a for s in extra for a in ("--set", s)]))

    from hypothesis import seed as hseed

    hseed(seed)(collect)()
    return out[:n]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--generated", type=int, default=3000, help="hypothesis-generated cases (default 3000)")
    ap.add_argument("--hang", type=float, default=20.0, help="seconds after which a case counts as a hang")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--show", type=int, default=5, help="findings shown per category")
    ap.add_argument("--only", help="run only this category")
    args = ap.parse_args()
    os.environ.setdefault("VOLCAP_CL_DEVICE", "cpu")
    importlib.import_module("enginenodes")
    from hostile import catalogue

    tmp = Path(tempfile.mkdtemp(prefix="volcap-fuzz-"))
    pwned = Path("/tmp/volcap_pwned")
    pwned.unlink(missing_ok=True)
    t0 = time.time()
    cases = catalogue(tmp) + generated(args.generated, args.seed)
    if args.only:
        cases = [c for c in cases if c[0] == args.only]
    print(f"{len(cases)} cases ({time.time() - t0:.0f} s to build)", flush=True)
    ctx = mp.get_context("spawn")

    def start():
        a, b = ctx.Pipe()
        p = ctx.Process(target=_worker, args=(b, str(tmp)), daemon=True)
        p.start()
        return p, a

    proc, conn = start()
    counts: dict[str, Counter] = defaultdict(Counter)
    findings: dict[str, list] = defaultdict(list)
    slowest = []
    for idx, (cat, text, extra) in enumerate(cases):
        conn.send((idx, text, extra))
        if conn.poll(args.hang + (30 if idx == 0 else 0)):  # the first case also imports everything
            outcome, detail, seconds = conn.recv()
        else:
            outcome, detail, seconds = "hang", f"no answer within {args.hang:.0f} s", args.hang
            proc.kill()
            proc.join()
            proc, conn = start()
        counts[cat][outcome] += 1
        slowest.append((seconds, cat, idx))
        if outcome not in ("ok", "clean", "node failed"):
            findings[cat].append((idx, outcome, detail, text if isinstance(text, bytes) else text[:300], extra[:4]))
        if (idx + 1) % 250 == 0:
            print(f"  {idx + 1} cases, {time.time() - t0:.0f} s", flush=True)
    conn.send(None)
    proc.join(5)
    shutil.rmtree(tmp, ignore_errors=True)

    total = Counter()
    print(f"\n{'category':18s} {'cases':>6s} {'ok':>6s} {'clean':>6s} {'node fail':>9s} {'traceback':>9s} {'hang':>5s} {'slow':>5s}")
    for cat in sorted(counts, key=lambda c: -sum(counts[c].values())):
        c = counts[cat]
        total.update(c)
        print(f"{cat:18s} {sum(c.values()):6d} {c['ok']:6d} {c['clean']:6d} {c['node failed']:9d} {c['traceback']:9d} "
              f"{c['hang']:5d} {c['slow']:5d}")
    print(f"{'total':18s} {sum(total.values()):6d} {total['ok']:6d} {total['clean']:6d} {total['node failed']:9d} {total['traceback']:9d} "
          f"{total['hang']:5d} {total['slow']:5d}")
    slowest.sort(reverse=True)
    print("slowest cases: " + ", ".join(f"{s:.2f} s ({c} #{i})" for s, c, i in slowest[:5]))
    print(f"code executed by a YAML tag: {'YES' if pwned.exists() else 'no'}; wall {time.time() - t0:.0f} s; "
          f"load average {os.getloadavg()[0]:.2f}")
    for cat, items in findings.items():
        for idx, outcome, detail, text, extra in items[: args.show]:
            print(f"\n[{cat} #{idx}] {outcome}: {detail[:800]}\n  graph: {text!r}\n  argv: {extra!r}")
    return 1 if total["traceback"] or total["hang"] or pwned.exists() else 0


if __name__ == "__main__":
    sys.exit(main())
