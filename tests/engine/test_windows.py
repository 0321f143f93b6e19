"""Windowed sequence nodes (graph key ``window:``): a sequence node split into work items of N frames, which run
in parallel; per-frame readers read their window, sequence readers the windows joined by the port type."""
from __future__ import annotations

import json
import textwrap

import numpy as np
import pytest

import enginenodes  # noqa: F401  (registers the t.* nodes)
from nodegraph import GraphError
from nodegraph.cache import Cache
from nodegraph.executors import LocalExecutor
from nodegraph.graphfile import load_graph
from nodegraph.records import Join
from nodegraph.run import plan_graph, run_graph

ROWS = """\
frames: 0:7
nodes:
  src:   {type: t.source, params: {value: 1.0, size: 2}}
  rows:  {type: t.rows, in: {x: src.out}, window: 3}
  pick:  {type: t.pick_row, in: {rows: rows.out}}
  more:  {type: t.add, in: {a: pick.out}}
  total: {type: t.rows_total, in: {rows: rows.out}}
"""


def graph(tmp_path, text, **kw):
    p = tmp_path / "g.yaml"
    p.write_text(textwrap.dedent(text))
    return load_graph(p, **kw)


def problems(tmp_path, text, **kw) -> list[str]:
    with pytest.raises(GraphError) as exc:
        graph(tmp_path, text, **kw)
    return exc.value.problems


def test_windows_are_items_of_their_own_read_per_frame_and_joined(tmp_path):
    from conftest import output

    for jobs in (1, 2):
        folder = tmp_path / f"j{jobs}"
        g = graph(tmp_path, ROWS)
        res = run_graph(g, Cache(folder / "cache"), folder / "out", LocalExecutor(jobs), progress=False)
        assert res.ok, res.failures
        windows = sorted(tuple(r["frames"]) for r in res.records if r["node"] == "rows")
        assert windows == [(0, 2), (3, 5), (6, 6)]
        assert res.counts() == {"done": 7 + 3 + 7 + 7 + 1}
        for f in range(7):   # frame f's row: 2 x (1 + f), plus one
            np.testing.assert_array_equal(output(res, "more", "out", f), [2.0 * (1 + f) + 1])
        np.testing.assert_array_equal(output(res, "total", "out", None), list(range(7)) + [sum(2.0 * (1 + f) for f in range(7))])
        logs = {r["log"] for r in res.records if r["node"] == "rows"}
        assert len(logs) == 3, logs
        doc = json.loads((folder / "out" / "run.json").read_text())
        assert {tuple(r["frames"]) for r in doc["items"] if r["node"] == "rows"} == set(windows)
        again = run_graph(graph(tmp_path, ROWS), Cache(folder / "cache"), folder / "out", LocalExecutor(jobs), progress=False)
        assert again.counts() == {"cached": 25}


