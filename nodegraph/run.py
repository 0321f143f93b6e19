"""Running a graph: plan -> decide what is up to date -> execute the rest in units -> publish -> run.json.

What runs and why (``to_run``, ``verify_reads``, ``make_units``) is the contract in nodegraph/plan.py's
docstring, with a worked example.

run.json (in the output folder) records, per node and frame: status (done / cached / failed / skipped),
cache_hit, wall seconds, key, the cache folder of its kept outputs, which ports were kept and which lived only
in memory, the files it published, its log.
"""
from __future__ import annotations

import inspect
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
from .records import Result, UnitSpec, refs


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
    from . import fingerprint

    if cache.root.is_dir():
        fingerprint.remember_in(cache.root / "imports.json")
    hasher = FileHasher(cache.root / "filehash.json", exclude=[cache.root])
    planned = make_plan(graph, hasher)
    for folder, names in hasher.skipped.items():
        if notes is not None:
            shown = ", ".join(names[:5]) + (f" and {len(names) - 5} more" if len(names) > 5 else "")
            notes.append(f"input folder {folder}: {len(names)} entries are not regular files (FIFO, socket or "
                         f"device) and were not read: {shown}")
    return planned


@dataclass
class Unit:
    """What one worker call runs: a frame's items (or one item) that are not up to date, in dependency order."""

    key: str
    label: str
    items: list
    deps: list[str]
    spec: UnitSpec


def to_run(items: list[WorkItem], cache: Cache, gone=()) -> tuple[dict[str, str], dict[str, set | None]]:
    """(why each item that must run runs, by key; stored ports per key) — see the module docstring. Entries in
    ``gone`` count as not stored (damaged ones that explain does not evict)."""
    stored = {it.key: None if it.key in gone else cache.stored(it.key) for it in items}
    kept = {it.key: set(it.kept) for it in items}
    label = {it.key: it.label for it in items}
    must: dict[str, str] = {}
    for it in reversed(items):  # items are in dependency order: readers come after their sources
        have = stored[it.key] or set()
        if it.key not in must and not kept[it.key] <= have:
            must[it.key] = "not in the cache" if stored[it.key] is None else \
                f"kept output {', '.join(sorted(kept[it.key] - have))} not in the cache"
        if it.key in must:
            for r in refs(it.inputs):
                if r.key in must:
                    continue
                if r.port not in kept.get(r.key, ()):
                    must[r.key] = f"its {r.port} lives in memory and {label[it.key]} runs"
                elif r.port not in (stored.get(r.key) or set()):
                    must[r.key] = f"kept output {r.port} not in the cache"
    return must, stored


def make_units(items: list[WorkItem], must: set[str], specs: dict) -> list[Unit]:
    """Group the items that must run into units (their ``unit`` from planning), with the units they read from."""
    by_unit: dict[str, list[WorkItem]] = {}
    for it in items:
        if it.key in must:
            by_unit.setdefault(it.unit, []).append(it)
    unit_of = {it.key: it.unit for its in by_unit.values() for it in its}
    units = []
    for name, its in by_unit.items():
        keys = {it.key for it in its}
        readers: dict[str, int] = {}
        deps = []
        for it in its:
            for r in refs(it.inputs):
                if r.key in keys:
                    readers[r.name] = readers.get(r.name, 0) + 1
                elif r.key in unit_of and unit_of[r.key] not in deps:
                    deps.append(unit_of[r.key])
        label = name if name.startswith("frame:") else its[0].label
        units.append(Unit(name, label, its, deps, UnitSpec([specs[it.key] for it in its], readers)))
    return units


def _index_path(cache: Cache, graph: Graph) -> Path:
    """The record of the last run of this graph file: per node@frame its key and key components (for explain)."""
    return cache.root / "index" / f"{digest(str(graph.path))[:16]}.json"


def _read_index(cache: Cache, graph: Graph) -> dict | None:
    """The graph's last run record ({} when there is none, None when it is unreadable)."""
    try:
        doc = json.loads(_index_path(cache, graph).read_text())
        return doc if isinstance(doc, dict) else None
    except FileNotFoundError:
        return {}
    except (OSError, ValueError):
        return None


def verify_reads(graph: Graph, items: list[WorkItem], cache: Cache, out_dir: Path | None = None,
                 evict: bool = True) -> tuple[set[str], dict, dict[str, str]]:
    """``to_run`` after checking the content of every cached entry the run will read: the entries holding inputs
    of items that run, and those of publishing nodes whose files are not already in ``out_dir`` as published
    (all of them when ``out_dir`` is None). A damaged entry (a file missing or not matching its recorded hash,
    a garbage meta.json) is evicted (``evict``, else only counted as gone) and its item runs; what it reads is
    checked in turn. Returns (must, stored, {key: problem})."""
    damaged: dict[str, str] = {}
    checked: set[str] = set()
    published = _Published(out_dir) if out_dir is not None else None
    while True:
        must, stored = to_run(items, cache, gone=() if evict else set(damaged))
        reads = {r.key for it in items if it.key in must for r in refs(it.inputs) if r.key not in must}
        for it in items:
            if it.key not in must and stored[it.key] is not None and graph.nodes[it.node].cls.publishes:
                if published is None or not _all_current(graph, cache, it, out_dir, published):
                    reads.add(it.key)
        fresh = [k for k in reads if k not in checked and stored.get(k) is not None]
        found = False
        for key in fresh:
            checked.add(key)
            problem = cache.verify(key)
            if problem:
                damaged[key] = problem
                found = True
                if evict:
                    cache.evict(key)
        if not found:
            return must, stored, damaged


