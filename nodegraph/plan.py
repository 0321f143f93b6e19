"""Planning: a validated Graph -> work items with cache keys.

The contract (what the scheduler, the cache and `explain` rely on):
- A work item is one node run: (node, frame) for per-frame nodes, (node, all frames) for sequence nodes.
- Its spec is small, plain data (node type and module, params, input artifact references, key): it can be
  pickled to a process pool or a Dask cluster, never a live object.
- Its key is the SHA-256 of: the key schema version, node type, node version, the implementation
  fingerprint (nodegraph.fingerprint: the node's module, what it imports within the project's packages,
  data files beside them, its OpenCL sources and their headers), the canonical params (input
  paths replaced by their content hash), the keys of its input artifacts, the
  frame number if the node ``uses_frame``, the list of frames for a sequence node, and the environment
  (nodegraph/environment.py: the versions of the libraries that change numbers, the OpenCL device). Same key = same result, so an item whose key is in the cache is
  never rerun, and two items with the same key (a per-frame node fed only frame-independent data) run once.
- An item runs when it is not cached and all its inputs exist; when an input failed, it is skipped.

Frame units (what runs together, what is kept):
- A frame's own items (per-frame items whose key no other frame shares) form one *unit*: they run together in
  one worker, in dependency order, handing their values over in memory (a device-resident value, such as a
  key's silhouettes packed for the hull, stays on the OpenCL device). Every other item is a unit of its own:
  sequence items, and per-frame items several frames share (a frame-independent source).
- Only the ports that must be *kept* are stored in the cache (``WorkItem.kept``): outputs of a type kept by
  default (small values: tables, cameras, boxes, files), exported files (publishing nodes), outputs read by
  another unit (a sequence node, another frame), the outputs of nodes nothing reads (results), and
  checkpoints: every output of a node class that declares ``checkpoint = True`` (a renderer) and the ports a
  graph lists under a node's ``keep:``; an output nothing reads is kept when nothing reads any output of its
  node (a result), not when a sibling output is read (a by-product, e.g. a key's despilled images beside the
  masks the hull reads). Large intermediate values (images, masks, volumes, meshes) live only in memory.
  Which values are kept never changes a key.
- What runs is decided from the cache (nodegraph/run.py): an item with a kept port missing from the cache
  runs, and so do the items of its unit whose in-memory values it needs; the rest is up to date.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from .graphfile import Graph
from . import fingerprint
from .environment import environment
from .fingerprint import implementation_fingerprint
from .hashing import KEY_SCHEMA, FileHasher, digest
from .node import InPath
from .records import Inputs, ItemSpec, Ref, refs, type_name
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

    @property
    def label(self) -> str:
        return f"{self.node}@{'all' if self.frame is None else self.frame}"

    def spec(self, log_path: str | None = None) -> ItemSpec:
        return ItemSpec(self.node, self.type_name, self.module, self.frame, self.frames, self.params, self.inputs,
                        self.key, self.components, list(self.kept), log_path)


def make_plan(graph: Graph, hasher: FileHasher) -> tuple[list[WorkItem], dict[tuple[str, int | None], str]]:
    """Work items in dependency order (deduplicated by key) and the (node, frame) -> key map.
    Sequence items are stored under frame None."""
    items: dict[str, WorkItem] = {}
    slot: dict[tuple[str, int | None], str] = {}
    env = environment()

    def key_of(node: str, frame: int) -> str:
        return slot[(node, frame)] if (node, frame) in slot else slot[(node, None)]

    for name in graph.order():
        spec = graph.nodes[name]
        cls = spec.cls
        impl = implementation_fingerprint(cls)
        hashed_params = {}
        for p, v in spec.params.items():
            decl = cls.params[p]
            hashed_params[p] = {"content": hasher.path(v)} if (decl.type is InPath and v is not None) else v
        frame_sets = [[f] for f in graph.frames] if cls.per == "frame" else [list(graph.frames)]
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
                if cls.per == "frame" or src_is_seq:
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
            slot[(name, frame)] = key
            if key not in items:
                items[key] = WorkItem(name, spec.type_name, cls.__module__, frame, frames, dict(spec.params),
                                      inputs, key, components, sorted(set(deps)))
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
