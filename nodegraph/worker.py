"""Executes work units from their specs (in this process, a pool worker or a Dask worker).

A unit is a list of item specs in dependency order (nodegraph/plan.py: a frame's own items, or one item).
Each item takes its inputs from the values earlier items of the unit produced (in memory: a value may even
stay on the OpenCL device) or else from the cache, runs its node, checks the declared output types, and
writes the ports it keeps atomically into the cache. Never raises for a node's own failure: returns a result
dict per item instead, so one failing item cannot take a pool down (its dependents in the unit are skipped);
the traceback goes to the item's log file.
"""
from __future__ import annotations

import importlib
import logging
import time
import traceback
from pathlib import Path

from .cache import Cache
from .errors import DataError, NodeError, VolcapError
from .node import node_class


_STARTUP: list = []


def on_worker_start(fn):
    """Register ``fn()`` to run once in each worker process (pool or Dask) before its first item: node packages
    use it to warm up what every item needs (an OpenCL context, library thread counts). Returns ``fn``."""
    _STARTUP.append(fn)
    return fn


def start_worker():
    """Import the node packages (they register their start-up hooks) and run the hooks; a failing hook is
    left to the nodes that need it to report."""
    from .node import registry

    registry()
    for fn in _STARTUP:
        try:
            fn()
        except Exception:
            pass


class _Collector(logging.Handler):
    """Keeps the warnings a node logs, so the run summary and run.json can show them."""

    def __init__(self, out: list):
        super().__init__(logging.WARNING)
        self.out = out

    def emit(self, record):
        if len(self.out) < 20:
            self.out.append(record.getMessage())


def _resolve_type(ref: str):
    module, qual = ref.split(":")
    obj = importlib.import_module(module)
    for part in qual.split("."):
        obj = getattr(obj, part)
    return obj


class CorruptInput(VolcapError):
    def __init__(self, key: str, message: str):
        self.key = key
        super().__init__(message)


class Values:
    """The in-memory outputs of a unit's items, each dropped once its last reader in the unit has read it."""

    def __init__(self, readers: dict | None = None):
        self.values: dict[str, object] = {}
        self.left = dict(readers or {})   # "key/port" -> readers still to come

    def put(self, key: str, port: str, value):
        if self.left.get(f"{key}/{port}", 0) > 0:
            self.values[f"{key}/{port}"] = value

    def take(self, key: str, port: str):
        """(True, value) when the unit holds it, else (False, None)."""
        ref = f"{key}/{port}"
        if ref not in self.values:
            return False, None
        value = self.values[ref]
        self.left[ref] -= 1
        if self.left[ref] <= 0:
            del self.values[ref]
        return True, value


def _load_input(cache: Cache, spec: dict, port: str, ref: dict, memory: Values | None):
    if memory is not None:
        found, value = memory.take(ref["key"], ref["port"])
        if found:
            return value
    try:
        return cache.load(ref["key"], ref["port"], _resolve_type(ref["type"]))
    except DataError as exc:
        raise CorruptInput(ref["key"], f"input '{port}': {exc}; the entry was removed, rerun to recompute it") from None


def _input_keys(spec: dict) -> list[str]:
    keys = []
    for ref in spec["inputs"].values():
        for r in (ref if isinstance(ref, list) else [ref] if ref else []):
            keys.append(r["key"])
    return keys


def execute_unit(unit: dict, cache_root: str) -> dict:
    """Run a unit: {"items": [item spec, ...] in dependency order, "readers": {"key/port": n} (how many items of
    the unit read each in-memory value), "failed": {key: node} of items of other units that did not produce
    their outputs}. Returns {item key: result}; an item whose input failed is skipped, and so are its
    dependents, with the name of the node that failed first."""
    memory = Values(unit.get("readers"))
    bad = {k: f"upstream '{node}' failed" for k, node in (unit.get("failed") or {}).items()}
    results = {}
    for spec in unit["items"]:
        down = [k for k in _input_keys(spec) if k in bad]
        if down:
            results[spec["key"]] = {"status": "skipped", "error": bad[down[0]], "seconds": 0.0}
            bad[spec["key"]] = bad[down[0]]
            continue
        res = execute(spec, cache_root, memory)
        results[spec["key"]] = res
        if res["status"] != "done":
            bad[spec["key"]] = f"upstream '{spec['node']}' failed"
    return results


