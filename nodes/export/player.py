"""The stream player: a small web page on three.js that plays a volcap-stream ladder (stream.py) with
scrubbing, a play button and a rung selector (player/index.html, player/player.js); and the view-dependent
viewer (player/views.html, views.js) that export.views writes beside a frame's layers: its textured mesh
blended per fragment by the viewing direction, as nodes/common/viewlayers.py layer_weights says.

three.js is a pinned npm package that ``setup.sh`` installs into ``.player/node_modules`` (never copied into
the repository); ``player_files`` publishes the page with the parts of it the page loads (three.module.min.js,
DRACOLoader, OrbitControls, the Draco decoder) beside it, so the output folder plays offline from any static
web server (``python3 -m http.server`` in it: browsers load ES modules over http, not from file://).
"""
from __future__ import annotations

import json
import os
from pathlib import Path


HERE = Path(__file__).resolve().parent
THREE_VERSION = "0.170.0"
LIBS = {"three.module.min.js": "build/three.module.min.js", "DRACOLoader.js": "examples/jsm/loaders/DRACOLoader.js",
        "OrbitControls.js": "examples/jsm/controls/OrbitControls.js",
        "draco/draco_decoder.wasm": "examples/jsm/libs/draco/draco_decoder.wasm",
        "draco/draco_wasm_wrapper.js": "examples/jsm/libs/draco/draco_wasm_wrapper.js",
        "draco/draco_decoder.js": "examples/jsm/libs/draco/draco_decoder.js"}


def _version(root: Path) -> str | None:
    try:
        return json.loads((root / "package.json").read_text()).get("version")
    except (OSError, ValueError):
        return None


def three_dir() -> tuple[Path | None, list[str]]:
    """(where three.js THREE_VERSION is, the places looked at): $VOLCAP_THREE, else the checkout's .player/ (where
    setup.sh installs it), else the working folder's .player/."""
    env = os.environ.get("VOLCAP_THREE")
    places = [Path(env)] if env else [HERE.parents[1] / ".player" / "node_modules" / "three",
                                      Path.cwd() / ".player" / "node_modules" / "three"]
    for root in places:
        if _version(root) == THREE_VERSION:
            return root, [str(p) for p in places]
    return None, [f"{p} ({_version(p) or 'absent'})" for p in places]


def player_files(name: str, rungs: list[str]) -> tuple[dict[str, bytes], str | None]:
    """(files, warning): the page, its script, rungs.json and the three.js parts it loads, under ``name/``; without
    three.js the page and a warning saying how to complete it (the viewer is optional: a run does not fail)."""
    files = {f"{name}/index.html": (HERE / "player" / "index.html").read_bytes(),
             f"{name}/player.js": (HERE / "player" / "player.js").read_bytes(),
             f"{name}/camera.js": (HERE / "player" / "camera.js").read_bytes(),
             f"{name}/rungs.json": json.dumps(list(rungs)).encode()}
    return _with_three(files, name, LIBS)


def views_files(folder: str) -> tuple[dict[str, bytes], str | None]:
    """(files, warning): the view-dependent viewer's page (index.html), its scripts and the three.js parts it loads,
    under ``folder/``, to sit beside export.views' layers, mesh.bin and base.png."""
    files = {f"{folder}/index.html": (HERE / "player" / "views.html").read_bytes(),
             f"{folder}/views.js": (HERE / "player" / "views.js").read_bytes(),
             f"{folder}/camera.js": (HERE / "player" / "camera.js").read_bytes()}
    return _with_three(files, folder, {k: v for k, v in LIBS.items() if k in ("three.module.min.js", "OrbitControls.js")})


def _with_three(files: dict, folder: str, libs: dict) -> tuple[dict[str, bytes], str | None]:
    root, looked = three_dir()
    if root is None:
        return files, (f"three.js {THREE_VERSION} not found ({'; '.join(looked)}): the page {folder}/index.html is "
                       f"written without its lib/ folder; run ./setup.sh (npm install three@{THREE_VERSION} in .player/) "
                       "or set VOLCAP_THREE, then run again")
    for dst, src in libs.items():
        files[f"{folder}/lib/{dst}"] = (root / src).read_bytes()
    return files, None
