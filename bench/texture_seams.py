"""Seams before and after levelling: colour jumps across atlas seams vs inside charts in the baked texture, and
how much the two views of a view seam disagree where they meet (raw, with per-camera gains, with gains and
seam levelling).

    python3 bench/texture_seams.py          # thu_wd_human (graph mesh, 20 views) and a synthetic figure whose
                                            # cameras have vignetting / brightness ramps
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from nodegraph.testing import run_node  # noqa: E402
from nodes.texture import views as V  # noqa: E402
from nodes.texture.quality import seam_jumps, uneven_shading, view_seam_disagreement  # noqa: E402
from nodes.texture.texturing import Settings, texture_mesh  # noqa: E402


def uneven_figure():
    s = run_node("synth", {}, {"scene": "figure", "cameras": 12, "width": 640, "height": 480, "shadow": False})
    return s["mesh"], uneven_shading(s["images"].images), s["masks"].masks, s["cameras"]


def main():
    from texture_loo import load_dataset

    from machine import describe

    print(describe())
    cases = [("synthetic figure, uneven cameras", uneven_figure())]
    mesh, images, masks, cams = load_dataset("thu_wd_human", Path("/tmp/volcap_texture_loo/cache"))
    cases.append(("thu_wd_human", (mesh, images.images, masks.masks, cams)))
    print("| scene | settings | jump across atlas seams | jump inside charts | view-seam disagreement |")
    print("|---|---|---|---|---|")
    for name, (m, imgs, msk, cm) in cases:
        frame = V.FrameImages.build(imgs, msk, 1)
        for label, st in (("raw: no gains, no levelling, no cross-fade", Settings(size=2048, balance=False, level=False, feather=0)),
                          ("gains only", Settings(size=2048, level=False)),
                          ("gains + levelling + cross-fade (default)", Settings(size=2048))):
            r = texture_mesh(m.vertices, m.faces, imgs, msk, cm, st)
            j = seam_jumps(r, m.faces)
            d = view_seam_disagreement(r, m.vertices, m.faces, cm, frame, corrected=not label.startswith("raw"))
            print(f"| {name} | {label} | {j['atlas_seams']:.2f} ({j['n_atlas_seams']} edges) | {j['inside']:.2f} | "
                  f"{d['view_seam_disagreement']:.2f} ({d['edges']} edges) |", flush=True)


if __name__ == "__main__":
    main()
