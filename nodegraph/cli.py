"""Headless command line: run, validate, explain, nodes, describe, dot, cache, devices."""
from __future__ import annotations

import argparse
import os
import re
import sys
from pathlib import Path

from .errors import GraphError, VolcapError
from .records import frames_of


def _cache_dir(args) -> Path:
    return Path(args.cache or os.environ.get("VOLCAP_CACHE") or ".volcap-cache")


def _load(args):
    from .graphfile import load_graph

    return load_graph(args.graph, getattr(args, "set", None) or [], getattr(args, "frames", None))


def cmd_run(args) -> int:
    from .cache import Cache
    from .executors import make_executor
    from .run import run_graph

    graph = _load(args)
    if args.device:
        _check_device(args.device)
        os.environ["VOLCAP_CL_DEVICE"] = args.device  # inherited by worker processes
    if args.verbose:
        os.environ["VOLCAP_CL_VERBOSE"] = "1"  # OpenCL compiler output (nodegraph/clrt.py), in workers too
    if args.keep_all or args.report:  # a report draws the values: keep them all
        graph.keep_all()
    out = Path(args.out or Path("out") / Path(args.graph).stem)
    if args.executor == "dask":
        executor = make_executor("dask", args.workers or args.jobs, scheduler=args.scheduler)
    else:
        executor = make_executor("local", args.jobs)
    result = run_graph(graph, Cache(_cache_dir(args)), out, executor, progress=not args.quiet)
    counts = result.counts()
    print(f"{graph.path.name}: {len(result.records)} items in {result.seconds:.2f} s — "
          + ", ".join(f"{v} {k}" for k, v in sorted(counts.items())) + f"; run record: {result.out_dir / 'run.json'}")
    for line in result.summaries:
        print(line)
    for w in result.warnings:
        print(f"warning: {w}", file=sys.stderr)
    for line in warning_lines(result.records):
        print(line, file=sys.stderr)
    for f in result.failures:
        frame = "" if frames_of(f) == "all" else f" frame{'s' * ('frames' in f)} {frames_of(f)}"
        print(f"FAILED node '{f['node']}' ({f['type']}){frame}: {f['error']}\n  log: {f['log']}", file=sys.stderr)
    if args.report:
        from .report import write_report

        print(f"report: {write_report(result.out_dir)}")
    return 1 if result.failures else 0


def warning_lines(records: list[dict]) -> list[str]:
    """The items' warnings as the summary prints them: one line per node and message, naming every frame that gave
    it (a camera's calibration note on each of a take's 100 frames is one line, not 100). Messages that differ only
    in their figures ("9186 of 36378 faces ...", one per frame) are one line too, the first frame's standing for
    the others; two messages one item gave (camera 'cam01' and 'cam02') stay two lines. Each item's own text stays
    in run.json."""
    import re

    exact: dict[tuple, list] = {}
    for r in records:
        for w in dict.fromkeys(r.get("warnings", [])):     # a message an item logged twice counts once
            exact.setdefault((r["node"], r["type"], w), []).append(r)
    alike: dict[tuple, list] = {}                    # (node, type, message with its figures blanked) -> exact keys
    for key in exact:
        alike.setdefault((key[0], key[1], re.sub(r"\d+(\.\d+)?", "#", key[2])), []).append(key)
    groups = []
    for keys in alike.values():
        items = [id(r) for k in keys for r in exact[k]]
        if len(keys) > 1 and len(items) == len(set(items)):      # one such message per item: figures per frame
            groups.append((keys[0], [r for k in keys for r in exact[k]], True))
        else:
            groups.extend((k, exact[k], False) for k in keys)
    lines = []
    for (node, type_name, w), found, merged in groups:
        labels = [frames_of(r) for r in found]
        if len(found) == 1:
            frame = "" if labels[0] == "all" else f" frame{'s' * ('frames' in found[0])} {labels[0]}"
            lines.append(f"warning: node '{node}' ({type_name}){frame}: {w}")
            continue
        note = f" (frame {labels[0]}; the others with their own figures in run.json)" if merged else ""
        lines.append(f"warning: node '{node}' ({type_name}) frames {_frame_list(labels)} ({len(found)} items): {w}{note}")
    return lines


def _frame_list(labels: list[str]) -> str:
    """"0-49, 60-99" from frame labels (numbers as runs of consecutive frames; window and "all" labels as they are)."""
    nums = sorted({int(x) for x in labels if x.isdigit()})
    parts, start = [], None
    for i, n in enumerate(nums):
        if start is None:
            start = n
        if i + 1 == len(nums) or nums[i + 1] != n + 1:
            parts.append(str(start) if start == n else f"{start}-{n}")
            start = None
    return ", ".join(parts + [x for x in dict.fromkeys(labels) if not x.isdigit()])


