"""Tiny nodes for engine tests (imported by tests; spawned workers import this module by name)."""
from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from nodegraph import Array, Files, InPath, Node, NodeError, OutPath, Param
from nodegraph.types import DataType, Table


class Source(Node):
    """A per-frame array: value + frame."""

    type_name = "t.source"
    uses_frame = True
    outputs = {"out": Array}
    params = {"value": Param(float, 0.0, doc="base value"), "size": Param(int, 4, range=(1, 1000))}

    def run(self, *, value, size, frame):
        return {"out": np.full(size, value + frame)}


class Scale(Node):
    """Multiply by a factor."""

    type_name = "t.scale"
    inputs = {"x": Array}
    outputs = {"out": Array}
    params = {"factor": Param(float, 2.0, range=(-100, 100)), "mode": Param(str, "mul", choices=("mul", "add"))}

    def run(self, x, *, factor, mode):
        if factor == 0:
            self.log.warning("factor 0 gives zeros")
        return {"out": x * factor if mode == "mul" else x + factor}


class Add(Node):
    """Add one."""

    type_name = "t.add"
    inputs = {"a": Array}
    outputs = {"out": Array}

    def run(self, a):
        return {"out": a + 1}


class Total(Node):
    """Sequence node: one array of per-frame sums."""

    type_name = "t.total"
    per = "sequence"
    inputs = {"x": Array}
    outputs = {"out": Array}

    def run(self, x):
        assert isinstance(x, list) and len(x) == len(self.frames)
        return {"out": np.array([float(a.sum()) for a in x])}


class Pick(Node):
    """A frame's element of a sequence node's array (a per-frame node after a sequence node)."""

    type_name = "t.pick"
    uses_frame = True
    inputs = {"x": Array}
    outputs = {"out": Array}

    def run(self, x, *, frame):
        return {"out": np.array([x[frame]])}


class Fail(Node):
    """Fails on chosen frames."""

    type_name = "t.fail"
    inputs = {"x": Array}
    outputs = {"out": Array}
    params = {"frames": Param(list, [], item=int)}

    def run(self, x, *, frames):
        if self.frame in frames:
            raise NodeError(f"frame {self.frame} is broken on purpose")
        return {"out": x}


class ReadFile(Node):
    """Bytes of an input file as an array (hashed by content, not path)."""

    type_name = "t.readfile"
    outputs = {"out": Array}
    params = {"path": Param(InPath, doc="a file")}

    def run(self, *, path):
        return {"out": np.frombuffer(Path(path).read_bytes(), dtype=np.uint8)}


class ReadDir(Node):
    """Total size of the regular files in an input folder (never opens anything else)."""

    type_name = "t.readdir"
    outputs = {"out": Array}
    params = {"path": Param(InPath, doc="a folder")}

    def run(self, *, path):
        return {"out": np.array([sum(p.stat().st_size for p in sorted(Path(path).iterdir()) if p.is_file())])}


class WriteText(Node):
    """Publishes a text file with the array's sum."""

    type_name = "t.write"
    uses_frame = True
    publishes = True
    inputs = {"x": Array}
    outputs = {"files": Files}
    params = {"path": Param(OutPath, "sum_{frame:03d}.txt")}

    def run(self, x, *, path, frame):
        return {"files": {path.format(frame=frame): f"{float(x.sum())}\n".encode()}}


class SlowType(DataType):
    """A type whose save() announces itself and then stalls, so a test can kill the writer mid-write."""

    name = "Slow"

    @classmethod
    def save(cls, value, folder):
        (folder / "part1.bin").write_bytes(b"x" * 1000)
        Path(os.environ["VOLCAP_TEST_SIGNAL"]).write_text("writing")
        time.sleep(60)
        (folder / "part2.bin").write_bytes(b"y")

    @classmethod
    def load(cls, folder):
        return (folder / "part1.bin").read_bytes()


class SlowWriter(Node):
    """Produces a SlowType output (see SlowType)."""

    type_name = "t.slowwrite"
    outputs = {"out": SlowType}

    def run(self):
        return {"out": b"data"}


