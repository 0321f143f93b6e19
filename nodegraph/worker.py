"""Executes one work item from its spec (in this process, a pool worker or a Dask worker).

Loads the inputs from the cache, runs the node, checks the declared output types, writes the outputs
atomically into the cache. Never raises for a node's own failure: returns a result dict instead, so one
failing item cannot take a pool down; the traceback goes to the item's log file.
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


def _load_input(cache: Cache, spec: dict, port: str, ref: dict):
    try:
        return cache.load(ref["key"], ref["port"], _resolve_type(ref["type"]))
    except DataError as exc:
        raise CorruptInput(ref["key"], f"input '{port}': {exc}; the entry was removed, rerun to recompute it") from None


def execute(spec: dict, cache_root: str) -> dict:
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
                kwargs[port] = [_load_input(cache, spec, port, r) for r in ref]
            else:
                kwargs[port] = _load_input(cache, spec, port, ref)
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
            outputs[port] = (decl.type, value)
        seconds = time.perf_counter() - t0
        cache.write(spec["key"], outputs, {"node": spec["node"], "type": spec["type"], "frame": spec["frame"],
                                           "components": spec["components"], "seconds": seconds})
        log.info("done in %.3f s", seconds)
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
