"""Running a graph: plan -> decide what is up to date -> execute the rest in units -> publish -> run.json.

What runs (``to_run``): walking the items from the last to the first, an item runs when a port it keeps is
missing from the cache, or when an item that runs reads a value of it that lives only in memory (a unit
recomputes its intermediate values from the nearest kept ones). Everything else is up to date.

run.json (in the output folder) records, per node and frame: status (done / cached / failed / skipped),
cache_hit, wall seconds, key, the cache folder of its kept outputs, which ports were kept and which lived only
in memory, the files it published, its log.
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

    @property
    def ok(self) -> bool:
        return not self.failures

    def counts(self) -> dict:
        c: dict[str, int] = {}
        for r in self.records:
            c[r["status"]] = c.get(r["status"], 0) + 1
        return c


def plan_graph(graph: Graph, cache: Cache):
    from . import fingerprint

    if cache.root.is_dir():
        fingerprint.remember_in(cache.root / "imports.json")
    return make_plan(graph, FileHasher(cache.root / "filehash.json"))


@dataclass
class Unit:
    """What one worker call runs: a frame's items (or one item) that are not up to date, in dependency order."""

    key: str
    label: str
    items: list
    deps: list[str]
    spec: dict


def _refs(it: WorkItem):
    for ref in it.inputs.values():
        for r in (ref if isinstance(ref, list) else [ref] if ref else []):
            yield r


def to_run(items: list[WorkItem], cache: Cache) -> tuple[dict[str, str], dict[str, set | None]]:
    """(why each item that must run runs, by key; stored ports per key) — see the module docstring."""
    stored = {it.key: cache.stored(it.key) for it in items}
    kept = {it.key: set(it.kept) for it in items}
    label = {it.key: it.label for it in items}
    must: dict[str, str] = {}
    for it in reversed(items):  # items are in dependency order: readers come after their sources
        have = stored[it.key] or set()
        if it.key not in must and not kept[it.key] <= have:
            must[it.key] = "not in the cache" if stored[it.key] is None else \
                f"kept output {', '.join(sorted(kept[it.key] - have))} not in the cache"
        if it.key in must:
            for r in _refs(it):
                if r["key"] in must:
                    continue
                if r["port"] not in kept.get(r["key"], ()):
                    must[r["key"]] = f"its {r['port']} lives in memory and {label[it.key]} runs"
                elif r["port"] not in (stored.get(r["key"]) or set()):
                    must[r["key"]] = f"kept output {r['port']} not in the cache"
    return must, stored


def make_units(items: list[WorkItem], must: set[str], specs: dict[str, dict]) -> list[Unit]:
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
            for r in _refs(it):
                if r["key"] in keys:
                    readers[f"{r['key']}/{r['port']}"] = readers.get(f"{r['key']}/{r['port']}", 0) + 1
                elif r["key"] in unit_of and unit_of[r["key"]] not in deps:
                    deps.append(unit_of[r["key"]])
        label = name if name.startswith("frame:") else its[0].label
        units.append(Unit(name, label, its, deps, {"items": [specs[it.key] for it in its], "readers": readers}))
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


def explain(graph: Graph, cache: Cache) -> list[dict]:
    """Per work item: up to date or to run, which of its outputs are kept in the cache, and which parts of its
    key differ from the last run of the same node and frame of this graph file."""
    items, slot = plan_graph(graph, cache)
    must, stored = to_run(items, cache)
    by_key = {it.key: it for it in items}
    index = _read_index(cache, graph)
    rows = []
    for (node, frame), key in slot.items():
        it = by_key[key]
        row = {"node": node, "frame": frame, "key": key, "cached": key not in must, "changed": [], "kept": list(it.kept),
               "in_memory": [p for p in graph.nodes[node].cls.outputs if p not in it.kept]}
        if not row["cached"]:
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
    items, slot = plan_graph(graph, cache)
    by_key = {it.key: it for it in items}
    must, stored = to_run(items, cache)
    results: dict[str, dict] = {}
    for it in items:
        if it.key not in must:
            results[it.key] = {"status": "cached", "seconds": 0.0}
            if stored[it.key] is not None:
                cache.touch(it.key)
    log_dir = out_dir / "logs"
    specs = {it.key: it.spec(str(log_dir / it.node / f"{'all' if it.frame is None else it.frame}.log"))
             for it in items if it.key in must}
    units = make_units(items, must, specs)

    bar = None
    if progress and must:
        from tqdm import tqdm

        bar = tqdm(total=len(must), unit="item", file=sys.stderr, dynamic_ncols=True, disable=None,
                   desc=f"{graph.path.name}")

    def on_result(key, res):
        results[key] = res
        if res.get("corrupt"):  # an unreadable cached input: drop it so the next run recomputes it
            cache.evict(res["corrupt"])
        if bar is not None:
            it = by_key[key]
            bar.set_postfix_str(f"{it.label} {res['status']}", refresh=False)
            bar.update(1)

    if units:
        executor.run(units, str(cache.root), on_result)
    if bar is not None:
        bar.close()

    records, failures = [], []
    index = _read_index(cache, graph) or {}
    published = _Published(out_dir)
    for (node, frame), key in slot.items():
        it = by_key[key]
        res = results.get(key, {"status": "skipped", "error": "not run", "seconds": 0.0})
        rec = {"node": node, "type": it.type_name, "frame": frame, "status": res["status"],
               "cache_hit": res["status"] == "cached", "seconds": round(res.get("seconds", 0.0), 4), "key": key,
               "cache_dir": str(cache.object_dir(key)) if cache.has(key) else None,
               "log": specs[key]["log"] if key in specs else None, "published": [], "kept": list(it.kept),
               "in_memory": [p for p in graph.nodes[node].cls.outputs if p not in it.kept]}
        if res.get("error"):
            rec["error"] = res["error"]
        if res.get("warnings"):
            rec["warnings"] = res["warnings"]
        if res["status"] in ("done", "cached"):
            try:
                rec["published"] = _publish(graph, cache, it, out_dir, published)
            except DataError as exc:  # a damaged cache entry: report it, drop it, the rerun recomputes it
                cache.evict(key)
                rec.update(status="failed", cache_dir=None, error=f"{exc}; the entry was removed, rerun to recompute it")
                failures.append(rec)
                records.append(rec)
                continue
            index[f"{node}@{'all' if frame is None else frame}"] = {"key": key, "components": it.components}
        if res["status"] == "failed":
            failures.append(rec)
        records.append(rec)
    atomic_write_text(_index_path(cache, graph), json.dumps(index))
    published.save()
    result = RunResult(records, out_dir, time.perf_counter() - t0, failures)
    doc = {"graph": str(graph.path), "overrides": graph.overrides, "frames": graph.frames, "cache": str(cache.root), "seconds": round(result.seconds, 3),
           "counts": result.counts(), "items": records}
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


def _publish(graph: Graph, cache: Cache, it: WorkItem, out_dir: Path, published: _Published) -> list[str]:
    """Copy the Files outputs of a publishing node into the output folder (atomically per file)."""
    cls = graph.nodes[it.node].cls
    if not cls.publishes:
        return []
    from .types import Files

    written = []
    for port, decl in cls.outputs.items():
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
