"""mc `largest` (issue 12, item 3): small disconnected parts (noise) are dropped, real parts are kept, and
what was dropped is logged. `largest: true` used to keep only the biggest part: a model of 15 separate
parts lost 34 % of its faces, silently."""
from __future__ import annotations

import logging

import numpy as np

from nodegraph.testing import run_node
from nodes.common.types import VoxelGrid
from nodes.mesh.nodes import MarchingCubes


def parts_volume():
    """A 12^3 block, 14 smaller blocks (3^3 .. 5^3: real parts, 6 % .. 17 % of its faces) and 2 single-voxel specks."""
    occ = np.zeros((64, 64, 16), np.uint8)
    occ[2:14, 2:14, 2:14] = 1
    spots = [(x, y) for x in range(18, 60, 8) for y in range(2, 60, 8)][:14]
    for k, (x, y) in enumerate(spots):
        s = 3 + k % 3
        occ[x:x + s, y:y + s, 4:4 + s] = 1
    occ[2, 40, 14] = 1
    occ[10, 50, 14] = 1
    return VoxelGrid(occ, [0, 0, 0], [6.4, 6.4, 1.6])


def components(mesh) -> list[int]:
    return sorted((len(p.faces) for p in mesh.split(only_watertight=False)), reverse=True)


class Lines(logging.Handler):
    def __init__(self):
        super().__init__(logging.DEBUG)
        self.records = []

    def emit(self, record):
        self.records.append((record.levelno, record.getMessage()))


def test_largest_keeps_every_real_part_and_logs_what_it_dropped():
    vol = parts_volume()
    everything = components(run_node("mc", {"volume": vol})["mesh"])
    assert len(everything) == 17
    node = MarchingCubes()
    node.log = logging.getLogger("test.mc")
    node.log.setLevel(logging.DEBUG)
    lines = Lines()
    node.log.addHandler(lines)
    try:
        kept = components(node.run(vol, level=0.5, largest=True, min_part=0.01, method="opencl")["mesh"])
    finally:
        node.log.removeHandler(lines)
    assert kept == everything[:15], (kept, everything)
    assert sum(kept) / sum(everything) > 0.99
    text = " ".join(m for _, m in lines.records)
    assert "dropped 2 of 17 parts" in text and "16 faces" in text, lines.records


def test_min_part_one_keeps_only_the_largest():
    vol = parts_volume()
    only = components(run_node("mc", {"volume": vol}, {"largest": True, "min_part": 1.0})["mesh"])
    assert only == [components(run_node("mc", {"volume": vol})["mesh"])[0]]
