"""Helpers for node tests: run one node directly, with its declared types checked and (optionally) its
outputs round-tripped through their on-disk form, exactly as the scheduler would."""
from __future__ import annotations

import tempfile
from pathlib import Path

from .errors import NodeError
from .node import REQUIRED, node_class


def run_node(type_name: str, inputs: dict | None = None, params: dict | None = None, *, frame: int = 0,
             frames: list[int] | None = None, roundtrip: bool = False) -> dict:
    """Run node ``type_name`` on in-memory inputs. Params not given take their defaults."""
    cls = node_class(type_name)
    given = dict(params or {})
    unknown = set(given) - set(cls.params)
    if unknown:
        raise NodeError(f"{type_name}: unknown params {sorted(unknown)}")
    kw = {}
    for name, p in cls.params.items():
        v = given.get(name, p.default)
        if v is REQUIRED:
            raise NodeError(f"{type_name}: param '{name}' is required")
        kw[name] = p.coerce(v)
    for name, inp in cls.inputs.items():
        kw[name] = (inputs or {}).get(name)
    node = cls()
    node.frame = frame
    node.frames = frames or [frame]
    if cls.uses_frame:
        kw["frame"] = frame
    out = node.run(**kw)
    for name, o in cls.outputs.items():
        if name not in out:
            raise NodeError(f"{type_name}: run() did not return output '{name}'")
        if out[name] is None:
            if not o.optional:
                raise NodeError(f"{type_name}: output '{name}' is None but not declared optional")
            continue
        problem = o.type.check(out[name])
        if problem:
            raise NodeError(f"{type_name}: output '{name}': {problem}")
        out[name] = o.type.canonical(out[name])
        if roundtrip:
            with tempfile.TemporaryDirectory() as d:
                o.type.save(out[name], Path(d))
                out[name] = o.type.load(Path(d))
    return out


def unit_purity(graph, root: Path) -> list[str]:
    """Check "same key = same result" across units (Gaffer's assertHashesValid in spirit): run ``graph`` as the
    scheduler does (a frame's items together in one unit, values handed over in memory) with every output kept,
    then run every item alone (``worker.execute`` without the unit's memory: inputs read back from a second
    cache, in dependency order) and compare the stored files' hashes port by port for every item that shares a
    unit. Returns one line per
    output that differs, naming the first item in dependency order (its inputs were equal, so it is impure)."""
    from .cache import Cache
    from .executors import LocalExecutor
    from .run import plan_graph, run_graph
    from .worker import execute

    root = Path(root)
    graph.keep_all()
    together = Cache(root / "units")
    result = run_graph(graph, together, root / "out", LocalExecutor(1), progress=False)
    if not result.ok:
        raise NodeError(f"{graph.path.name}: the run failed, no purity to check")
    alone = Cache(root / "alone")
    alone.prepare()
    items, _ = plan_graph(graph, alone)
    problems: list[str] = []
    differs: set[str] = set()
    sizes: dict[str, int] = {}
    for it in items:
        sizes[it.unit] = sizes.get(it.unit, 0) + 1
    for it in items:
        res = execute(it.spec(None), str(alone.root))
        if res["status"] != "done":
            raise NodeError(f"{it.label} alone: {res.get('error')}")
        if sizes[it.unit] == 1:  # ran alone both times (a sequence node's wall times may differ: not impure)
            continue
        a, b = together.meta(it.key), alone.meta(it.key)
        for port in sorted(a["files"]):
            fa, fb = a["files"][port] or [], b["files"].get(port) or []
            if [a["hashes"][f] for f in fa] != [b["hashes"][f] for f in fb]:
                upstream = [r["key"] for r in _refs(it.inputs) if r["key"] in differs]
                if not upstream:
                    problems.append(f"{it.label} ({it.type_name}) output '{port}': differs when the node runs alone "
                                    f"from its cached inputs")
                differs.add(it.key)
    return problems


def _refs(inputs: dict):
    for ref in inputs.values():
        yield from (ref if isinstance(ref, list) else [ref] if ref else [])
