"""Dask executor: same outputs as the local executor; survives a killed worker; nothing half-written."""
from __future__ import annotations

import textwrap

import pytest

import enginenodes  # noqa: F401
from nodegraph.cache import Cache
from nodegraph.dask_executor import DaskExecutor
from nodegraph.executors import LocalExecutor
from nodegraph.graphfile import load_graph
from nodegraph.run import run_graph

import distributed  # noqa: E402,F401

GRAPH = """\
frames: 0:6
nodes:
  src:   {type: t.source, params: {value: 2.0}}
  scale: {type: t.scale, in: {x: src.out}, params: {factor: 3}}
  total: {type: t.total, in: {x: scale.out}}
  write: {type: t.write, in: {x: scale.out}}
"""


def _run(tmp, graph_text, executor, **kw):
    p = tmp / "g.yaml"
    p.write_text(textwrap.dedent(graph_text))
    return run_graph(load_graph(p, **kw), Cache(tmp / "cache"), tmp / "out", executor, progress=False)


def _published(tmp):
    return {p.name: p.read_bytes() for p in sorted((tmp / "out").glob("sum_*.txt"))}


@pytest.mark.slow
def test_dask_matches_local(tmp_path):
    (tmp_path / "local").mkdir()
    (tmp_path / "dask").mkdir()
    a = _run(tmp_path / "local", GRAPH, LocalExecutor(1))
    b = _run(tmp_path / "dask", GRAPH, DaskExecutor(workers=2))
    assert a.ok and b.ok and b.counts() == {"done": 19}
    keys = lambda r: {(x["node"], x["frame"]): x["key"] for x in r.records}  # noqa: E731
    assert keys(a) == keys(b)
    assert _published(tmp_path / "local") == _published(tmp_path / "dask") and len(_published(tmp_path / "dask")) == 6


@pytest.mark.slow
def test_dask_runs_frame_nodes_after_a_sequence_node(tmp_path):
    """A frame's nodes after a sequence node are a unit of their own (they would otherwise wait on themselves)."""
    from conftest import output

    text = GRAPH + "  pick:  {type: t.pick, in: {x: total.out}}\n"
    res = _run(tmp_path, text, DaskExecutor(workers=2))
    assert res.ok and res.counts() == {"done": 25}, res.failures
    for f in range(6):   # 4 elements x (2 + f) x 3
        assert output(res, "pick", "out", f).tolist() == [12.0 * (2 + f)]


@pytest.mark.slow
def test_dask_runs_a_windowed_sequence_node(tmp_path):
    """The windows of a windowed sequence node are items of their own on the cluster; a frame after it reads its
    window, a sequence node after it the windows joined."""
    from conftest import output

    text = GRAPH + ("  rows:  {type: t.rows, in: {x: scale.out}, window: 4}\n  pick:  {type: t.pick_row, in: {rows: rows.out}}\n"
                    "  all:   {type: t.rows_total, in: {rows: rows.out}}\n")
    res = _run(tmp_path, text, DaskExecutor(workers=2))
    assert res.ok and res.counts() == {"done": 19 + 2 + 6 + 1}, res.failures
    assert sorted(r["frames"] for r in res.records if r["node"] == "rows") == [[0, 3], [4, 5]]
    for f in range(6):   # 4 elements x (2 + f) x 3
        assert output(res, "pick", "out", f).tolist() == [12.0 * (2 + f)]
    assert output(res, "all", "out", None).tolist() == [0, 1, 2, 3, 4, 5, sum(12.0 * (2 + f) for f in range(6))]


@pytest.mark.slow
def test_dask_survives_a_killed_worker(tmp_path):
    marker = tmp_path / "crashed"
    text = GRAPH.replace("  total:", f"  crash: {{type: t.crash, in: {{x: scale.out}}, params: {{on_frame: 2, marker: '{marker}'}}}}\n  total:")
    res = _run(tmp_path, text, DaskExecutor(workers=2))
    assert marker.exists(), "the fault was not injected"
    assert res.ok, res.failures
    assert {r["status"] for r in res.records} == {"done"}
    cache = Cache(tmp_path / "cache")
    assert not any(cache.staging.glob("*")), "nothing may be left half-written"
    assert all(cache.has(r["key"]) for r in res.records)