class SlowFrameWriter(Node):
    """SlowWriter per frame: each frame its own work item, each stalling in its write."""

    type_name = "t.slowwrite.frame"
    uses_frame = True
    outputs = {"out": SlowType}

    def run(self, *, frame):
        return {"out": b"data"}


class Crash(Node):
    """Fault injection: kills its own process the first time it runs on frame ``on_frame`` (a marker file
    remembers that it happened), like a worker lost to the OOM killer; marker "always" crashes every time."""

    type_name = "t.crash"
    inputs = {"x": Array}
    outputs = {"out": Array}
    params = {"on_frame": Param(int, 1), "marker": Param(str, "")}

    def run(self, x, *, on_frame, marker):
        if self.frame == on_frame and marker == "always":
            os.kill(os.getpid(), 9)
        if self.frame == on_frame and not Path(marker).exists():
            Path(marker).write_text("crashed once")
            os.kill(os.getpid(), 9)
        time.sleep(0.2)
        return {"out": x * 10}


class HandsOver(Node):
    """Hangs a by-product on its output object (as refine once handed relax its last search): impure."""

    type_name = "t.handsover"
    inputs = {"x": Array}
    outputs = {"out": Array}

    def run(self, x):
        out = np.array(x, dtype=float)
        return {"out": _Tagged(out, hint=float(x.sum()))}


class _Tagged(np.ndarray):
    def __new__(cls, a, hint):
        obj = np.asarray(a).view(cls)
        obj.hint = hint
        return obj


class UsesHint(Node):
    """Reads the by-product when it is there (only in memory, in the same unit)."""

    type_name = "t.useshint"
    inputs = {"x": Array}
    outputs = {"out": Array}

    def run(self, x):
        return {"out": np.asarray(x) + getattr(x, "hint", 0.0)}


class Steps(Node):
    """Sums the frames' values in ``steps`` steps, saying how far it has come (Node.progress), ``pause`` s each."""

    type_name = "t.steps"
    per = "sequence"
    inputs = {"x": Array}
    outputs = {"out": Array}
    params = {"steps": Param(int, 5), "pause": Param(float, 0.0)}

    def run(self, x, *, steps, pause):
        for i in range(steps):
            time.sleep(pause)
            self.progress(i + 1, steps, "steps")
        return {"out": np.sum(x, axis=0)}


class WorkerEnviron(Node):
    """The environment a worker runs its items in (test_dask: what the Dask executor's nannies hand over)."""

    type_name = "t.environ"
    outputs = {"out": Table}
    params = {"names": Param(list, [], item=str, doc="variables to report")}

    def run(self, *, names):
        return {"out": {n: os.environ.get(n) for n in names}}


class Rows(Array):
    """Per-frame rows of a sequence node ([frame, value] each): windows join by stacking (graph key ``window:``)."""

    name = "t.Rows"

    @classmethod
    def join(cls, parts):
        return np.concatenate(parts)


class FrameRows(Node):
    """Sequence node: one row [frame, sum] per frame it covers."""

    type_name = "t.rows"
    per = "sequence"
    inputs = {"x": Array}
    outputs = {"out": Rows, "sum": Array}

    def run(self, x):
        assert len(x) == len(self.frames)
        return {"out": np.array([[f, float(a.sum())] for f, a in zip(self.frames, x)]),
                "sum": np.array([float(sum(a.sum() for a in x))])}


class RowsTotal(Node):
    """Sequence node over rows: the frames it was given, and the sum of the values."""

    type_name = "t.rows_total"
    per = "sequence"
    inputs = {"rows": Rows}
    outputs = {"out": Array}

    def run(self, rows):
        return {"out": np.concatenate([rows[:, 0], [rows[:, 1].sum()]])}


class PickRow(Node):
    """A frame's row of a rows table (a per-frame reader of a sequence node)."""

    type_name = "t.pick_row"
    uses_frame = True
    inputs = {"rows": Rows}
    outputs = {"out": Array}

    def run(self, rows, *, frame):
        at = np.nonzero(rows[:, 0] == frame)[0]
        if not len(at):
            raise NodeError(f"frame {frame} not in rows {rows[:, 0].tolist()}")
        return {"out": rows[at[0], 1:]}