def _check_device(spec: str):
    """Refuse an OpenCL device that does not exist before any work runs (not in the first OpenCL node)."""
    from .clrt import OpenCLUnavailable, _choose_device

    old = os.environ.get("VOLCAP_CL_DEVICE")
    os.environ["VOLCAP_CL_DEVICE"] = spec
    try:
        _choose_device()
    except OpenCLUnavailable as exc:
        raise VolcapError(f"--device {spec}: {exc}") from None
    finally:
        if old is None:
            os.environ.pop("VOLCAP_CL_DEVICE", None)
        else:
            os.environ["VOLCAP_CL_DEVICE"] = old


def cmd_validate(args) -> int:
    g = _load(args)
    print(f"{g.path}: OK — {len(g.nodes)} nodes, frames {g.frames[0]}..{g.frames[-1]} ({len(g.frames)})")
    return 0


def cmd_explain(args) -> int:
    from .cache import Cache
    from .run import explain

    graph = _load(args)
    if args.device:   # the device is part of every key (nodegraph/environment.py): explain the run that uses it
        _check_device(args.device)
        os.environ["VOLCAP_CL_DEVICE"] = args.device
    rows = explain(graph, Cache(_cache_dir(args)))
    for r in rows:
        frame = frames_of(r)
        state = "cached" if r["cached"] else "run   "
        why = "" if r["cached"] else "  changed: " + ", ".join(r["changed"])
        mem = f"  in memory: {', '.join(r['in_memory'])}" if r["in_memory"] else ""
        print(f"{state} {r['node']}@{frame}  {r['key'][:12]}{why}{mem}")
    n = sum(not r["cached"] for r in rows)
    print(f"{n} of {len(rows)} work items to run")
    return 0


def cmd_nodes(args) -> int:
    from .node import discovery_problems, registry

    for name, cls in sorted(registry().items()):
        first = (cls.doc().splitlines() or [""])[0]
        print(f"{name:22s} {first}")
    for p in discovery_problems():
        print(f"warning: {p}", file=sys.stderr)
    return 0


def cmd_describe(args) -> int:
    from .graphfile import suggest
    from .node import registry

    reg = registry()
    if args.node not in reg:
        raise VolcapError(f"unknown node type '{args.node}'{suggest(args.node, reg)}; see `nodes`")
    print(reg[args.node].describe())
    return 0


def cmd_dot(args) -> int:
    g = _load(args)
    lines = [f'digraph "{g.path.stem}" {{', "  rankdir=LR;", '  node [shape=box, style=rounded, fontname="Helvetica"];']
    for name, spec in g.nodes.items():
        lines.append(f'  {name} [label="{name}\\n({spec.type_name})"];')
    for name, spec in g.nodes.items():
        for port, (src, sport) in spec.inputs.items():
            lines.append(f'  {src} -> {name} [label="{sport}→{port}", fontsize=10];')
    lines.append("}")
    print("\n".join(lines))
    return 0


def cmd_cache(args) -> int:
    from .cache import Cache

    cache = Cache(_cache_dir(args))
    if args.action == "ls":
        total = 0
        for key, meta, size in cache.entries():
            total += size
            frame = "all" if meta.get("frame") is None else meta.get("frame")
            print(f"{key[:16]}  {meta.get('type', '?'):18s} {meta.get('node', '?')}@{frame}  {size / 1e6:8.2f} MB  {meta.get('seconds', 0):.3f} s")
        print(f"total {total / 1e6:.1f} MB in {cache.root}")
    elif args.action == "gc":
        n, freed = cache.gc(args.max_age)
        print(f"removed {n} entries, {freed / 1e6:.1f} MB")
    elif args.action == "verify":
        checked = damaged = legacy = 0
        for key, meta, problem in cache.verify_all():
            checked += 1
            if meta is not None and "hashes" not in meta:
                legacy += 1
            if problem:
                damaged += 1
                frame = "?" if meta is None else ("all" if meta.get("frame") is None else meta.get("frame"))
                where = "" if meta is None else f" ({meta.get('type', '?')} {meta.get('node', '?')}@{frame})"
                print(f"damaged {key}{where}: {problem}")
                cache.evict(key)
        print(f"{checked} entries checked, {damaged} damaged" + (" (removed)" if damaged else "")
              + (f"; {legacy} written before content hashes (only checked for missing files)" if legacy else ""))
        return 1 if damaged else 0
    elif args.action == "clear":
        cache.clear()
        print(f"cleared {cache.root}")
    return 0


