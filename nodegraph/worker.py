"""Executes work units from their specs (in this process, a pool worker or a Dask worker).

A unit is a list of item specs in dependency order (records.UnitSpec; what a unit is and when an item runs:
the contract in nodegraph/plan.py's docstring).
Each item takes its inputs from the values earlier items of the unit produced (in memory: a value may even
stay on the OpenCL device) or else from the cache, runs its node (``call_node``: run(), then the declared
outputs and their types checked), and writes the ports it keeps atomically into the cache (``keep``). Never
raises for a node's own failure: returns a Result per item instead, so one failing item cannot take a pool
down (its dependents in the unit are skipped); the traceback goes to the item's log file.
``nodegraph.testing.run_node`` runs a node through the same ``call_node`` and ``keep``.
"""
from __future__ import annotations

import copy
import gc
import logging
import os
import time
import traceback
from pathlib import Path

import numpy as np

from .cache import Cache
from .errors import DataError, NodeError, VolcapError
from .node import node_class
from .records import ItemSpec, Join, Ref, Result, UnitSpec, refs, resolve_type, type_name


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


class CorruptInput(VolcapError):
    def __init__(self, key: str, message: str):
        self.key = key
        super().__init__(message)


class Values:
    """The in-memory outputs of a unit's items, each dropped once its last reader in the unit has read it; also
    a cached input that several of the unit's items read (a frame's cameras, read by the key and the hull), loaded
    once and kept pristine: each reader but the last gets its own copy (``private_copy``), as if it had loaded
    it from the cache itself, so a reader that edits its input cannot change another's."""

    def __init__(self, readers: dict | None = None):
        self.values: dict[str, object] = {}
        self.left = dict(readers or {})   # Ref.name -> readers still to come
        self.loaded: set[str] = set()     # the names in ``values`` that came from the cache

    def put(self, ref: Ref, value):
        if self.left.get(ref.name, 0) > 0:
            self.values[ref.name] = value

    def take(self, ref: Ref):
        """(True, value) when the unit holds it, else (False, None)."""
        if ref.name not in self.values:
            return False, None
        value = self.values[ref.name]
        self.left[ref.name] -= 1
        if self.left[ref.name] <= 0:
            del self.values[ref.name]
            self.loaded.discard(ref.name)
        elif ref.name in self.loaded:
            try:
                value = private_copy(value)
            except Exception:   # not copyable: this reader loads its own from the cache
                self.left[ref.name] += 1
                return False, None
        return True, value

    def share(self, ref: Ref, value):
        """``value`` just loaded from the cache for one reader: kept for the unit's later readers of it when there
        are any. Returns what this reader gets (its own copy when others are to come)."""
        if self.left.get(ref.name, 0) <= 1 or ref.name in self.values:
            return value
        try:
            mine = private_copy(value)
        except Exception:   # not copyable: every reader loads its own
            return value
        self.left[ref.name] -= 1
        self.values[ref.name] = value
        self.loaded.add(ref.name)
        return mine


def private_copy(value):
    """A deep copy of a value loaded from the cache, sharing its read-only arrays (memory-mapped images and
    masks: nobody can edit them, and copying 24 HD images would cost more than loading them)."""
    memo: dict = {}
    _seed_read_only(value, memo, 0)
    return copy.deepcopy(value, memo)


def _seed_read_only(x, memo: dict, depth: int):
    if isinstance(x, np.ndarray):
        if not x.flags.writeable:
            memo[id(x)] = x
        return
    if depth > 6 or isinstance(x, (str, bytes, int, float, bool, type(None))):
        return
    if isinstance(x, dict):
        items = x.values()
    elif isinstance(x, (list, tuple)):
        items = x
    elif hasattr(x, "__dict__"):
        items = vars(x).values()
    else:
        return
    for y in items:
        _seed_read_only(y, memo, depth + 1)


def _load_input(cache: Cache, port: str, ref: Ref, memory: Values | None):
    if memory is not None:
        found, value = memory.take(ref)
        if found:
            return value
    try:
        value = cache.load(ref.key, ref.port, resolve_type(ref.type))
    except DataError as exc:
        raise CorruptInput(ref.key, f"input '{port}': {exc}; the entry was removed, rerun to recompute it") from None
    # more readers of this cached value in the unit: they get it from memory
    return value if memory is None else memory.share(ref, value)


