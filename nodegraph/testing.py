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
from .records import ItemSpec
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
