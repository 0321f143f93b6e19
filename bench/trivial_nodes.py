"""Trivial nodes for measuring the engine's own overhead (bench/engine.py)."""
import numpy as np

from nodegraph import Array, Node, Param


class Make(Node):
    """A small per-frame array."""

    type_name = "bench.make"
    uses_frame = True
    outputs = {"out": Array}
    params = {"size": Param(int, 16)}

    def run(self, *, size, frame):
        return {"out": np.full(size, float(frame))}


class Step(Node):
    """x + 1."""

    type_name = "bench.step"
    inputs = {"x": Array}
    outputs = {"out": Array}
    params = {"salt": Param(int, 0, doc="changes the key only")}

    def run(self, x, *, salt):
        return {"out": x + 1}