def _readers(unit: UnitSpec) -> dict[str, int]:
    """Ref.name -> how many of the unit's items read it: the unit's own values (``unit.readers``) and the cached
    values read by more than one of its items."""
    outside: dict[str, int] = {}
    for spec in unit.items:
        for r in refs(spec.inputs):
            if r.name not in unit.readers:
                outside[r.name] = outside.get(r.name, 0) + 1
    return {**{k: n for k, n in outside.items() if n > 1}, **unit.readers}


def execute_unit(unit: UnitSpec, cache_root: str) -> dict[str, Result]:
    """Run a unit (its items in dependency order; see records.UnitSpec). Returns {item key: Result}; an item
    whose input failed is skipped, and so are its dependents, with the name of the node that failed first."""
    memory = Values(_readers(unit))
    cache = Cache(cache_root)   # one per unit: what it learnt of an entry (meta.json, verified) serves every item
    bad = {k: f"upstream '{node}' failed" for k, node in unit.failed.items()}
    results = {}
    for spec in unit.items:
        down = [k for k in spec.input_keys() if k in bad]
        if down:
            results[spec.key] = Result("skipped", error=bad[down[0]], node=spec.node)
            bad[spec.key] = bad[down[0]]
            continue
        res = execute(spec, cache_root, memory, cache)
        results[spec.key] = res
        if res.status != "done":
            bad[spec.key] = f"upstream '{spec.node}' failed"
    del memory
    _settle()
    return results


_SETTLED = []


def _settle():
    """After a process's first unit (its imports done, its kernels built): one full garbage collection, then the
    objects left (modules, classes, programs: some 10^5) are frozen out of the collector's sight. Each later
    full collection otherwise walked them all: 40-90 ms, three times in a 20-frame key -> hull -> mc run, the last
    at exit. Frozen objects are still freed by reference counting; only a reference cycle among them that
    becomes garbage later is never collected (bounded by what was alive here, the unit's own values dropped
    first: ``memory`` is gone, the collection runs before the freeze)."""
    if not _SETTLED:
        _SETTLED.append(True)
        gc.collect()
        gc.freeze()


def call_node(cls, inputs: dict, params: dict, *, frame: int | None, frames: list[int], log: logging.Logger,
              progress=None) -> dict:
    """Run node class ``cls`` on input values and params (as run() receives them) and check what it returns:
    a dict with exactly the declared outputs, None only where declared optional, each value passing its type's
    check. Returns port -> (DataType, value in its type's canonical form: as the cache gives it back); raises
    NodeError (or what run() raised)."""
    node = cls()
    node.frame = frame
    node.frames = frames
    node.log = log
    node._progress = progress
    kwargs = {**params, **inputs}
    if cls.uses_frame:
        kwargs["frame"] = frame
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
            value = decl.type.canonical(value)   # what a reader gets from the cache, also from memory
        outputs[port] = (decl.type, value)
    return outputs


def keep(cache: Cache, spec: ItemSpec, outputs: dict, seconds: float, phases: dict | None = None) -> set[str]:
    """Write the ports ``spec`` keeps (and those an earlier entry of its key held) into the cache, atomically.
    Returns the ports written. ``phases`` gets the seconds of making the kept values that a node produces lazily
    ("make") and of writing them ("write")."""
    kept = set(spec.kept) | (cache.stored(spec.key) or set())
    t = time.perf_counter()
    if kept:
        for p in kept:
            made = getattr(outputs.get(p, (None, None))[1], "materialise", None)
            if callable(made):
                made()
    t1 = time.perf_counter()
    if kept:
        cache.write(spec.key, {p: v for p, v in outputs.items() if p in kept},
                    {"node": spec.node, "type": spec.type, "frame": spec.frame, "components": spec.components,
                     "seconds": seconds, "in_memory": sorted(set(outputs) - kept)})
    if phases is not None:
        phases.update(make=t1 - t, write=time.perf_counter() - t1)
    return kept


# In-process runs (one job): the caller's callback(key, done, total, what), called straight from Node.progress
PROGRESS_HOOK = None
PROGRESS_EVERY_S = 0.25


def progress_path(log_path: str | None) -> Path | None:
    """Where an item running in another process says how far it has come (beside its log): "done total what"."""
    return None if not log_path else Path(log_path + ".progress")


def read_progress(log_path: str | None) -> tuple[int, int, str] | None:
    path = progress_path(log_path)
    try:
        done, total, what = path.read_text().split(" ", 2)
        return int(done), int(total), what
    except (AttributeError, OSError, ValueError):
        return None