def cmd_devices(args) -> int:
    from .clrt import devices_table

    print("OpenCL devices, fastest first by a short probe kernel (ms, measured once per machine; * = used):")
    for row in devices_table(refresh=args.refresh):
        print(row)
    return 0


def cmd_report(args) -> int:
    from .report import write_report

    print(write_report(Path(args.out_dir)))
    return 0


def _board(text: str) -> list[int]:
    m = re.fullmatch(r"\s*(\d+)\s*[xX,]\s*(\d+)\s*", text)
    if not m:
        raise argparse.ArgumentTypeError(f"board '{text}': give the inner corners as COLSxROWS, e.g. 9x6")
    return [int(m.group(1)), int(m.group(2))]


def cmd_calibrate(args) -> int:
    """`volcap calibrate FOLDER`: writes a one-node graph (OUT/calibrate.yaml, rerun or edit it) and runs it."""
    import json

    folder = Path(args.folder).resolve()
    if not folder.is_dir():
        raise GraphError(f"calibrate: {args.folder} is not a folder")
    out = Path(args.out or Path("out") / f"calibrate_{folder.name}")
    params = {"path": str(folder), "board": args.board, "square": args.square, "marker": args.marker,
              "dictionary": args.dictionary, "intrinsics": args.intrinsics,
              "extrinsics": args.extrinsics, "cameras": [c for c in (args.cameras or "").split(",") if c],
              "every": args.every, "k3": args.k3, "outlier_px": args.outlier_px, "out": "calibration"}
    out.mkdir(parents=True, exist_ok=True)
    graph = out / "calibrate.yaml"
    text = ("# written by `volcap calibrate`; rerun with `volcap run " + graph.as_posix() + f" --out {out.as_posix()}`\n"
            "frames: 0:1\nnodes:\n  calibrate: {type: calibrate, params: " + json.dumps(params) + "}\n")
    from .cache import atomic_write_text

    atomic_write_text(graph, text)
    run_args = argparse.Namespace(graph=str(graph), set=None, frames=None, cache=args.cache, device=None, verbose=False,
                                  keep_all=False, report=False, out=str(out), executor="local", jobs=1, workers=None,
                                  scheduler=None, quiet=True)
    rc = cmd_run(run_args)
    report = out / "calibration" / "report.json"
    if rc == 0 and report.is_file():
        r = json.loads(report.read_text())
        print(f"{'camera':<16}{'RMS px':>8}{'max px':>8}{'views':>7}{'shared':>7}{'dropped':>8}   fx        fy        cx       cy")
        for c in r["cameras"]:
            print(f"{c['camera']:<16}{c['rms_px']:8.3f}{c['max_px']:8.2f}{c['views']:7d}{c['shared_views']:7d}"
                  f"{c['dropped_views']:8d}   {c['fx']:<9.2f} {c['fy']:<9.2f} {c['cx']:<8.2f} {c['cy']:.2f}")
        print(f"all: RMS {r['rms_px']:.3f} px; world: {r['world']}; files: {out / 'calibration'}")
    return rc


def _positive_int(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"expects a whole number >= 1, got {text!r}")
    return n