def _all_current(graph: Graph, cache: Cache, it: WorkItem, out_dir: Path, published: "_Published") -> bool:
    """Whether every file a publishing item exports is in the output folder as it was published from this key
    (then its cache entry is not read); Table outputs are always read."""
    from .types import Files

    try:
        files = cache.meta(it.key)["files"]
    except DataError:
        return False
    for port, decl in graph.nodes[it.node].cls.outputs.items():
        if not issubclass(decl.type, Files):
            if port in files and files[port]:
                return False
            continue
        targets = [out_dir / Path(f).relative_to(Path(port) / "files") for f in files.get(port) or []]
        if not targets or not all(published.current(t, it.key) for t in targets):
            return False
    return True


def explain(graph: Graph, cache: Cache) -> list[dict]:
    """Per work item: up to date or to run, which of its outputs are kept in the cache, and which parts of its
    key differ from the last run of the same node and frame of this graph file (or that its cached result is
    damaged)."""
    items, slot = plan_graph(graph, cache)
    must, stored, damaged = verify_reads(graph, items, cache, evict=False)
    by_key = {it.key: it for it in items}
    index = _read_index(cache, graph)
    rows = []
    for (node, frame), key in slot.items():
        it = by_key[key]
        row = {"node": node, "frame": frame, **({"frames": [it.frames[0], it.frames[-1]]} if it.window else {}),
               "key": key, "cached": key not in must, "changed": [], "kept": list(it.kept),
               "in_memory": [p for p in graph.nodes[node].cls.outputs if p not in it.kept]}
        if key in damaged:
            row["changed"] = [f"(cached result damaged: {damaged[key]})"]
        elif not row["cached"]:
            label = f"{node}@{'all' if frame is None else frame}"
            try:
                if index is None:
                    raise ValueError
                if label not in index:
                    row["changed"] = [f"(no earlier run; {must[key]})"]
                else:
                    row["changed"] = _diff(index[label]["components"], it.components) or [f"(nothing: {must[key]})"]
            except (KeyError, TypeError, ValueError):
                row["changed"] = ["(earlier run record unreadable)"]
        rows.append(row)
    return rows


