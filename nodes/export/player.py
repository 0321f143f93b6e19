"""The stream player: a small web page on three.js that plays a volcap-stream ladder (stream.py) with
scrubbing, a play button and a rung selector (player/index.html, player/player.js).

three.js is a pinned npm package that ``setup.sh`` installs into ``.player/node_modules`` (never copied into
the repository); ``player_files`` publishes the page with the parts of it the page loads (three.module.min.js,
DRACOLoader, OrbitControls, the Draco decoder) beside it, so the output folder plays offline from any static
web server (``python3 -m http.server`` in it: browsers load ES modules over http, not from file://).
"""
from __future__ import annotations

import json
import os
from pathlib import Path

from nodegraph import NodeError

HERE = Path(__file__).resolve().parent
THREE_VERSION = "0.170.0"
LIBS = {"three.module.min.js": "build/three.module.min.js", "DRACOLoader.js": "examples/jsm/loaders/DRACOLoader.js",
        "OrbitControls.js": "examples/jsm/controls/OrbitControls.js",
        "draco/draco_decoder.wasm": "examples/jsm/libs/draco/draco_decoder.wasm",
        "draco/draco_wasm_wrapper.js": "examples/jsm/libs/draco/draco_wasm_wrapper.js",
        "draco/draco_decoder.js": "examples/jsm/libs/draco/draco_decoder.js"}


def three_dir() -> Path:
    """Where setup.sh installed three.js ($VOLCAP_THREE overrides)."""
    return Path(os.environ.get("VOLCAP_THREE") or HERE.parents[1] / ".player" / "node_modules" / "three")


def player_files(name: str, rungs: list[str]) -> dict[str, bytes]:
    """The page, its script, rungs.json and the three.js parts it loads, under ``name/``."""
    root = three_dir()
    version = json.loads((root / "package.json").read_text()).get("version") if (root / "package.json").is_file() else None
    if version != THREE_VERSION:
        raise NodeError(f"export.player: three.js {THREE_VERSION} is not installed at {root} (found {version}): run "
                        f"./setup.sh (npm install three@{THREE_VERSION} in .player/) or set VOLCAP_THREE")
    files = {f"{name}/index.html": (HERE / "player" / "index.html").read_bytes(),
             f"{name}/player.js": (HERE / "player" / "player.js").read_bytes(),
             f"{name}/rungs.json": json.dumps(list(rungs)).encode()}
    for dst, src in LIBS.items():
        files[f"{name}/lib/{dst}"] = (root / src).read_bytes()
    return files
