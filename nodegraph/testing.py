"""Helpers for node tests: run one node directly, through the code the scheduler runs it with.

``run_node`` takes params as a graph file gives them (coerced and checked by ``graphfile.coerce_param``, input
paths resolved against the current folder, defaults as declared), calls ``worker.call_node`` (run(), then the
declared outputs and their types checked) and, with ``roundtrip``, stores every output with ``worker.keep``
in a temporary cache and loads it back with ``Cache.load``, exactly as a value read by another unit travels."""
from __future__ import annotations

import tempfile
from pathlib import Path

from .cache import Cache
from .errors import NodeError
from .graphfile import coerce_param
from .node import REQUIRED, node_class
from .records import ItemSpec, refs
from . import worker


def run_node(type_name: str, inputs: dict | None = None, params: dict | None = None, *, frame: int = 0,
             frames: list[int] | None = None, roundtrip: bool = False) -> dict:
    """Run node ``type_name`` on in-memory inputs (a port not given receives None, as an unconnected one).
    Params not given take their defaults. Returns port -> value; raises what the node or the checks raise."""
    cls = node_class(type_name)
    given = dict(params or {})
    unknown = set(given) - set(cls.params)
    if unknown:
        raise NodeError(f"{type_name}: unknown params {sorted(unknown)}")
    kw = {}
    for name, p in cls.params.items():
        if name not in given:
            if p.default is REQUIRED:
                raise NodeError(f"{type_name}: param '{name}' is required")
            kw[name] = p.default
            continue
        try:
            kw[name] = coerce_param(p, given[name], Path.cwd())
        except ValueError as exc:   # a graph file's parameter error: the value never reaches the node
            raise ValueError(f"{type_name}: parameter '{name}' {exc}") from None
    values = {name: (inputs or {}).get(name) for name in cls.inputs}
    outputs = worker.call_node(cls, values, kw, frame=frame, frames=frames or [frame], log=cls.log)
    if not roundtrip:
        return {port: value for port, (_, value) in outputs.items()}
    with tempfile.TemporaryDirectory() as d:
        cache = Cache(d)
        spec = ItemSpec("test", type_name, cls.__module__, frame, frames or [frame], kw, {}, "roundtrip", {},
                        kept=list(cls.outputs))
        worker.keep(cache, spec, outputs, 0.0)
        return {port: cache.load(spec.key, port, dtype) for port, (dtype, _) in outputs.items()}


def unit_purity(graph, root: Path) -> list[str]:
    """Check "same key = same result" across units (Gaffer's assertHashesValid in spirit): run ``graph`` as the
    scheduler does (a frame's items together in one unit, values handed over in memory) with every output kept,
    then run every item alone (``worker.execute`` without the unit's memory: inputs read back from a second
    cache, in dependency order) and compare the stored files' hashes port by port for every item that shares a
    unit. Returns one line per output that differs, naming the first item in dependency order (its inputs were
    equal, so it is impure)."""
    from .executors import LocalExecutor
    from .run import plan_graph, run_graph

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
        res = worker.execute(it.spec(None), str(alone.root))
        if res.status != "done":
            raise NodeError(f"{it.label} alone: {res.error}")
        if sizes[it.unit] == 1:  # ran alone both times (a sequence node's wall times may differ: not impure)
            continue
        a, b = together.meta(it.key), alone.meta(it.key)
        for port in sorted(a["files"]):
            fa, fb = a["files"][port] or [], b["files"].get(port) or []
            if [a["hashes"][f] for f in fa] != [b["hashes"][f] for f in fb]:
                upstream = [r.key for r in refs(it.inputs) if r.key in differs]
                if not upstream:
                    problems.append(f"{it.label} ({it.type_name}) output '{port}': differs when the node runs alone "
                                    f"from its cached inputs")
                differs.add(it.key)
    return problems
