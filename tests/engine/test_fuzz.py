"""Fuzz test (issue 12): hypothesis-generated graph files (random YAML documents over the node vocabulary,
with hostile edits: control characters, aliases, deep brackets, tags, huge numbers) and --set values, run
through `validate` and, when valid, `explain`. Every case must end with exit code 0 or 2, never a traceback,
within its time limit; faulthandler kills the process (the test then fails loudly) if a case hangs.
The long run of ~1000 catalogued attacks plus many more generated ones is tests/fuzz/run_fuzz.py."""
from __future__ import annotations

import faulthandler
import sys
from datetime import timedelta
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "fuzz"))
import enginenodes  # registers the t.* nodes  # noqa: E402
from hostile import attempt, strategies, write_case  # noqa: E402

assert enginenodes.Source.type_name == "t.source"
GRAPHS, SETS = strategies()
HANG_S = 30      # a case still running after this is a hang: faulthandler ends the process with a traceback
LIMIT_S = 5      # a case slower than this fails the test


@settings(max_examples=200, deadline=timedelta(seconds=LIMIT_S), derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@pytest.mark.slow
@given(text=GRAPHS, sets=SETS)
def test_hostile_graph_files_and_set_values(tmp_path_factory, text, sets):
    folder = tmp_path_factory.mktemp("fuzz", numbered=True)
    graph = folder / "g.yaml"
    write_case(graph, text)
    args = [a for s in sets for a in ("--set", s)]
    faulthandler.dump_traceback_later(HANG_S, exit=True)
    try:
        outcome, detail, seconds = attempt(["--cache", str(folder / "cache"), "validate", str(graph), *args], LIMIT_S)
        assert outcome in ("ok", "clean"), f"validate: {outcome}: {detail}\n--- graph ---\n{text[:2000]!r}\n--- set --- {sets!r}"
        if outcome == "ok":
            outcome, detail, seconds = attempt(["--cache", str(folder / "cache"), "explain", str(graph), *args], LIMIT_S)
            assert outcome in ("ok", "clean"), f"explain: {outcome}: {detail}\n--- graph ---\n{text[:2000]!r}"
    finally:
        faulthandler.cancel_dump_traceback_later()
