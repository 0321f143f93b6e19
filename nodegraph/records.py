"""The records the scheduler hands around (nodegraph/plan.py explains what they mean): plain dataclasses of
strings, numbers, lists and dicts, so they pickle to a process pool or a Dask worker unchanged.

    Ref         one output port of one work item, as an input of another: (key, port, type)
    Join        the windows of a windowed sequence node read as one value
    ItemSpec    what a worker needs to run one work item (never a live object)
    UnitSpec    a unit's items in dependency order, with how many of its items read each in-memory value
    Result      what running (or skipping) one item came to
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Iterator, Union


@dataclass(frozen=True)
class Ref:
    """Output ``port`` of the work item with key ``key``; ``type`` names the port's DataType ("module:qualname")."""

    key: str
    port: str
    type: str

    @property
    def name(self) -> str:
        """"KEY/PORT": how a key's components and a unit's in-memory values name this output."""
        return f"{self.key}/{self.port}"


def type_name(t: type) -> str:
    """How a Ref names a port's DataType: "module:qualname" (a worker imports it to load the value)."""
    return f"{t.__module__}:{t.__qualname__}"


def resolve_type(name: str) -> type:
    """The DataType a ``type_name`` names (its module imported)."""
    module, qual = name.split(":")
    obj = importlib.import_module(module)
    for part in qual.split("."):
        obj = getattr(obj, part)
    return obj


@dataclass(frozen=True)
class Join:
    """The windows of a windowed sequence node (graph key ``window:``) that one sequence item reads as one value:
    each loaded, then joined by the port type's ``join`` (frames in order)."""

    refs: tuple[Ref, ...]
    type: str


Inputs = dict[str, Union[Ref, list[Ref], Join, None]]   # port -> one ref, a ref per frame (a sequence reader), the
#                                                       windows to join, or None


def refs(inputs: Inputs) -> Iterator[Ref]:
    """Every Ref of an item's inputs, in port order."""
    for ref in inputs.values():
        if isinstance(ref, list):
            yield from ref
        elif isinstance(ref, Join):
            yield from ref.refs
        elif ref is not None:
            yield ref


def frames_of(record: dict) -> str:
    """Which frames a run.json / explain row covers, for a message: "N", "all" or "A-B" (a window's item)."""
    if record.get("frames"):
        return f"{record['frames'][0]}-{record['frames'][1]}"
    return "all" if record["frame"] is None else str(record["frame"])


@dataclass
class ItemSpec:
    """One work item as a worker runs it: its node (type and module, so a worker imports a plugin), frame(s),
    params as run() receives them, inputs, key and key components (written into the cache entry), the output
    ports to keep in the cache and its log file."""

    node: str
    type: str
    module: str
    frame: int | None                 # None for a sequence item
    frames: list[int]
    params: dict
    inputs: Inputs
    key: str
    components: dict
    kept: list[str] = field(default_factory=list)
    log: str | None = None
    window: bool = False              # one window of a windowed sequence node (``frames`` the window's)

    @property
    def where(self) -> str:
        return f"node '{self.node}' ({self.type})" + (
            f" frames {self.frames[0]}..{self.frames[-1]}" if self.window else "" if self.frame is None else f" frame {self.frame}")

    def input_keys(self) -> list[str]:
        return [r.key for r in refs(self.inputs)]


@dataclass
class UnitSpec:
    """What one worker call runs: ``items`` in dependency order; ``readers``: Ref.name -> how many items of the
    unit read that value (it stays in memory until the last one has); ``failed``: key -> node of the items of
    other units that did not produce their outputs (their readers are skipped)."""

    items: list[ItemSpec]
    readers: dict[str, int] = field(default_factory=dict)
    failed: dict[str, str] = field(default_factory=dict)


@dataclass
class Result:
    """How one work item ended: status done / failed / skipped (run.py adds cached), wall seconds, the error of
    a failed or skipped item, the warnings its node logged, and ``corrupt``: the key of a cached input found
    unreadable (run.py evicts it)."""

    status: str
    seconds: float = 0.0
    error: str | None = None
    warnings: list[str] = field(default_factory=list)
    corrupt: str | None = None
    node: str = ""                    # the item's node name (what a skipped reader names as the failure)
    phases: dict = field(default_factory=dict)   # seconds of a run item: load (inputs), run (the node's run()),
                                                 # make (lazy outputs produced for keeping), write (to the cache)
