"""Planning and scheduling: a validated Graph -> work items with cache keys -> units -> results.

This docstring is the scheduler's contract; plan.py, run.py, executors.py, dask_executor.py and worker.py
follow it (the records they hand around are in records.py, the cache's layout in cache.py).

State, per work item (``WorkItem``)
    node, frame        one node run: (node, frame) for a per-frame node, (node, None) over all frames for a
                       sequence node (``frames`` lists them), or over one window of N consecutive frames for a
                       sequence node with the graph key ``window: N`` (``window`` true; the (node, frame) map
                       lists it under the window's first frame)
    params             what run() receives (input paths absolute; graphfile.coerce_param)
    inputs             port -> Ref(key, port, type) of the item producing it, a list of Refs (a sequence node
                       reading a per-frame one: one per frame), a Join of Refs (a sequence node reading several
                       windows of a windowed one: loaded and joined by the port type's ``join``), or None (not
                       connected); a per-frame node reading a windowed one reads the window holding its frame
    key                SHA-256 (first 32 hex digits) of ``components``:
                         schema          hashing.KEY_SCHEMA, the recipe's version
                         node, version   the node type and its class's ``version``
                         implementation  fingerprint.py: the source of the node's module and of what it imports
                                         within the project's packages, the data files beside them, its OpenCL
                                         sources and their headers
                         params          canonical params, an input path replaced by its content hash
                         inputs          per port the Ref.name "KEY/PORT" of its source(s)
                         frame           the frame number if the node ``uses_frame``, else None
                         frames          (sequence nodes) the frames it covers
                         environment     environment.py: library versions, the OpenCL device
                       Same key = same result. Two items with the same key (a per-frame node fed only
                       frame-independent data) are one item.
    deps               keys of the items producing its inputs
    unit               where it runs: "frame:N" (or "frame:N/L") for a frame's own items, else "item:KEY"
    kept               the output ports stored in the cache (the rest live only in memory)
A worker never sees a WorkItem: it gets ``ItemSpec``s (plain data: node type and module, params, Refs, key,
kept ports, log file), grouped in a ``UnitSpec``, and reports one ``Result`` per item (done / failed /
skipped; run.py adds cached). Specs pickle to a process pool or a Dask cluster; values never travel in them.

Units (``_assign_units``): the engine's smallest job
- A frame's own items (per-frame items whose key no other frame shares) form one unit: one worker runs them in
  dependency order and hands their values over in memory (``worker.Values``: a value, even one resident on the
  OpenCL device, is dropped after its last reader in the unit). Items after a sequence node form the frame's
  next unit, level L = sequence nodes on the longest path from a source ("frame:3/1"), since they wait for
  every frame's first unit. Every other item is a unit of its own: sequence items, and per-frame items several
  frames share.
- A port is kept (stored) when: its type is kept by default (small values: tables, cameras, boxes, files), its
  node publishes files, another unit reads it, nothing reads any output of its node (a result), its node class
  declares ``checkpoint = True``, or the graph lists it under the node's ``keep:``. Large intermediate values
  (images, masks, volumes, meshes) read only inside their unit live in memory. Which ports are kept never
  changes a key.

When an item runs (run.py ``to_run``, walking the items from the last to the first)
- when a port it keeps is missing from the cache ("not in the cache": a new key, i.e. something in its
  components changed, or an evicted entry);
- when an item that runs reads one of its values that lives only in memory (its unit recomputes it from the
  nearest kept values);
- an item whose input failed is skipped, never run; its dependents too. Everything else is up to date.
Before running, every cached entry the run will read is checked against its content hashes
(``verify_reads``): a damaged one is evicted and recomputed in the same run. Then ``make_units`` groups the
items that run, an executor runs each unit once the units it reads from have finished, and ``worker.execute``
runs each item: inputs from the unit's memory or the cache, ``call_node`` (run(), the declared outputs and
their types checked), ``keep`` (the kept ports written atomically under the key).

Worked example: 2 nodes x 2 frames
    frames: 0:2
    nodes:
      src:   {type: load, params: {path: data}}      # per frame, uses its frame; out: Big (not kept by default)
      scale: {type: scale, in: {x: src.out}}         # per frame; out: Big
``make_plan`` gives four items (K(...) is an item's key):
    src@0    components {node: load, params: {path: {content: H(data)}}, inputs: {}, frame: 0, ...}
    src@1    the same with frame 1                      -> a different key
    scale@0  {node: scale, inputs: {x: "K(src@0)/out"}, frame: None, ...}
    scale@1  {node: scale, inputs: {x: "K(src@1)/out"}, ...}  -> differs from scale@0 through its input
Units: frame:0 = [src@0, scale@0], frame:1 = [src@1, scale@1]. src.out is read only inside its unit: kept = []
(in memory, readers {"K(src@0)/out": 1}); scale.out is read by nobody: a result, kept = [out].
- First run: no entry exists; every item runs, the two units in parallel. A worker runs src@0, hands its out
  to scale@0 in memory, and stores only scale@0's out under K(scale@0).
- Second run: K(scale@0) and K(scale@1) hold their kept port: all four up to date (src keeps nothing, so
  nothing of it is missing), nothing runs.
- ``--set scale.factor=4``: scale's params change its keys, which are not in the cache: scale@0, scale@1 run,
  and since they read src.out from memory, src@0 and src@1 run again in their units ("its out lives in
  memory and scale@0 runs"). Had src.out been kept (a checkpoint, ``keep: [out]``), src would stay cached and
  its entry would be read instead.
- A file under data/ edited, a numpy upgrade, another OpenCL device or an edit of the load node's module:
  src's components change, so its keys do, so scale's inputs and keys do: everything reruns, and ``explain``
  names the component that moved (``params.path``, ``environment.libraries.numpy (2.4 -> 2.5)``, ...).
- Had ``load`` not used its frame and read no frame-dependent input, src@0 and src@1 would have one key: one
  item in a unit of its own ("item:K"), its out kept (read by the two frame units).
"""
from __future__ import annotations

