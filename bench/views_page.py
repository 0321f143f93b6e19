"""The view-dependent viewer (export.views with the frame's mesh) on a real capture, as a browser shows it:
graphs/datasets/thu_wd_human_textured.yaml through the CLI, then its views/ page in headless Chromium at a capture
camera and at an eye halfway to the next one, with the layers and with the atlas alone (the page's static=1).
Prints PSNR against the photo inside the mask at the capture camera; writes the picture.

    python3 bench/views_page.py [--camera 4] [--picture docs/texture_views_thu.jpg]
"""
from __future__ import annotations

import argparse
import base64
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "tests"))

from nodes.common.cameras import look_at  # noqa: E402
from nodes.common.types import CameraSet, Images, Masks  # noqa: E402


def param(cam) -> str:
    return base64.b64encode(json.dumps({"K": cam.K.tolist(), "R": cam.Rt[:, :3].tolist(), "t": cam.Rt[:, 3].tolist(),
                                        "width": cam.width, "height": cam.height}).encode()).decode()


def main():
    import cv2

    from browser import screenshot, serve
    from machine import describe, load_average

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--camera", type=int, default=4)
    ap.add_argument("--picture", default=None)
    args = ap.parse_args()
    print(describe())
    data = os.environ.get("VOLCAP_DATA", str(ROOT.parent / "shared" / "data"))
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "out"
        r = subprocess.run([sys.executable, str(ROOT / "app.py"), "run", str(ROOT / "graphs/datasets/thu_wd_human_textured.yaml"),
                            "--out", str(out), "--cache", str(Path(d) / "cache"), "--keep-all", "--quiet"],
                           env={**os.environ, "VOLCAP_DATA": data, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True)
        if r.returncode != 0:
            raise SystemExit(f"the graph failed: {r.stdout[-600:]} {r.stderr[-600:]}")
        recs = {rec["node"]: Path(rec["cache_dir"]) for rec in json.loads((out / "run.json").read_text())["items"]
                if rec.get("cache_dir")}
        cams = CameraSet.load(recs["capture"] / "cameras")
        photo = Images.load(recs["capture"] / "images").images[args.camera]
        mask = Masks.load(recs["capture"] / "masks").masks[args.camera] > 127
        page = out / "views" / "thu_wd_human_0000"
        mb = (page / "mesh.bin").read_bytes()
        n = int.from_bytes(mb[:4], "little")
        nv = json.loads(mb[4:4 + n])["vertices"]
        centre = np.frombuffer(mb[4 + n:4 + n + 12 * nv], np.float32).reshape(-1, 3).mean(axis=0)
        cam = cams[args.camera]
        fov = 2 * np.degrees(np.arctan(0.5 * cam.height / cam.K[1, 1]))
        nxt = (args.camera + 1) % len(cams)
        between = look_at(0.5 * (cams.centers[args.camera] + cams.centers[nxt]), centre, [0, 0, 1], fov, cam.width,
                          cam.height)
        shots = []
        with serve(page) as url:
            for label, c, extra in ((f"layers at camera {args.camera}", cam, ""),
                                    (f"atlas alone at camera {args.camera}", cam, "&static=1"),
                                    (f"layers between cameras {args.camera} and {nxt}", between, ""),
                                    ("atlas alone there", between, "&static=1")):
                png, title = screenshot(f"{url}/index.html?still=1{extra}&camera={param(c)}", c.width, c.height)
                if title != "ready":
                    raise SystemExit(f"the page: {title}")
                shots.append((label, cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]))
    print(f"\n{describe()}\nthu_wd_human frame 0, the viewer page in headless Chromium (SwiftShader), load {load_average()}")
    print("| render at the capture camera | PSNR vs its photo inside the mask |\n|---|---|")
    for label, im in shots[:2]:
        sel = mask & (im.max(axis=2) > 0)
        err = np.mean((im[sel].astype(float) - photo[sel].astype(float)) ** 2)
        print(f"| {label} | {10 * np.log10(255 ** 2 / err):.2f} dB |")
    if args.picture:
        tiles = [(f"photo, camera {args.camera}", photo)] + shots

        def box(im):
            ys, xs = np.nonzero(im.max(axis=2) > 0)
            return max(ys.min() - 20, 0), ys.max() + 20, max(xs.min() - 20, 0), xs.max() + 20

        boxes = [box(shots[0][1])] * 3 + [box(shots[2][1])] * 2
        row = []
        for (label, im), (y0, y1, x0, x1) in zip(tiles, boxes):
            c = np.ascontiguousarray(im[y0:y1, x0:x1])
            c = cv2.resize(c, (int(c.shape[1] * 420 / c.shape[0]), 420), interpolation=cv2.INTER_AREA)
            cv2.putText(c, label, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 0), 1, cv2.LINE_AA)
            row.append(c)
        cv2.imwrite(args.picture, np.hstack(row)[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 88])
        print(f"picture: {args.picture}")


if __name__ == "__main__":
    main()
