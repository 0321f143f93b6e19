"""The whole chain per frame through the product's path (issue 26: "a minute of footage in half an hour on one
small machine"): graphs/demo.yaml through `volcap run` (the CLI in a fresh process: start-up, planning, cache,
frame units and all), every stage's seconds per frame from the run record (OUT/run.json), the end-to-end wall
time per frame, and the projected hours per minute of 30 fps footage next to the industry's figures.

    python bench/chain.py [--cameras 12] [--width 640] [--height 480] [--frames 0:12] [--resolution 128] [--jobs 1]
    python bench/chain.py --cameras 24 --width 1920 --height 1080    # the issue's 24-camera HD stage (slow here)

Every run uses a fresh, temporary cache folder, so no work item is a cache hit (the synthetic stage is rendered
too; it stands in for the cameras and is shown apart from the chain). Stages are grouped by node TYPE from
run.json: key (key.chroma + key.cleanup), hull, mc, refine, relax, track (a sequence node: its total / frames,
with track.frame), texture, deliver (export.volumetric, export.stream, track.simplify and what is fed from the
simplified sequence: the second track.frame and texture), rig (skeletonize*, skin, skeleton.export), carve
(carve.space_carving and the mc of its volume), evals/exports (the rest). Sequence nodes run once: their
seconds are divided by the frame count like the others. "median" is the median frame of a per-frame node (the
first frame of each node type also pays its OpenCL kernel loading); sequence nodes have one item.

The same run then runs every chain stage's work items again in this process (``in_memory``: run() on values
held in memory, in the plan's order; no cache, no units), so each stage's CLI / own-work ratio shows what the
engine adds (loading inputs, keeping outputs); and it times the fused path of the first stages (bench/e2e.py's: chroma key straight into the hull's
device silhouettes, hull, marching cubes, images in memory) on the same rendered frames (read back from the
run's cache) and box, for the CLI/fused ratio of key+hull+mc. Hours per minute = seconds per frame x 1800 / 3600;
4DViews ~ 8 h and Fraunhofer HHI / Volucap ~ 12 h per minute of footage (issue 26). Last, where each chain stage's
CLI seconds went (run.json's per-item phases: inputs loaded, run(), lazy outputs made for keeping, kept ones written),
and how busy the workers were (the items' seconds over run.json's seconds x jobs): near 100 %, only shorter items
shorten the wall. A few frames are mostly first-frame costs (kernels loaded, libraries imported, encoders started, one
track window): for the rate of a long take, run ~48 frames with windows, e.g. ``--frames 0:48 -j 2 --set
track.window=12``. With ``--prerender`` the rendered stage's entries are checked (content hashes) before the timed run,
as the first run that reads a capture from the cache does once (``--first-read`` times that run instead).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from machine import describe, load_average  # noqa: E402

GRAPH = ROOT / "graphs" / "demo.yaml"
INDUSTRY = (("4DViews", 8.0), ("Fraunhofer HHI / Volucap", 12.0))  # hours of processing per minute of footage
GROUPS = (  # group -> node types (in table order)
    ("key", ("key.chroma", "key.cleanup")),
    ("hull", ("hull",)),
    ("mc", ("mc",)),
    ("refine", ("refine",)),
    ("relax", ("relax",)),
    ("track", ("track", "track.frame")),
    ("texture", ("texture",)),
    ("deliver", ("export.volumetric", "export.stream", "track.simplify")),
    ("rig", ("skeletonize", "skeletonize.sequence", "skeletonize.humanoid", "skin", "skeleton.export")),
    ("carve", ("carve.space_carving",)),
)
RENDER = "stage (synth render)"
REST = "evals/exports"


def group_of(node: str, types: dict, upstream: dict) -> str:
    """The group of ``node``: by its type, except what is fed from the simplified sequence (deliver) and the mc of
    a carved volume (carve)."""
    todo, seen = list(upstream[node]), set()
    while todo:
        n = todo.pop()
        if n not in seen:
            seen.add(n)
            todo.extend(upstream[n])
    if types[node] in ("track.frame", "texture", "texture.transfer") and any(types[n] == "track.simplify" for n in seen):
        return "deliver"
    if types[node] == "mc" and any(types[n] == "carve.space_carving" for n in upstream[node]):
        return "carve"
    if types[node] == "synth":
        return RENDER
    return next((g for g, ts in GROUPS if types[node] in ts), REST)


def in_memory(g, cache, nodes: set[str]) -> dict[str, list[float]]:
    """Each stage's own work, in this process: every work item of ``nodes`` (and what they read) run by
    ``call_node`` (run() and its output checks, what an item does between loading its inputs and keeping its
    outputs) in the plan's order, every value handed over in memory and dropped after its last reader; the
    synthetic stage's images come from the CLI run's cache (the render is not the chain). No cache, no frame units,
    no processes: what is left of a stage's CLI seconds is the engine's (loading, keeping, hashing). Returns node ->
    seconds per item (frame order)."""
    import gc
    import logging

    from nodegraph.records import Join, refs, resolve_type
    from nodegraph.run import plan_graph
    from nodegraph.worker import call_node

    items, _ = plan_graph(g, cache)
    want, todo = set(), list(nodes)
    while todo:
        n = todo.pop()
        if n not in want:
            want.add(n)
            todo.extend(g.upstream[n])
    # frame by frame, as the engine's frame units run (the plan lists a node's items for every frame together, which
    # would hold every frame's images at once): per-frame items by (sequence nodes before them, frame), a sequence
    # item after the frames it reads
    level: dict[str, int] = {}
    for n in g.order():
        level[n] = max((level[s] + (g.nodes[s].cls.per == "sequence") for s in g.upstream[n]), default=0)
    items = sorted((it for it in items if it.node in want),
                   key=lambda it: (level[it.node], it.frame is None, -1 if it.frame is None else it.frame))
    gc.collect()      # as the engine's workers do after their first unit (worker._settle): later full collections
    gc.freeze()       # would otherwise walk every module, class and program object of this process
    readers: dict[tuple, int] = {}
    for it in items:
        for r in refs(it.inputs):
            readers[(r.key, r.port)] = readers.get((r.key, r.port), 0) + 1
    values, seconds, log = {}, {}, logging.getLogger("bench.chain")

    def take(r):
        v = values[(r.key, r.port)]
        readers[(r.key, r.port)] -= 1
        if not readers[(r.key, r.port)]:
            del values[(r.key, r.port)]
        return v

    for it in items:
        cls = g.nodes[it.node].cls
        if it.node == "stage":
            out = {p: (d.type, cache.load(it.key, p, d.type)) for p, d in cls.outputs.items()}
        else:
            inputs = {p: None if r is None else [take(x) for x in r] if isinstance(r, list)
                      else resolve_type(r.type).join([take(x) for x in r.refs]) if isinstance(r, Join) else take(r)
                      for p, r in it.inputs.items()}
            t0 = time.perf_counter()
            out = call_node(cls, inputs, it.params, frame=it.frame, frames=it.frames, log=log)
            seconds.setdefault(it.node, []).append(time.perf_counter() - t0)
            del inputs
        for p, (_, v) in out.items():
            if readers.get((it.key, p)):
                values[(it.key, p)] = v
    return seconds


def check_stage(cache: Path, graph: Path, sets: list[str], frames: str) -> tuple[int, float]:
    """Check the rendered stage's cache entries once (content hashes; checked.json then remembers them), as the
    first run that reads them does: (entries, seconds). The timed run is then a rerun on a rendered capture, whose
    start does not hash 149 MB per frame again. (A copy of a cache by hard links changes every file's ctime: the
    copy's first run hashes everything again.)"""
    from nodegraph.cache import SETTLED_NS, Cache
    from nodegraph.graphfile import load_graph
    from nodegraph.run import plan_graph

    time.sleep(SETTLED_NS / 1e9)            # files younger than this are not remembered as checked
    c = Cache(cache)
    items, _ = plan_graph(load_graph(graph, overrides=sets, frames=frames), c)
    keys = [it.key for it in items if it.node == "stage"]
    t = time.perf_counter()
    bad = {k: problem for k in keys if (problem := c.verify(k))}
    if bad:
        sys.exit("the rendered stage's entries do not check: " + "; ".join(f"{k}: {p}" for k, p in bad.items()))
    return len(keys), time.perf_counter() - t


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cameras", type=int, default=12)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--frames", default="0:12", help="frame range A:B (half-open)")
    ap.add_argument("--resolution", type=int, default=128, help="hull resolution")
    ap.add_argument("--jobs", "-j", type=int, default=1, help="volcap run -j (1: in one process, stage times uncontended)")
    ap.add_argument("--repeats", type=int, default=3, help="timed passes of the fused path over the frames")
    ap.add_argument("--graph", default=str(GRAPH), help="graphs/demo.yaml (default) or graphs/bench/chain.yaml (the "
                    "issue's chain alone: no evals, rig or carve, so the end-to-end wall is the chain's)")
    ap.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE",
                    help="passed to volcap run, e.g. track.window=4 (repeatable)")
    ap.add_argument("--prerender", action="store_true", help="render the synthetic stage into the cache first (not "
                    "timed): the timed run's wall is then the chain's alone, also with -j 2 (where the render's "
                    "items overlap the chain's and their seconds cannot be subtracted from the wall)")
    ap.add_argument("--first-read", action="store_true", help="with --prerender: time the run that first reads "
                    "the rendered stage (it checks every entry's content hash, ~5 s per 100 HD frames of 24 views); "
                    "without it the stage is checked before the timed run, as a rerun on a capture finds it")
    a = ap.parse_args()
    if a.first_read and not a.prerender:
        ap.error("--first-read goes with --prerender (without it the timed run renders the stage itself)")
    print(describe())

    from nodegraph.cache import Cache
    from nodegraph.graphfile import load_graph

    graph = Path(a.graph).resolve()
    sets = [f"stage.cameras={a.cameras}", f"stage.width={a.width}", f"stage.height={a.height}",
            f"hull.resolution={a.resolution}"] + a.set
    tmp = tempfile.TemporaryDirectory(dir=os.environ.get("VOLCAP_BENCH_TMP"))
    cache, out = Path(tmp.name) / "cache", Path(tmp.name) / "out"
    cmd = [sys.executable, str(ROOT / "app.py"), "--cache", str(cache), "run", str(graph), "--frames", a.frames,
           "--out", str(out), "-q", "-j", str(a.jobs)] + [x for s in sets for x in ("--set", s)]
    if a.prerender:   # the stage alone, same parameters and frames: its items' keys are the timed run's
        only = Path(tmp.name) / "stage.yaml"
        g0 = load_graph(graph, overrides=sets, frames=a.frames)
        only.write_text("nodes:\n  stage: " + json.dumps({"type": g0.nodes["stage"].type_name,
                                                           "params": g0.nodes["stage"].params}) + "\n")
        pre = [sys.executable, str(ROOT / "app.py"), "--cache", str(cache), "run", str(only), "--frames", a.frames,
               "--out", str(Path(tmp.name) / "pre"), "-q", "-j", str(a.jobs)]
        subprocess.run(pre, check=True, capture_output=True)
    checked = None
    if a.prerender and not a.first_read:   # a rerun on a rendered capture: its entries' content checked once before
        checked = check_stage(cache, graph, sets, a.frames)
    t = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if res.returncode != 0:
        sys.exit(f"volcap run failed:\n{res.stdout[-2000:]}\n{res.stderr[-2000:]}")
    doc = json.loads((out / "run.json").read_text())
    records, nf = doc["items"], len(doc["frames"])
    hits = sum(bool(r.get("cache_hit")) for r in records)

    g = load_graph(graph, overrides=sets, frames=a.frames)
    types = {n: g.nodes[n].type_name for n in g.nodes}
    by_node: dict[str, list[dict]] = {}
    for r in records:
        by_node.setdefault(r["node"], []).append(r)
    group = {n: group_of(n, types, g.upstream) for n in by_node}

    # the fused path on the same rendered frames, from this run's cache (synth is a checkpoint)
    import e2e  # bench/e2e.py: the fused path's functions and key colour

    c = Cache(cache)
    stage_t = g.nodes["stage"].cls.outputs
    frames = []
    for r in sorted(by_node["stage"], key=lambda r: r["frame"]):
        images = [np.ascontiguousarray(im) for im in c.load(r["key"], "images", stage_t["images"].type).images]
        frames.append((images, c.load(r["key"], "cameras", stage_t["cameras"].type),
                       np.asarray(c.load(r["key"], "bounds", stage_t["bounds"].type), dtype=np.float64)))
    key = e2e.K.key_direction_from_rgb([round(255 * x) for x in e2e.GREEN])
    sil, fused = None, []
    for rep in range(1 + a.repeats):
        for images, cams, bounds in frames:
            t0 = time.perf_counter()
            edges = [e2e.K.matte_edges(cams, v, bounds) for v in range(len(images))]
            sil = e2e.K.chroma_key_bits(images, key, edges=edges, out=sil)
            volume = e2e.visual_hull(sil, cams, bounds, a.resolution, method="sparse")  # the demo's box: stage.bounds
            e2e.marching_cubes(volume)
            if rep:  # the first pass warms up (kernel builds, buffers)
                fused.append(time.perf_counter() - t0)
    fused_ms = 1e3 * float(np.median(fused))

    # each chain stage's own work in this process, on the same frames (a first pass over 3 frames builds the kernels)
    named = ("key", "hull", "mc", "refine", "relax", "track", "texture", "deliver")
    chain_nodes = {n for n in by_node if group[n] in named}
    first = a.frames.split(":")[0]
    in_memory(load_graph(graph, overrides=sets, frames=f"{first}:{int(first) + 3}"), c, chain_nodes)
    own = in_memory(g, c, chain_nodes)

    # the table
    order = [RENDER] + [gname for gname, _ in GROUPS] + [REST]
    print(f"{graph.relative_to(ROOT) if graph.is_relative_to(ROOT) else graph}{' ' + ' '.join(a.set) if a.set else ''}, {nf} frames ({a.frames}), {a.cameras} cameras x {a.width}x{a.height}, hull "
          f"{a.resolution}; `volcap run -j {a.jobs}` in a fresh process, fresh temporary cache: "
          f"{len(records)} items, {hits} cache hits")
    print("CLI = the item's seconds in run.json (inputs loaded, run, outputs kept); own = the same items' run() in this "
          "process, values in memory (bench.chain.in_memory); ratio = CLI / own on the median frame (sequence nodes: "
          "their items summed; the CLI's first frame also pays the kernels' loading)")
    print(f"{'group':>22} {'node':>14} {'type':>22} {'items':>5} {'s/frame':>8} {'median':>7} {'own':>7} "
          f"{'median':>7} {'ratio':>6}")
    sums, own_sums = {}, {}
    for gname in order:
        nodes = [n for n in by_node if group[n] == gname]
        if not nodes:
            continue
        for n in nodes:
            secs = [r["seconds"] for r in by_node[n]]
            per_frame = by_node[n][0]["frame"] is not None and "frames" not in by_node[n][0]   # not a window's item
            med = f"{np.median(secs):7.3f}" if per_frame else f"{'':>7}"
            mine = ""
            if n in own:
                ref = np.median(secs) if per_frame else sum(secs)
                ours = np.median(own[n]) if per_frame else sum(own[n])
                mine = (f" {sum(own[n]) / nf:7.3f} " + (f"{ours:7.3f}" if per_frame else f"{'':>7}")
                        + f" {ref / max(ours, 1e-9):6.2f}")
            print(f"{'':>22} {n:>14} {types[n]:>22} {len(secs):5d} {sum(secs) / nf:8.3f} {med}{mine}")
        sums[gname] = sum(r["seconds"] for n in nodes for r in by_node[n]) / nf
        if all(n in own for n in nodes):
            own_sums[gname] = sum(sum(own[n]) for n in nodes) / nf
            print(f"{gname:>22} {'':>14} {'group sum':>22} {'':>5} {sums[gname]:8.3f} {'':>7} {own_sums[gname]:7.3f} "
                  f"{'':>7} {sums[gname] / max(own_sums[gname], 1e-9):6.2f}")
        else:
            print(f"{gname:>22} {'':>14} {'group sum':>22} {'':>5} {sums[gname]:8.3f}")
    chain = sum(v for k, v in sums.items() if k != RENDER)
    per = wall / nf
    print(f"{'sum of items':>22} {'':>14} {'chain (no render)':>22} {'':>5} {chain:8.3f}")
    print(f"{'end to end':>22} {'':>14} {'wall, whole run':>22} {'':>5} {per:8.3f}   "
          f"({wall:.1f} s: start-up, planning, {'(the render cached: --prerender) ' if a.prerender else 'render and '}chain; "
          f"run.json says {doc['seconds']:.1f} s)")
    print(f"{'':>22} {'':>14} {'wall less the render':>22} {'':>5} {per - sums.get(RENDER, 0):8.3f}")
    if checked:
        print(f"{'':>22} {'':>14} {'stage checked before':>22} {'':>5} {checked[1] / nf:8.3f}   ({checked[0]} rendered "
              f"frames' entries hashed in {checked[1]:.1f} s before the timed run, as the first run on them does once; "
              "--first-read times that run instead)")
    # how busy the workers were: when they are (near 100 %) only shorter items shorten the wall; when not, the run
    # waited on something (a serial step, the start, the tail of sequence nodes)
    busy = sum(r["seconds"] for r in records if not r.get("cache_hit"))
    print(f"{'workers busy':>22} {'':>14} {'items / (run x jobs)':>22} {'':>5} {busy / (doc['seconds'] * a.jobs):8.1%}   "
          f"({busy:.1f} s of items in run.json's {doc['seconds']:.1f} s x {a.jobs} worker{'s' if a.jobs > 1 else ''})")

    def hours(s):
        return s * 1800 / 3600

    core = sum(sums.get(x, 0) for x in named)
    own_core = sum(own_sums.get(x, 0) for x in named)
    print(f"{'issue 26 chain':>22} {'':>14} {'key..deliver items':>22} {'':>5} {core:8.3f} {'':>7} {own_core:7.3f} "
          f"{'':>7} {core / max(own_core, 1e-9):6.2f}   (" + " + ".join(named)
          + f": {hours(core):.2f} h per minute of 30 fps footage, {hours(own_core):.2f} h for the stages' own work; "
          "goal 1 s/frame = 0.5 h)")

    print(f"projected hours per minute of 30 fps footage: {hours(per - sums.get(RENDER, 0)):.2f} h (wall less the "
          f"render), {hours(per):.2f} h (wall with it), {hours(chain):.2f} h (sum of chain items); "
          + ", ".join(f"{name} ~{h:.0f} h" for name, h in INDUSTRY))

    # where the CLI's seconds of each chain stage went (run.json's phases, median per-frame item, ms): inputs loaded,
    # run(), lazy outputs made for keeping, kept ones written (and hashed); the rest is the item's bookkeeping
    rows = []
    for n in sorted(chain_nodes, key=lambda n: (named.index(group[n]), n)):
        recs = [r for r in by_node[n] if r.get("phases")]
        if recs:
            med = {ph: 1e3 * float(np.median([r["phases"][ph] for r in recs])) for ph in ("load", "run", "make", "write")}
            rows.append(f"{n} " + " / ".join(f"{med[ph]:.0f}" for ph in med))
    print("engine phases, load / run / make / write, median item, ms: " + "; ".join(rows))

    k = ("key", "hull", "mc")
    khm = sum(sums.get(x, 0) for x in k)
    khm_med = sum(np.median([r["seconds"] for r in by_node[n]]) for n in by_node if group[n] in k)
    print(f"key+hull+mc: CLI {khm:.3f} s/frame (median frame {khm_med:.3f} s; the node key also despills the images "
          f"for the texture, and cleans the masks) vs fused {fused_ms:.1f} ms/frame (median of {len(fused)}): "
          f"{1e3 * khm / fused_ms:.1f}x ({1e3 * khm_med / fused_ms:.1f}x on the median frame)")
    print(f"load average at the end: {load_average()}")


if __name__ == "__main__":
    main()