from dataclasses import dataclass, field

from .graphfile import Graph, windows
from . import fingerprint
from .environment import environment
from .fingerprint import implementation_fingerprint
from .hashing import KEY_SCHEMA, FileHasher, digest
from .node import InPath
from .records import Inputs, ItemSpec, Join, Ref, refs, type_name
from .types import Files


@dataclass
class WorkItem:
    node: str
    type_name: str
    module: str
    frame: int | None               # None for sequence items
    frames: list[int]
    params: dict                    # what run() receives
    inputs: Inputs                  # port -> Ref | [Ref per frame] | None
    key: str
    components: dict                # the parts of the key, for `explain`
    deps: list[str] = field(default_factory=list)  # keys of the items producing the inputs
    kept: list[str] = field(default_factory=list)  # output ports stored in the cache
    unit: str = ""                  # "frame:N" for a frame's own items, else "item:KEY"
    window: bool = False            # one window of a windowed sequence node (frames: the window's)

    @property
    def tag(self) -> str:
        """Which frames: "N", "all" (a sequence item) or "A-B" (a window's item)."""
        return f"{self.frames[0]}-{self.frames[-1]}" if self.window else "all" if self.frame is None else str(self.frame)

    @property
    def label(self) -> str:
        return f"{self.node}@{self.tag}"

    def spec(self, log_path: str | None = None) -> ItemSpec:
        return ItemSpec(self.node, self.type_name, self.module, self.frame, self.frames, self.params, self.inputs,
                        self.key, self.components, list(self.kept), log_path, self.window)


