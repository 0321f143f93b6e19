"""Shared fixtures: the golden-file harness, the real-data group, and what is expensive computed once.

Layout: tests/engine (the engine), tests/stages/<stage> (one folder per stage package), tests/graphs (the
graph files in graphs/); helpers here: rig.py (the one camera rig builder), golden.py, enginenodes.py.

Real-data tests carry ``@pytest.mark.realdata`` and read ``data_dir`` (``$VOLCAP_DATA``, default
``../shared/data`` beside the checkout). Without that folder they are deselected with a notice, so a fresh
clone passes; with ``VOLCAP_REQUIRE_DATA=1`` (set by .ci/run) a missing folder is an error instead.

Session fixtures compute the expensive things once for every test that needs them: ``dataset_run`` runs a
dataset graph through the engine (one cache for the whole session), ``real_capture`` loads a dataset's
frame 0, ``small_stage`` renders a small synthetic capture.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
# every box a producer promises (MaskSet.boxes, ImageSet.windows: 0 outside) is verified when a set is made, also in
# the workers the tests' runs spawn (nodes.common.types.CHECK_PROMISES)
os.environ["VOLCAP_CHECK_PROMISES"] = "1"
sys.path.insert(0, str(Path(__file__).resolve().parent))

from golden import Golden  # noqa: E402


def data_root() -> Path:
    return Path(os.environ.get("VOLCAP_DATA", ROOT.parent / "shared" / "data")).resolve()


def pytest_addoption(parser):
    parser.addoption("--update-golden", action="store_true", help="rewrite golden files (review the diff!)")


_rewritten: list[str] = []


@pytest.fixture
def golden(request):
    return Golden(request.config.getoption("--update-golden"), _rewritten)


@pytest.fixture(scope="session")
def data_dir() -> Path:
    return data_root()


@pytest.fixture(scope="session")
def dataset_run(tmp_path_factory, data_dir):
    """run(name, overrides=(), frames=None) -> RunResult of graphs/datasets/NAME.yaml (or a graph's Path) on the
    real data, computed
    once per session for each (name, overrides, frames), all runs sharing one cache (so a capture or a hull two
    graphs have in common is computed once). ``run.output(res, node, port)`` loads a node's frame-0 output."""
    from nodegraph.cache import Cache
    from nodegraph.executors import LocalExecutor
    from nodegraph.graphfile import load_graph
    from nodegraph.run import run_graph

    base = tmp_path_factory.mktemp("dataset_runs")
    runs: dict = {}
    mp = pytest.MonkeyPatch()
    mp.setenv("VOLCAP_DATA", str(data_dir))

    def run(name, overrides=(), frames=None):
        key = (str(name), tuple(overrides), frames)
        if key not in runs:
            path = name if isinstance(name, Path) else ROOT / "graphs" / "datasets" / f"{name}.yaml"
            g = load_graph(path, overrides=list(overrides), frames=frames).keep_all()  # tests read intermediate values
            out = base / f"out{len(runs)}"
            res = run_graph(g, Cache(base / "cache"), out, LocalExecutor(1), progress=False)
            assert res.ok, res.failures
            runs[key] = res
        return runs[key]

    run.output = output
    yield run
    mp.undo()


def output(res, node: str, port: str, frame=0):
    """The value a node of a finished run produced on ``port`` (frame ``frame``), loaded from the cache."""
    from nodegraph.cache import Cache
    from nodegraph.node import node_class

    [rec] = [r for r in res.records if r["node"] == node and r["frame"] in (frame, None)]
    cls = node_class(rec["type"])
    return Cache(Path(rec["cache_dir"]).parents[2]).load(rec["key"], port, cls.outputs[port].type)


@pytest.fixture(scope="session")
def real_capture(data_dir):
    """capture(name) -> load_capture of the dataset's frame 0, loaded once per session."""
    from nodes.capture.load import load_capture

    loaded: dict = {}

    def capture(name: str) -> dict:
        if name not in loaded:
            loaded[name] = load_capture(data_dir / name)
        return loaded[name]

    return capture


@pytest.fixture(scope="session")
def small_stage():
    """A small synthetic capture (walking figure, 8 cameras of 160x120, green screen) from the synth node."""
    from nodegraph.testing import run_node

    return run_node("synth", params={"scene": "figure", "cameras": 8, "width": 160, "height": 120, "background": "green"})


def pytest_collection_modifyitems(config, items):
    if data_root().is_dir():
        return
    if os.environ.get("VOLCAP_REQUIRE_DATA") == "1":
        raise pytest.UsageError(f"VOLCAP_REQUIRE_DATA=1 but the real-data folder {data_root()} does not exist (set VOLCAP_DATA)")
    real = [it for it in items if it.get_closest_marker("realdata")]
    if real:
        items[:] = [it for it in items if not it.get_closest_marker("realdata")]
        config.hook.pytest_deselected(items=real)
        config._volcap_notice = f"{len(real)} real-data tests deselected: {data_root()} not found (set VOLCAP_DATA)"


def pytest_terminal_summary(terminalreporter, config):
    if getattr(config, "_volcap_notice", None):
        terminalreporter.write_line(config._volcap_notice)
    if _rewritten:
        terminalreporter.write_line("golden files rewritten (review with git diff tests/golden): " + ", ".join(_rewritten))