def _diff(old, new, prefix="") -> list[str]:
    """The key components that differ, as dotted paths; the environment's with old -> new (an upgrade says so)."""
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for k in sorted(set(old) | set(new)):
            out += _diff(old.get(k), new.get(k), f"{prefix}.{k}" if prefix else k)
        return out
    if old == new:
        return []
    return [f"{prefix} ({old} -> {new})" if prefix.startswith("environment") else prefix]


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
    must, stored, damaged = verify_reads(graph, items, cache, out_dir)
    results: dict[str, Result] = {}
    for it in items:
        if it.key not in must:
            results[it.key] = Result("cached", node=it.node)
            if stored[it.key] is not None:
                cache.touch(it.key)
    log_dir = out_dir / "logs"
    specs = {it.key: it.spec(str(log_dir / it.node / f"{it.tag}.log"))
             for it in items if it.key in must}
    units = make_units(items, must, specs)

    bar = None
    if progress and must:
        from tqdm import tqdm

        bar = tqdm(total=len(must), unit="item", file=sys.stderr, dynamic_ncols=True, disable=None,
                   desc=f"{graph.path.name}")

    def on_result(key: str, res: Result):
        results[key] = res
        if res.corrupt:  # an unreadable cached input: drop it so the next run recomputes it
            cache.evict(res.corrupt)
        if bar is not None:
            it = by_key[key]
            bar.set_postfix_str(f"{it.label} {res.status}", refresh=False)
            bar.update(1)

    def on_progress(key: str, done: int, total: int, what: str):
        it = by_key[key]
        bar.set_postfix_str(f"{it.label} {done}/{total} {what}".rstrip(), refresh=True)

    if units:
        if bar is not None and "on_progress" in inspect.signature(executor.run).parameters:
            executor.run(units, str(cache.root), on_result, on_progress=on_progress)
        else:
            executor.run(units, str(cache.root), on_result)
    if bar is not None:
        bar.close()
    if not any(r.status == "failed" for r in results.values()):
        for key in must:   # never a silent "skipped": an item nothing ran, with no failure upstream, is an engine fault
            if key not in results:
                results[key] = Result("failed", error="the scheduler never started it (its work unit waits on itself: "
                                                      "an engine bug)", node=by_key[key].node)
    for key, problem in damaged.items():  # say so: a recomputed result that was cached is worth a line
        if key in results:
            results[key].warnings = [f"its cached result was damaged ({problem}): recomputed"] + list(results[key].warnings)

    records, failures = [], []
    index = _read_index(cache, graph) or {}
    published = _Published(out_dir)
    tables: dict[tuple[str, str], dict] = {}
    for (node, frame), key in slot.items():
        it = by_key[key]
        res = results.get(key, Result("skipped", error="not run"))
        rec = {"node": node, "type": it.type_name, "frame": frame, **({"frames": [it.frames[0], it.frames[-1]]} if it.window else {}),
               "status": res.status,
               "cache_hit": res.status == "cached", "seconds": round(res.seconds, 4),
               **({"phases": {k: round(v, 4) for k, v in res.phases.items()}} if res.phases else {}), "key": key,
               "cache_dir": str(cache.object_dir(key)) if stored.get(key) is not None or (res.status == "done" and it.kept) else None,
               "log": specs[key].log if key in specs else None, "published": [], "kept": list(it.kept),
               "in_memory": [p for p in graph.nodes[node].cls.outputs if p not in it.kept]}
        if res.error:
            rec["error"] = res.error
        if res.warnings:
            rec["warnings"] = list(res.warnings)
        if res.status in ("done", "cached"):
            try:
                rec["published"] = _publish(graph, cache, it, out_dir, published, node, frame, tables)
            except DataError as exc:  # a damaged cache entry: report it, drop it, the rerun recomputes it
                cache.evict(key)
                rec.update(status="failed", cache_dir=None, error=f"{exc}; the entry was removed, rerun to recompute it")
                failures.append(rec)
                records.append(rec)
                continue
            index[f"{node}@{'all' if frame is None else frame}"] = {"key": key, "components": it.components}
        if res.status == "failed":
            failures.append(rec)
        records.append(rec)
    atomic_write_text(_index_path(cache, graph), json.dumps(index))
    published.save()
    summaries = _publish_tables(graph, tables, out_dir)
    result = RunResult(records, out_dir, time.perf_counter() - t0, failures, notes, summaries)
    doc = {"graph": str(graph.path), "overrides": graph.overrides, "frames": graph.frames, "cache": str(cache.root), "seconds": round(result.seconds, 3),
           "counts": result.counts(), "items": records}
    if notes:
        doc["warnings"] = notes
    atomic_write_text(out_dir / "run.json", json.dumps(doc, indent=1))
    return result


class _Published:
    """What the last runs published into an output folder (.volcap-published.json): per file the cache key it
    came from and the file's size and mtime after publishing. A file whose record matches is left alone
    without reading it; anything else (a new key, a file changed or removed by hand) is published again."""

    def __init__(self, out_dir: Path):
        self.path = out_dir / ".volcap-published.json"
        try:
            self.files = json.loads(self.path.read_text())
        except (OSError, ValueError):
            self.files = {}
        self.dirty = False

    def current(self, target: Path, key: str) -> bool:
        rec = self.files.get(str(target))
        if not rec or rec[0] != key:
            return False
        try:
            st = target.stat()
        except OSError:
            return False
        return [st.st_size, st.st_mtime_ns] == rec[1:]

    def record(self, target: Path, key: str):
        st = target.stat()
        self.files[str(target)] = [key, st.st_size, st.st_mtime_ns]
        self.dirty = True

    def save(self):
        if self.dirty:
            atomic_write_text(self.path, json.dumps(self.files))


def _publish(graph: Graph, cache: Cache, it: WorkItem, out_dir: Path, published: _Published, node: str | None = None,
             frame=None, tables: dict | None = None) -> list[str]:
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
            if not published.current(target, it.key):
                atomic_write_text(target, json.dumps(table, indent=1))
                published.record(target, it.key)
            written.append(str(target))
            if tables is not None:
                tables.setdefault((node, port), {})[frame] = table
            continue
        if not issubclass(decl.type, Files):
            continue
        names = (cache.meta(it.key).get("files") or {}).get(port) or []
        targets = [out_dir / Path(f).relative_to(Path(port) / "files") for f in names]
        if targets and all(published.current(t, it.key) for t in targets):
            written += [str(t) for t in targets]
            continue
        files = cache.load(it.key, port, Files) or {}
        for rel, data in files.items():
            target = out_dir / rel
            if not (target.is_file() and target.stat().st_size == len(data) and target.read_bytes() == data):
                atomic_write_bytes(target, data)
            published.record(target, it.key)
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
            target, text = out_dir / "tables" / (f"{stem}.csv" if k == "" else f"{stem}.{k}.csv"), _csv_text(rows)
            try:
                same = target.read_text() == text
            except (OSError, UnicodeDecodeError):
                same = False
            if not same:
                atomic_write_text(target, text)
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
