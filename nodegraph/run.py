"""Running a graph: plan -> skip what is cached -> execute the rest -> publish exports -> run.json.

run.json (in the output folder) records, per node and frame: status (done / cached / failed / skipped),
cache_hit, wall seconds, key, the cache folder of its outputs, the files it published, its log.
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from .cache import Cache, atomic_write_bytes, atomic_write_text
from .errors import DataError
from .graphfile import Graph
from .hashing import FileHasher, digest
from .plan import WorkItem, make_plan


@dataclass
class RunResult:
    records: list[dict]
    out_dir: Path
    seconds: float
    failures: list[dict] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)   # about the run as a whole (not one work item)
    summaries: list[str] = field(default_factory=list)  # one line per node that declares `summary` keys

    @property
    def ok(self) -> bool:
        return not self.failures

    def counts(self) -> dict:
        c: dict[str, int] = {}
        for r in self.records:
            c[r["status"]] = c.get(r["status"], 0) + 1
        return c


def plan_graph(graph: Graph, cache: Cache, notes: list | None = None):
    """Work items and slots of ``graph``; ``notes`` (a list) receives warnings about its inputs."""
    hasher = FileHasher(cache.root / "filehash.json", exclude=[cache.root])
    planned = make_plan(graph, hasher)
    for folder, names in hasher.skipped.items():
        if notes is not None:
            shown = ", ".join(names[:5]) + (f" and {len(names) - 5} more" if len(names) > 5 else "")
            notes.append(f"input folder {folder}: {len(names)} entries are not regular files (FIFO, socket or "
                         f"device) and were not read: {shown}")
    return planned


def _index_path(cache: Cache, graph: Graph, node: str, frame) -> Path:
    return cache.root / "index" / digest(str(graph.path))[:16] / f"{node}@{'all' if frame is None else frame}.json"


def check_cached(graph: Graph, items: list[WorkItem], cache: Cache, evict: bool = True) -> tuple[set, dict]:
    """(keys to run, {key: problem} of damaged entries). An item runs when it is not cached, or when its
    cached content is read by this run (an input of an item that runs, or the files a publishing node
    puts into the output folder) and fails verification: then it is evicted (``evict``) and recomputed, and
    its own inputs are checked in turn. Items are in dependency order, so walking them backwards sees every
    consumer before its producer."""
    run_keys = {it.key for it in items if not cache.has(it.key)}
    needed: set[str] = set()
    damaged: dict[str, str] = {}
    for it in reversed(items):
        if it.key not in run_keys and (it.key in needed or graph.nodes[it.node].cls.publishes):
            problem = cache.verify(it.key)
            if problem:
                damaged[it.key] = problem
                run_keys.add(it.key)
                if evict:
                    cache.evict(it.key)
        if it.key in run_keys:
            needed.update(it.deps)
    return run_keys, damaged


def explain(graph: Graph, cache: Cache) -> list[dict]:
    """Per work item: cached or to run, and which parts of its key differ from the last run of the same
    node and frame of this graph file (or that its cached result is damaged)."""
    items, slot = plan_graph(graph, cache)
    by_key = {it.key: it for it in items}
    run_keys, damaged = check_cached(graph, items, cache, evict=False)
    rows = []
    for (node, frame), key in slot.items():
        it = by_key[key]
        row = {"node": node, "frame": frame, "key": key, "cached": key not in run_keys, "changed": []}
        idx = _index_path(cache, graph, node, frame)
        if key in damaged:
            row["changed"] = [f"(cached result damaged: {damaged[key]})"]
        elif not row["cached"]:
            try:
                old = json.loads(idx.read_text())["components"]
                row["changed"] = _diff(old, it.components)
            except FileNotFoundError:
                row["changed"] = ["(no earlier run)"]
            except (OSError, ValueError, KeyError, TypeError):
                row["changed"] = ["(earlier run record unreadable)"]
        rows.append(row)
    return rows


def _diff(old, new, prefix="") -> list[str]:
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for k in sorted(set(old) | set(new)):
            out += _diff(old.get(k), new.get(k), f"{prefix}.{k}" if prefix else k)
        return out
    return [] if old == new else [prefix]


def run_graph(graph: Graph, cache: Cache, out_dir: Path, executor, progress: bool = True) -> RunResult:
    t0 = time.perf_counter()
    out_dir = Path(out_dir).resolve()
    cache.prepare()
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out_dir / ".volcap-write-test", "")
        (out_dir / ".volcap-write-test").unlink()
    except OSError as exc:
        raise DataError(f"output folder {out_dir} cannot be written: {exc.strerror or exc} (choose another with --out)") from None
    notes: list[str] = []
    items, slot = plan_graph(graph, cache, notes)
    by_key = {it.key: it for it in items}
    results: dict[str, dict] = {}
    to_run: list[WorkItem] = []
    run_keys, damaged = check_cached(graph, items, cache)
    for it in items:
        if it.key not in run_keys:
            results[it.key] = {"status": "cached", "seconds": 0.0}
            cache.touch(it.key)
        else:
            to_run.append(it)
    log_dir = out_dir / "logs"
    specs = {it.key: it.spec(str(log_dir / it.node / f"{'all' if it.frame is None else it.frame}.log")) for it in to_run}

    bar = None
    if progress and to_run:
        from tqdm import tqdm

        bar = tqdm(total=len(to_run), unit="item", file=sys.stderr, dynamic_ncols=True, disable=None,
                   desc=f"{graph.path.name}")

    def on_result(key, res):
        results[key] = res
        if res.get("corrupt"):  # an unreadable cached input: drop it so the next run recomputes it
            cache.evict(res["corrupt"])
        if bar is not None:
            it = by_key[key]
            bar.set_postfix_str(f"{it.label} {res['status']}", refresh=False)
            bar.update(1)

    if to_run:
        executor.run(to_run, specs, str(cache.root), on_result)
    if bar is not None:
        bar.close()
    for key, problem in damaged.items():  # say so: a recomputed result that was cached is worth a line
        if key in results:
            results[key]["warnings"] = [f"its cached result was damaged ({problem}): recomputed"] + list(results[key].get("warnings") or [])

    records, failures = [], []
    tables: dict[tuple[str, str], dict] = {}
    for (node, frame), key in slot.items():
        it = by_key[key]
        res = results.get(key, {"status": "skipped", "error": "not run", "seconds": 0.0})
        rec = {"node": node, "type": it.type_name, "frame": frame, "status": res["status"],
               "cache_hit": res["status"] == "cached", "seconds": round(res.get("seconds", 0.0), 4), "key": key,
               "cache_dir": str(cache.object_dir(key)) if res["status"] in ("done", "cached") else None,
               "log": specs[key]["log"] if key in specs else None, "published": []}
        if res.get("error"):
            rec["error"] = res["error"]
        if res.get("warnings"):
            rec["warnings"] = res["warnings"]
        if res["status"] in ("done", "cached"):
            try:
                rec["published"] = _publish(graph, cache, it, out_dir, node, frame, tables)
            except DataError as exc:  # a damaged cache entry: report it, drop it, the rerun recomputes it
                cache.evict(key)
                rec.update(status="failed", cache_dir=None, error=f"{exc}; the entry was removed, rerun to recompute it")
                failures.append(rec)
                records.append(rec)
                continue
            idx = _index_path(cache, graph, node, frame)
            atomic_write_text(idx, json.dumps({"key": key, "components": it.components}))
        if res["status"] == "failed":
            failures.append(rec)
        records.append(rec)
    summaries = _publish_tables(graph, tables, out_dir)
    result = RunResult(records, out_dir, time.perf_counter() - t0, failures, notes, summaries)
    doc = {"graph": str(graph.path), "overrides": graph.overrides, "frames": graph.frames, "cache": str(cache.root), "seconds": round(result.seconds, 3),
           "counts": result.counts(), "items": records}
    if notes:
        doc["warnings"] = notes
    atomic_write_text(out_dir / "run.json", json.dumps(doc, indent=1))
    return result


def _publish(graph: Graph, cache: Cache, it: WorkItem, out_dir: Path, node: str | None = None, frame=None,
             tables: dict | None = None) -> list[str]:
    """Copy the Files outputs of a publishing node into the output folder (atomically per file), and write its
    Table outputs as OUT/tables/NODE/FRAME.json (collected in ``tables`` for the CSVs and summaries)."""
    cls = graph.nodes[it.node].cls
    if not cls.publishes:
        return []
    from .types import Files, Table

    node = node or it.node
    n_tables = sum(issubclass(d.type, Table) for d in cls.outputs.values())
    written = []
    for port, decl in cls.outputs.items():
        if issubclass(decl.type, Table):
            table = cache.load(it.key, port, Table)
            if table is None:
                continue
            name = ("all" if frame is None else str(frame)) if n_tables == 1 else f"{port}_{'all' if frame is None else frame}"
            target = out_dir / "tables" / node / f"{name}.json"
            atomic_write_text(target, json.dumps(table, indent=1))
            written.append(str(target))
            if tables is not None:
                tables.setdefault((node, port), {})[frame] = table
            continue
        if not issubclass(decl.type, Files):
            continue
        files = cache.load(it.key, port, Files) or {}
        for rel, data in files.items():
            target = out_dir / rel
            if not (target.is_file() and target.stat().st_size == len(data) and target.read_bytes() == data):
                atomic_write_bytes(target, data)
            written.append(str(target))
    return written


def _scalar(v) -> bool:
    return isinstance(v, (int, float, str, bool)) or v is None


def table_rows(table: dict) -> dict:
    """A Table as CSV rows: key "" holds its scalar fields (one row), and every field that is a list of flat
    mappings (e.g. per view) becomes its own list of rows."""
    rows = {"": {k: v for k, v in table.items() if _scalar(v)}}
    for k, v in table.items():
        if isinstance(v, list) and v and all(isinstance(r, dict) and all(_scalar(x) for x in r.values()) for r in v):
            rows[k] = v
    return rows


def _csv_text(rows: list[dict]) -> str:
    import csv
    import io

    columns: list[str] = []
    for r in rows:
        columns += [k for k in r if k not in columns]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=columns, lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    return buf.getvalue()


def _publish_tables(graph: Graph, tables: dict, out_dir: Path) -> list[str]:
    """OUT/tables/NODE.csv (one row per frame: the scalar fields) and OUT/tables/NODE.FIELD.csv (one row per
    frame and entry of a list field); returns one summary line per node that declares ``summary`` keys."""
    lines = []
    for (node, port), by_frame in tables.items():
        cls = graph.nodes[node].cls
        stem = node if sum(1 for n, _ in tables if n == node) == 1 else f"{node}.{port}"
        frames = sorted(by_frame, key=lambda f: (f is not None, f if f is not None else 0))
        per_key: dict[str, list[dict]] = {}
        for f in frames:
            for k, rows in table_rows(by_frame[f]).items():
                frame_col = {"frame": "all" if f is None else f}
                per_key.setdefault(k, []).extend([{**frame_col, **rows}] if k == "" else [{**frame_col, **r} for r in rows])
        for k, rows in per_key.items():
            atomic_write_text(out_dir / "tables" / (f"{stem}.csv" if k == "" else f"{stem}.{k}.csv"), _csv_text(rows))
        parts = []
        for k in cls.summary:
            vals = [(f, by_frame[f].get(k)) for f in frames if isinstance(by_frame[f].get(k), (int, float))]
            if not vals:
                continue
            xs = [v for _, v in vals]
            text = f"{k} {sum(xs) / len(xs):.4g}"
            if len(xs) > 1:
                lo, hi = min(vals, key=lambda fv: fv[1]), max(vals, key=lambda fv: fv[1])
                text += f" (min {lo[1]:.4g} frame {lo[0]}, max {hi[1]:.4g} frame {hi[0]})"
            parts.append(text)
        if parts:
            n = len(frames)
            lines.append(f"{node} ({graph.nodes[node].type_name}): {n} frame{'s' if n != 1 else ''}, "
                         f"{'mean ' if n > 1 else ''}" + ", ".join(parts) + f"  [{out_dir / 'tables' / (stem + '.csv')}]")
    return lines