def make_plan(graph: Graph, hasher: FileHasher) -> tuple[list[WorkItem], dict[tuple[str, int | None], str]]:
    """Work items in dependency order (deduplicated by key) and the (node, frame) -> key map.
    Sequence items are stored under frame None, a windowed sequence node's under each window's first frame."""
    items: dict[str, WorkItem] = {}
    slot: dict[tuple[str, int | None], str] = {}
    env = environment()

    window_of: dict[tuple[str, int], str] = {}   # (windowed node, frame) -> the key of the window holding it

    def key_of(node: str, frame: int) -> str:
        for at in ((node, frame), (node, None)):
            if at in slot:
                return slot[at]
        return window_of[(node, frame)]

    for name in graph.order():
        spec = graph.nodes[name]
        cls = spec.cls
        impl = implementation_fingerprint(cls)
        hashed_params = {}
        for p, v in spec.params.items():
            decl = cls.params[p]
            hashed_params[p] = {"content": hasher.path(v)} if (decl.type is InPath and v is not None) else v
        frame_sets = [[f] for f in graph.frames] if cls.per == "frame" else windows(graph.frames, spec.window)
        for frames in frame_sets:
            frame = frames[0] if cls.per == "frame" else None
            inputs, in_keys, deps = {}, {}, []
            for port in cls.inputs:
                if port not in spec.inputs:
                    inputs[port] = None
                    in_keys[port] = None
                    continue
                src, sport = spec.inputs[port]
                stype = type_name(graph.nodes[src].cls.outputs[sport].type)
                keys = [key_of(src, f) for f in frames]
                per_frame = [Ref(k, sport, stype) for k in keys]
                src_is_seq = graph.nodes[src].cls.per == "sequence"
                if src_is_seq and cls.per == "sequence" and len(set(keys)) > 1:   # a windowed source's windows
                    joined = [Ref(k, sport, stype) for k in dict.fromkeys(keys)]
                    inputs[port], in_keys[port] = Join(tuple(joined), stype), {"join": [r.name for r in joined]}
                elif cls.per == "frame" or src_is_seq:
                    inputs[port], in_keys[port] = per_frame[0], per_frame[0].name
                else:
                    inputs[port], in_keys[port] = per_frame, [r.name for r in per_frame]
                deps.extend(keys)
            components = {"schema": KEY_SCHEMA, "node": spec.type_name, "version": cls.version,
                          "implementation": impl, "params": hashed_params, "inputs": in_keys,
                          "frame": frame if cls.uses_frame else None, "environment": env}
            if cls.per == "sequence":  # run() sees self.frames: which frames it covers is part of the work
                components["frames"] = frames
            key = digest(components)[:32]
            if cls.per == "sequence" and len(frame_sets) > 1:   # a window's item: listed under its first frame
                slot[(name, frames[0])] = key
                window_of.update(((name, f), key) for f in frames)
            else:
                slot[(name, frame)] = key
            if key not in items:
                items[key] = WorkItem(name, spec.type_name, cls.__module__, frame, frames, dict(spec.params),
                                      inputs, key, components, sorted(set(deps)),
                                      window=cls.per == "sequence" and len(frame_sets) > 1)
    hasher.save()
    fingerprint.save_parsed()
    _assign_units(graph, items, slot)
    return list(items.values()), slot


def _assign_units(graph: Graph, items: dict[str, WorkItem], slot: dict) -> None:
    """Set each item's unit and kept ports (see the module docstring)."""
    uses: dict[str, int] = {}
    for key in slot.values():
        uses[key] = uses.get(key, 0) + 1
    # A frame's nodes after a sequence node (which reads every frame) cannot share a unit with the nodes before
    # it: the unit would wait on itself. Level = sequence nodes on the longest path from a source.
    level: dict[str, int] = {}
    for name in graph.order():
        level[name] = max((level[src] + (graph.nodes[src].cls.per == "sequence") for src in graph.upstream[name]),
                          default=0)
    for it in items.values():
        own = graph.nodes[it.node].cls.per == "frame" and uses[it.key] == 1
        lv = level[it.node]
        it.unit = (f"frame:{it.frame}" + (f"/{lv}" if lv else "")) if own else f"item:{it.key}"
    readers: dict[tuple[str, str], list[WorkItem]] = {}
    for it in items.values():
        for r in refs(it.inputs):
            readers.setdefault((r.key, r.port), []).append(it)
    for it in items.values():
        spec = graph.nodes[it.node]
        cls = spec.cls
        read = {port: readers.get((it.key, port), []) for port in cls.outputs}
        leaf = not any(read.values())  # nothing reads this node: its outputs are the graph's results
        it.kept = [port for port, out in cls.outputs.items()
                   if out.type.kept_by_default or cls.checkpoint or port in spec.keep or leaf
                   or (cls.publishes and issubclass(out.type, Files)) or any(u.unit != it.unit for u in read[port])]