def test_a_frame_waits_only_on_its_window(tmp_path):
    g = graph(tmp_path, ROWS)
    items, slot = plan_graph(g, Cache(tmp_path / "cache"))
    by_key = {it.key: it for it in items}
    rows = {it.frames[0]: it for it in items if it.node == "rows"}
    assert sorted(rows) == [0, 3, 6] and all(it.window for it in rows.values())
    assert [rows[0].label, rows[6].label] == ["rows@0-2", "rows@6-6"]
    for f in range(7):
        pick = by_key[slot[("pick", f)]]
        assert pick.deps == [rows[3 * (f // 3)].key], f
    total = by_key[slot[("total", None)]]
    assert isinstance(total.inputs["rows"], Join)
    assert [r.key for r in total.inputs["rows"].refs] == [rows[0].key, rows[3].key, rows[6].key]


def test_the_window_is_part_of_the_work(tmp_path):
    def keys(text, **kw):
        return plan_graph(graph(tmp_path, text, **kw), Cache(tmp_path / "cache"))[1]

    three, four = keys(ROWS), keys(ROWS.replace("window: 3", "window: 4"))
    assert three[("rows", 0)] != four[("rows", 0)], "other frames in the first window: another item"
    assert three[("src", 5)] == four[("src", 5)] and three[("pick", 5)] != four[("pick", 5)]
    whole = keys(ROWS.replace(", window: 3", ""))
    assert keys(ROWS.replace("window: 3", "window: 7")) == whole, "one window over every frame is the plain node"
    assert keys(ROWS.replace("window: 3", "window: 0")) == whole
    assert keys(ROWS.replace(", window: 3", ""), overrides=["rows.window=3"]) == three


@pytest.mark.parametrize("text, needle", [
    (ROWS.replace("window: 3}", "window: 3}\n  w: {type: t.scale, in: {x: src.out}, window: 2}"),
     ":5: node 'w': window applies to sequence nodes; type 't.scale' runs per frame"),
    (ROWS.replace("window: 3", "window: -1"), ":4: node 'rows': window must be a whole number of frames >= 1"),
    (ROWS.replace("window: 3", "window: two"), ":4: node 'rows': window must be a whole number"),
    (ROWS.replace("in: {rows: rows.out}}\n", "in: {rows: rows.out}, window: 2}\n").replace("pick_row, in: {rows: rows.out}, window: 2", "pick_row, in: {rows: rows.out}"),
     ":7: node 'total': input 'rows': 'rows' works in windows (0..2 is one) that total's own windows cut"),
    (ROWS + "  sums: {type: t.total, in: {x: rows.sum}}\n",
     ":8: node 'sums': input 'x': 'rows' works in windows of 3 frames and Array cannot be joined over windows"),
    (ROWS.replace(", window: 3", "").replace("rows_total, in: {rows: rows.out}", "rows_total, in: {rows: rows.out}, window: 2"),
     ":7: node 'total': input 'rows': 'rows' covers all frames in one item"),
])
def test_window_mistakes_name_file_line_and_node(tmp_path, text, needle):
    found = problems(tmp_path, text)
    assert any(needle in p for p in found), found


def test_window_by_set_names_the_argument(tmp_path):
    found = problems(tmp_path, ROWS, overrides=["pick.window=2"])
    assert any(p.startswith("--set pick.window=2: node 'pick': window applies to sequence nodes") for p in found), found


def test_a_windows_error_names_its_frames(tmp_path):
    text = ROWS.replace("size: 2}}\n", "size: 2}}\n  bad:   {type: t.fail, in: {x: src.out}, params: {frames: [4]}}\n")
    text = text.replace("in: {x: src.out}, window", "in: {x: bad.out}, window")
    g = graph(tmp_path, text)
    res = run_graph(g, Cache(tmp_path / "cache"), tmp_path / "out", LocalExecutor(1), progress=False)
    assert not res.ok
    skipped = [r for r in res.records if r["node"] == "rows" and r["status"] == "skipped"]
    assert [r["frames"] for r in skipped] == [[3, 5]], res.records
    done = sorted(r["frames"][0] for r in res.records if r["node"] == "rows" and r["status"] == "done")
    assert done == [0, 6], "the other windows run"


def test_a_reader_whose_window_is_a_multiple_joins_the_windows_it_covers(tmp_path):
    text = ROWS.replace("rows_total, in: {rows: rows.out}", "rows_total, in: {rows: rows.out}, window: 6")
    items, _ = plan_graph(graph(tmp_path, text), Cache(tmp_path / "cache"))
    totals = {it.frames[0]: it for it in items if it.node == "total"}
    assert isinstance(totals[0].inputs["rows"], Join) and len(totals[0].inputs["rows"].refs) == 2
    assert not isinstance(totals[6].inputs["rows"], Join), "one window: read as it is"
    res = run_graph(graph(tmp_path, text), Cache(tmp_path / "cache"), tmp_path / "out", LocalExecutor(1), progress=False)
    assert res.ok, res.failures
    first = [r for r in res.records if r["node"] == "total" and r["frame"] == 0]
    assert first[0]["frames"] == [0, 5]
    rows = {r["frame"]: r for r in res.records if r["node"] == "total"}
    from nodegraph.node import node_class

    out = {f: Cache(tmp_path / "cache").load(r["key"], "out", node_class("t.rows_total").outputs["out"].type) for f, r in rows.items()}
    np.testing.assert_array_equal(out[0], [0, 1, 2, 3, 4, 5, sum(2.0 * (1 + f) for f in range(6))])
    np.testing.assert_array_equal(out[6], [6, 14.0])