def _scheduler_address(text: str) -> str:
    if not re.fullmatch(r"[A-Za-z][A-Za-z0-9+.-]*://[^\s/]+(/\S*)?", text) or len(text) > 1000:
        raise argparse.ArgumentTypeError(f"expects a Dask scheduler address such as tcp://HOST:PORT, got {text[:100]!r}")
    return text


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="volcap", description="Volumetric capture node graphs, run headless.")
    p.add_argument("--cache", help="cache folder (default $VOLCAP_CACHE or ./.volcap-cache)")
    sub = p.add_subparsers(dest="command", required=True)

    def graph_cmd(name, help_text, fn):
        sp = sub.add_parser(name, help=help_text)
        sp.add_argument("graph", help="graph file (YAML)")
        sp.add_argument("--set", action="append", metavar="NODE.PARAM=VALUE", help="override a parameter, or a sequence node's window: NODE.window=FRAMES (repeatable)")
        sp.add_argument("--frames", metavar="A:B", help="override the frame range (half-open)")
        sp.add_argument("--cache", default=argparse.SUPPRESS, help=argparse.SUPPRESS)
        sp.set_defaults(fn=fn)
        return sp

    r = graph_cmd("run", "run a graph", cmd_run)
    r.add_argument("--out", help="output folder (default out/GRAPHNAME)")
    r.add_argument("--jobs", "-j", type=_positive_int, help="parallel work items (default: CPU count; 1 = in this process)")
    r.add_argument("--executor", choices=["local", "dask"], default="local")
    r.add_argument("--workers", type=_positive_int, help="dask: worker processes of the LocalCluster (default 2)")
    r.add_argument("--scheduler", type=_scheduler_address, help="dask: address of an existing scheduler (tcp://HOST:PORT)")
    r.add_argument("--device", help="OpenCL device: cpu, gpu or PLATFORM:DEVICE (see `devices`)")
    r.add_argument("--report", action="store_true", help="write report.html into the output folder (keeps every output)")
    r.add_argument("--keep-all", action="store_true", help="store every output in the cache, not only the kept ones")
    r.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    r.add_argument("--verbose", "-v", action="store_true", help="show the OpenCL compiler's output (= VOLCAP_CL_VERBOSE=1)")
    graph_cmd("validate", "check a graph file without running it", cmd_validate)
    e = graph_cmd("explain", "dry run: which work items are cached, which run and why", cmd_explain)
    e.add_argument("--device", help="OpenCL device the run would use (part of the cache key; as for run)")
    graph_cmd("dot", "print the graph as Graphviz text", cmd_dot)
    sub.add_parser("nodes", help="list node types").set_defaults(fn=cmd_nodes)
    d = sub.add_parser("describe", help="ports, parameters and docs of a node type")
    d.add_argument("node")
    d.set_defaults(fn=cmd_describe)
    c = sub.add_parser("cache", help="inspect or clean the cache")
    c.add_argument("action", choices=["ls", "gc", "verify", "clear"],
                   help="ls: list entries; gc: remove leftovers (and old entries); verify: check every entry's content "
                        "against its recorded hashes, remove damaged ones (exit 1 when any); clear: remove everything")
    c.add_argument("--max-age", type=float, metavar="DAYS", help="gc: also remove entries unused for DAYS")
    c.add_argument("--cache", default=argparse.SUPPRESS, help=argparse.SUPPRESS)
    c.set_defaults(fn=cmd_cache)
    dv = sub.add_parser("devices", help="list OpenCL devices, fastest first (the fastest is used by default)")
    dv.add_argument("--refresh", action="store_true", help="measure the devices again")
    dv.set_defaults(fn=cmd_devices)
    cb = sub.add_parser("calibrate", help="calibrate a rig from checkerboard images or videos in a folder")
    cb.add_argument("folder", help="folder holding the board images or videos")
    cb.add_argument("--board", type=_board, required=True, help="inner corners COLSxROWS, e.g. 9x6")
    cb.add_argument("--square", type=float, required=True, help="side of a square in metres")
    cb.add_argument("--marker", type=float, default=0.0, help="ChArUco: side of a marker in metres (default 0: a "
                    "checkerboard); --board still counts inner corners")
    cb.add_argument("--dictionary", default="DICT_4X4_50", help="ChArUco: ArUco dictionary (default %(default)s)")
    cb.add_argument("--intrinsics", default="intrinsics/{name}/*",
                    help="pattern of each camera's own board images ({name} = camera; default %(default)s; '' = none)")
    cb.add_argument("--extrinsics", default="", help="pattern of the shared shots ({name}, {shot}), e.g. "
                    "'extrinsics/{name}/{shot}.png'; default: none (intrinsics only)")
    cb.add_argument("--cameras", help="comma-separated camera names (default: every {name} found)")
    cb.add_argument("--every", type=_positive_int, default=10, help="videos: every k-th frame (default 10)")
    cb.add_argument("--k3", action="store_true", help="also fit the third radial coefficient")
    cb.add_argument("--outlier-px", type=float, default=2.0, help="outlier threshold floor in pixels (default 2)")
    cb.add_argument("--out", help="output folder (default out/calibrate_FOLDERNAME)")
    cb.add_argument("--cache", default=argparse.SUPPRESS, help=argparse.SUPPRESS)
    cb.set_defaults(fn=cmd_calibrate)
    rp = sub.add_parser("report", help="write report.html for an existing output folder")
    rp.add_argument("out_dir")
    rp.set_defaults(fn=cmd_report)
    return p


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "run" and args.executor != "dask":
        for opt in ("scheduler", "workers"):
            if getattr(args, opt) is not None:
                parser.error(f"--{opt} needs --executor dask")
    try:
        return args.fn(args)
    except GraphError as exc:
        for line in exc.problems:
            print(f"error: {line}", file=sys.stderr)
        return 2
    except VolcapError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a folder or file the command needs (not a node's own failure: that is a result)
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted: finished work items are cached; rerun to continue", file=sys.stderr)
        return 130
