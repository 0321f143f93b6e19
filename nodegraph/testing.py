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
        if roundtrip:
            with tempfile.TemporaryDirectory() as d:
                o.type.save(out[name], Path(d))
                out[name] = o.type.load(Path(d))
    return out
