"""Shared fixtures: the golden-file harness and the real-data group.

Real-data tests carry ``@pytest.mark.realdata`` and read ``data_dir`` (``$VOLCAP_DATA``, default
``../shared/data`` beside the checkout). Without that folder they are deselected with a notice, so a fresh
clone passes; with ``VOLCAP_REQUIRE_DATA=1`` (set by .ci/run) a missing folder is an error instead.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
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