def execute(spec: dict, cache_root: str, memory: Values | None = None) -> dict:
    t0 = time.perf_counter()
    log = logging.getLogger(f"volcap.item.{spec['node']}")
    log.propagate = False
    log.setLevel(logging.INFO)
    handler = None
    if spec.get("log"):
        Path(spec["log"]).parent.mkdir(parents=True, exist_ok=True)
        handler = logging.FileHandler(spec["log"], mode="w")
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
        log.addHandler(handler)
    warnings: list[str] = []
    collector = _Collector(warnings)
    log.addHandler(collector)
    logging.getLogger("volcap").addHandler(collector)  # module loggers (volcap.raster, ...) propagate here
    where = f"node '{spec['node']}' ({spec['type']})" + ("" if spec["frame"] is None else f" frame {spec['frame']}")
    try:
        cache = Cache(cache_root)
        cls = node_class(spec["type"], spec["module"])
        kwargs = dict(spec["params"])
        for port, ref in spec["inputs"].items():
            if ref is None:
                kwargs[port] = None
            elif isinstance(ref, list):
                kwargs[port] = [_load_input(cache, spec, port, r, memory) for r in ref]
            else:
                kwargs[port] = _load_input(cache, spec, port, ref, memory)
            if kwargs[port] is None and ref is not None and not cls.inputs[port].optional:
                raise NodeError(f"input '{port}' received nothing: its source produced no value for this frame")
        node = cls()
        node.frame = spec["frame"]
        node.frames = spec["frames"]
        node.log = log
        if cls.uses_frame:
            kwargs["frame"] = spec["frame"]
        log.info("running %s with params %s", where, spec["params"])
        out = node.run(**kwargs)
        if not isinstance(out, dict):
            raise NodeError(f"run() must return a dict of outputs, got {type(out).__name__}")
        missing = [p for p in cls.outputs if p not in out]
        extra = [p for p in out if p not in cls.outputs]
        if missing or extra:
            raise NodeError(f"run() returned outputs {sorted(out)}, declared {sorted(cls.outputs)}")
        outputs = {}
        for port, decl in cls.outputs.items():
            value = out[port]
            if value is None and not decl.optional:
                raise NodeError(f"output '{port}' is None but not declared optional")
            if value is not None:
                problem = decl.type.check(value)
                if problem:
                    raise NodeError(f"output '{port}': {problem}")
                value = decl.type.canonical(value)
            outputs[port] = (decl.type, value)
            if memory is not None:
                memory.put(spec["key"], port, value)
        seconds = time.perf_counter() - t0
        keep = set(spec.get("kept", cls.outputs)) | (cache.stored(spec["key"]) or set())
        if keep:  # the ports that must be kept (and those an earlier entry of this key held)
            cache.write(spec["key"], {p: v for p, v in outputs.items() if p in keep},
                        {"node": spec["node"], "type": spec["type"], "frame": spec["frame"],
                         "components": spec["components"], "seconds": seconds, "in_memory": sorted(set(outputs) - keep)})
        log.info("done in %.3f s (kept: %s)", seconds, ", ".join(sorted(keep)) or "nothing")
        return {"status": "done", "seconds": time.perf_counter() - t0, "warnings": warnings}
    except CorruptInput as exc:
        log.error("%s failed: %s", where, exc)
        return {"status": "failed", "error": str(exc), "corrupt": exc.key, "seconds": time.perf_counter() - t0}
    except VolcapError as exc:
        log.error("%s failed: %s", where, exc)
        return {"status": "failed", "error": str(exc), "seconds": time.perf_counter() - t0}
    except Exception as exc:
        log.error("%s crashed:\n%s", where, traceback.format_exc())
        return {"status": "failed", "error": f"{type(exc).__name__}: {exc}", "seconds": time.perf_counter() - t0}
    finally:
        log.removeHandler(collector)
        logging.getLogger("volcap").removeHandler(collector)
        if handler:
            log.removeHandler(handler)
            handler.close()