def _progress_writer(spec: ItemSpec):
    """Node.progress for this item: the in-process hook, or a small file the pool's parent polls (written at most
    every PROGRESS_EVERY_S, and at the end; atomically: the reader never sees half a line)."""
    path = progress_path(spec.log)
    last = [0.0]

    def write(done: int, total: int, what: str):
        if PROGRESS_HOOK is not None:
            PROGRESS_HOOK(spec.key, done, total, what)
            return
        now = time.perf_counter()
        if path is None or (now - last[0] < PROGRESS_EVERY_S and done < total):
            return
        last[0] = now
        try:
            tmp = path.with_suffix(".tmp")
            tmp.write_text(f"{done} {total} {what}")
            os.replace(tmp, path)
        except OSError:
            pass   # progress is a courtesy: never a failure

    return write


def execute(spec: ItemSpec, cache_root: str, memory: Values | None = None, cache: Cache | None = None) -> Result:
    t0 = time.perf_counter()
    log = logging.getLogger(f"volcap.item.{spec.node}")
    log.propagate = False
    log.setLevel(logging.INFO)
    handler = None
    if spec.log:
        path = Path(spec.log)
        path.parent.mkdir(parents=True, exist_ok=True)
        # a new file, not the last run's truncated: ext4 flushes a truncated-and-rewritten file when it is closed
        # (auto_da_alloc), 0.2 ms per item on an idle machine and about 2 ms under load, three times a frame
        try:
            path.unlink(missing_ok=True)
        except OSError:   # e.g. a folder the file may be rewritten in but not removed from: truncate it
            pass
        handler = logging.FileHandler(spec.log, mode="w")
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
        log.addHandler(handler)
    warnings: list[str] = []
    collector = _Collector(warnings)
    log.addHandler(collector)
    logging.getLogger("volcap").addHandler(collector)  # module loggers (volcap.raster, ...) propagate here
    where = spec.where

    def failed(error: str, corrupt: str | None = None) -> Result:
        return Result("failed", time.perf_counter() - t0, error, corrupt=corrupt, node=spec.node)

    try:
        cache = cache if cache is not None else Cache(cache_root)
        cls = node_class(spec.type, spec.module)
        inputs = {}
        for port, ref in spec.inputs.items():
            if ref is None:
                inputs[port] = None
            elif isinstance(ref, list):
                inputs[port] = [_load_input(cache, port, r, memory) for r in ref]
            elif isinstance(ref, Join):   # a windowed sequence node's windows, frames in order
                inputs[port] = resolve_type(ref.type).join([_load_input(cache, port, r, memory) for r in ref.refs])
            else:
                inputs[port] = _load_input(cache, port, ref, memory)
            if inputs[port] is None and ref is not None and not cls.inputs[port].optional:
                raise NodeError(f"input '{port}' received nothing: its source produced no value for this frame")
        log.info("running %s with params %s", where, spec.params)
        phases = {"load": time.perf_counter() - t0}
        outputs = call_node(cls, inputs, spec.params, frame=spec.frame, frames=spec.frames, log=log,
                            progress=_progress_writer(spec))
        phases["run"] = time.perf_counter() - t0 - phases["load"]
        if memory is not None:
            for port, (dtype, value) in outputs.items():
                memory.put(Ref(spec.key, port, type_name(dtype)), value)
        kept = keep(cache, spec, outputs, time.perf_counter() - t0, phases)
        log.info("done in %.3f s (kept: %s)", time.perf_counter() - t0, ", ".join(sorted(kept)) or "nothing")
        return Result("done", time.perf_counter() - t0, warnings=warnings, node=spec.node, phases=phases)
    except CorruptInput as exc:
        log.error("%s failed: %s", where, exc)
        return failed(str(exc), exc.key)
    except VolcapError as exc:
        log.error("%s failed: %s", where, exc)
        return failed(str(exc))
    except Exception as exc:
        log.error("%s crashed:\n%s", where, traceback.format_exc())
        return failed(f"{type(exc).__name__}: {exc}")
    finally:
        log.removeHandler(collector)
        logging.getLogger("volcap").removeHandler(collector)
        if handler:
            log.removeHandler(handler)
            handler.close()
        done_path = progress_path(spec.log)
        if done_path is not None:
            done_path.unlink(missing_ok=True)   # finished: nothing more to show
