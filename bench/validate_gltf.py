"""The Khronos glTF validator on GLB files: errors, warnings, infos and the first messages, per file.

    npm install --prefix .player gltf-validator@2.0.0-dev.3.10      # beside the player's three.js (not part of setup)
    python3 bench/validate_gltf.py out/demo/*.glb [more.glb ...]

Runs the validator's own JavaScript API (validateBytes) with node; exits 1 when any file has an error or a
warning, so a pipeline can gate on it.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

SCRIPT = """
const v = require(process.argv[1]); const fs = require('fs');
(async () => { const out = [];
  for (const f of process.argv.slice(2)) {
    const r = await v.validateBytes(new Uint8Array(fs.readFileSync(f)), {maxIssues: 20});
    out.push({file: f, errors: r.issues.numErrors, warnings: r.issues.numWarnings, infos: r.issues.numInfos,
              messages: r.issues.messages.slice(0, 5).map(m => `${m.code} ${m.pointer || ''}`)});
  }
  console.log(JSON.stringify(out));
})();
"""


def main():
    from machine import describe

    print(describe())
    module = ROOT / ".player" / "node_modules" / "gltf-validator"
    if not module.is_dir():
        raise SystemExit(f"gltf-validator not installed at {module}: npm install --prefix .player gltf-validator@2.0.0-dev.3.10")
    version = json.loads((module / "package.json").read_text())["version"]
    files = [str(Path(f).resolve()) for f in sys.argv[1:]]
    res = subprocess.run(["node", "-e", SCRIPT, str(module), *files], capture_output=True, text=True, check=True)
    rows = json.loads(res.stdout)
    print(f"Khronos glTF validator {version}")
    print(f"{'file':44s} {'errors':>6s} {'warnings':>8s} {'infos':>5s}  first messages")
    bad = 0
    for r in rows:
        bad += r["errors"] + r["warnings"]
        print(f"{Path(r['file']).name:44s} {r['errors']:6d} {r['warnings']:8d} {r['infos']:5d}  {'; '.join(r['messages'])}")
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