@pytest.mark.slow
def test_local_pool_killed_worker_then_rerun_computes_only_missing(tmp_path):
    marker = tmp_path / "crashed"
    text = GRAPH.replace("  total:", f"  crash: {{type: t.crash, in: {{x: scale.out}}, params: {{on_frame: 2, marker: '{marker}'}}}}\n  total:")
    first = _run(tmp_path, text, LocalExecutor(2))
    st = {(r["node"], r["frame"]): r["status"] for r in first.records}
    assert st[("crash", 2)] == "failed" and "died" in first.failures[0]["error"]
    assert st[("write", 5)] == "done" and st[("src", 2)] == "done"
    second = _run(tmp_path, text, LocalExecutor(2))
    st2 = {(r["node"], r["frame"]): r["status"] for r in second.records}
    assert second.ok
    rerun = {k for k, v in st2.items() if v == "done"}
    assert ("crash", 2) in rerun and rerun <= {k for k, v in st.items() if v != "done"}


@pytest.mark.slow
def test_dask_worker_that_keeps_dying_fails_its_item_and_skips_downstream(tmp_path):
    import dask

    text = GRAPH.replace("  total: {type: t.total, in: {x: scale.out}}\n  write: {type: t.write, in: {x: scale.out}}",
                         "  crash: {type: t.crash, in: {x: scale.out}, params: {on_frame: 1, marker: always}}\n"
                         "  write: {type: t.write, in: {x: crash.out}}")
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        res = _run(tmp_path, text, DaskExecutor(workers=2))
    st = {(r["node"], r["frame"]): r for r in res.records}
    assert st[("crash", 1)]["status"] == "failed" and "KilledWorker" in st[("crash", 1)]["error"]
    assert st[("write", 1)]["status"] == "skipped" and st[("write", 1)]["error"] == "upstream 'crash' failed"
    # a dying worker also takes down whatever else it was running (allowed-failures 0): those fail with
    # KilledWorker too, and everything downstream of a failure is skipped, never run or reported as failed
    for r in res.records:
        assert r["status"] in ("done", "failed", "skipped")
        if r["status"] == "failed":
            assert "KilledWorker" in r["error"]
        if r["status"] == "skipped":
            assert r["error"].startswith("upstream '")
    assert any(st[("write", f)]["status"] == "done" for f in (0, 2, 3, 4, 5))


@pytest.mark.slow
def test_dask_joins_an_existing_scheduler(tmp_path, capsys):
    from distributed import LocalCluster

    from nodegraph.cli import main as cli

    p = tmp_path / "g.yaml"
    p.write_text(GRAPH)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        args = ["--cache", str(tmp_path / "cache"), "run", str(p), "--out", str(tmp_path / "out"), "-q",
                "--executor", "dask", "--scheduler", cluster.scheduler_address]
        assert cli(args) == 0
    assert "19 done" in capsys.readouterr().out
    assert len(_published(tmp_path)) == 6


@pytest.mark.slow
def test_dask_workers_get_glibc_malloc_and_their_share_of_threads(tmp_path, monkeypatch):
    """The nanny's default pre-spawn environment sets MALLOC_TRIM_THRESHOLD_ (glibc's dynamic mmap threshold
    off: every large NumPy temporary a fresh mmap; one worker ran the demo graph 1.5x slower than a local
    process) and OpenBLAS / OMP / MKL to 1 thread; our workers start with neither."""
    import os

    from conftest import output

    names = ["MALLOC_TRIM_THRESHOLD_", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"]
    for n in names:   # a cluster made by another test (Dask's defaults) leaves its values in this process
        monkeypatch.delenv(n, raising=False)
    text = f"frames: 0:1\nnodes:\n  env: {{type: t.environ, params: {{names: {names}}}}}\n"
    res = _run(tmp_path, text, DaskExecutor(workers=1))
    assert res.ok, res.failures
    got = output(res, "env", "out", 0)
    share = str(os.cpu_count() or 1)
    assert got["MALLOC_TRIM_THRESHOLD_"] is None
    assert {n: got[n] for n in names[1:]} == {n: share for n in names[1:]}
    assert not any(n in os.environ for n in names)   # nothing left behind in this process
