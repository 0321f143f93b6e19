"""The layers keep their import rules (ARCHITECTURE.md): the engine imports nothing from the stages or the
kernels package; a stage imports nodegraph, kernels and nodes.common, never another stage; nodes.common
imports no stage. Read from the sources (imports inside functions count), so a lazy import cannot hide."""
from __future__ import annotations

from pathlib import Path

import pytest

from nodegraph.fingerprint import imported_names

ROOT = Path(__file__).resolve().parents[2]


def modules(package: str):
    for path in sorted((ROOT / package).rglob("*.py")):
        rel = path.relative_to(ROOT).with_suffix("")
        parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
        yield ".".join(parts), path, rel.name == "__init__"


def project_imports(name: str, path: Path, is_pkg: bool) -> set[str]:
    return {n for n in imported_names(path.read_text(), name, is_pkg) if n.split(".")[0] in ("nodes", "nodegraph", "kernels")}


ENGINE = list(modules("nodegraph"))
STAGES = [m for m in modules("nodes") if m[0].count(".") >= 1]


@pytest.mark.parametrize("name, path, is_pkg", ENGINE, ids=[m[0] for m in ENGINE])
def test_engine_imports_no_stage(name, path, is_pkg):
    bad = sorted(n for n in project_imports(name, path, is_pkg) if n.split(".")[0] in ("nodes", "kernels"))
    assert not bad, f"{path.relative_to(ROOT)} (engine) imports {bad}"


@pytest.mark.parametrize("name, path, is_pkg", STAGES, ids=[m[0] for m in STAGES])
def test_stages_import_only_common(name, path, is_pkg):
    own = name.split(".")[1]
    allowed = {"common"} if own == "common" else {"common", own}
    bad = sorted(n for n in project_imports(name, path, is_pkg)
                 if n.startswith("nodes.") and n.split(".")[1] not in allowed)
    assert not bad, f"{path.relative_to(ROOT)} ({'shared' if own == 'common' else 'stage ' + own}) imports {bad}"


def test_every_stage_is_a_package_below_nodes():
    loose = [p.name for p in (ROOT / "nodes").glob("*.py") if p.name != "__init__.py"]
    assert not loose, f"modules directly in nodes/ (put them in a stage package or nodes/common): {loose}"


# Node classes outside their stage's nodes.py, each with its reason. A node's fingerprint covers its module's
# whole import closure, so a class beside another stage's nodes makes them rerun for each other's edits.
NODES_ELSEWHERE = {
    "nodes.export.textured": "export/nodes.py would then import the rasterizer and USD code: export.mesh and "
                             "export.masks would rerun on every edit of them",
    "nodes.mesh.photo": "mesh/nodes.py would then import the rasterizer (photo's visibility and outline tests): mc, "
                        "refine and relax would rerun on every edit of it",
    "nodes.track.export": "track/nodes.py would then import the glTF/USD writers: the tracker would rerun on "
                          "every edit of an export format",
}


def test_node_classes_live_in_their_stage_nodes_module():
    """One place for a node: every Node class of a stage is declared in nodes/<stage>/nodes.py."""
    import ast

    stray = []
    for name, path, _ in STAGES:
        if name.endswith(".nodes") or name in NODES_ELSEWHERE:
            continue
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, ast.ClassDef) and any(getattr(b, "id", None) == "Node" for b in node.bases):
                stray.append(f"{path.relative_to(ROOT)}: class {node.name}")
    assert not stray, f"node classes outside their stage's nodes.py: {stray}"
