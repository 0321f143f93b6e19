"""Published files are readable as the process's umask allows (a plain open()'s mode), not mkstemp's private
0600: a pipeline's other users read the run's outputs."""
from __future__ import annotations

import os
import stat
import textwrap
from contextlib import contextmanager

import enginenodes  # noqa: F401  (registers the t.* nodes)
from nodegraph.cache import Cache, atomic_write_bytes
from nodegraph.executors import LocalExecutor
from nodegraph.graphfile import load_graph
from nodegraph.run import run_graph


@contextmanager
def umask(mask: int):
    old = os.umask(mask)
    try:
        yield
    finally:
        os.umask(old)


def mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def test_atomic_writes_follow_the_umask(tmp_path):
    for mask, want in ((0o022, 0o644), (0o027, 0o640), (0o077, 0o600)):
        with umask(mask):
            atomic_write_bytes(tmp_path / f"f{mask:o}", b"x")
        assert mode(tmp_path / f"f{mask:o}") == want, oct(mask)


def test_published_outputs_are_0644_under_umask_022(tmp_path):
    (tmp_path / "g.yaml").write_text(textwrap.dedent("""\
        frames: 0:2
        nodes:
          src:   {type: t.source, params: {value: 1.0}}
          write: {type: t.write, in: {x: src.out}}
        """))
    with umask(0o022):
        res = run_graph(load_graph(tmp_path / "g.yaml"), Cache(tmp_path / "cache"), tmp_path / "out", LocalExecutor(1),
                        progress=False)
    assert res.ok
    published = [p for r in res.records for p in r.get("published") or []]
    assert sorted(os.path.basename(p) for p in published) == ["sum_000.txt", "sum_001.txt"]
    for p in published + [str(tmp_path / "out" / "run.json")]:
        assert mode(p) == 0o644, (p, oct(mode(p)))
