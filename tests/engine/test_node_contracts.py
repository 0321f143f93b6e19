"""Every registered node type keeps its declaration honest: run() takes exactly its declared inputs and
params, defaults are valid, every param is documented, kernels exist, describe() works."""
from __future__ import annotations

import inspect
from pathlib import Path

import pytest

from nodegraph import REQUIRED, registry
from nodegraph.fingerprint import implementation_fingerprint
from nodegraph.node import discovery_problems

from nodegraph.fingerprint import project_packages

# the node types of the registered node packages (not the small nodes other test modules define for themselves)
NODES = sorted((n, c) for n, c in registry().items() if c.__module__.split(".")[0] in project_packages())


def test_all_node_modules_import():
    assert discovery_problems() == []


def test_stage_nodes_are_registered():
    assert {"export.mesh", "export.masks", "export.volume"} <= set(registry())


@pytest.mark.parametrize("name, cls", NODES, ids=[n for n, _ in NODES])
def test_declaration_matches_run(name, cls):
    assert cls.doc(), f"{name}: needs a docstring (shown by `describe`)"
    sig = inspect.signature(cls.run)
    args = {p.name for p in sig.parameters.values() if p.name != "self" and p.kind != p.VAR_KEYWORD}
    want = set(cls.inputs) | set(cls.params) | ({"frame"} if cls.uses_frame else set())
    if not any(p.kind == p.VAR_KEYWORD for p in sig.parameters.values()):
        assert args == want, f"{name}: run() takes {sorted(args)}, declaration says {sorted(want)}"
    for pname, p in cls.params.items():
        if p.default is not REQUIRED:
            assert p.coerce(p.default) == p.default or p.default is None, f"{name}.{pname}: default {p.default!r} is invalid"
        assert p.doc or name.startswith("t."), f"{name}.{pname}: parameter needs a one-line doc"
    for k in cls.kernels:
        assert Path(k).is_file()
    assert cls.outputs, f"{name}: declares no outputs"
    assert name in cls.describe() and implementation_fingerprint(cls)
