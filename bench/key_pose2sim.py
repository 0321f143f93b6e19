"""Keying real footage with neither a green screen nor a plate (pose2sim_single: 4 colour videos of a man on a
treadmill in a cluttered lab, other people in two views), every route in the same run, judged by the 4 views'
consensus: each route's mattes carve a 4-view hull (automatic box, floor), and each view's matte is compared with
that hull's silhouette (IoU; what only some views believe is foreground lowers it), plus each route's agreement
with the learned person matte.

Routes: a plate from the footage (key.plate: per-pixel median over 20 frames spread over the 100, with its coverage
report) then key.difference; the mixture learnt from the footage itself (capture.background over the same frames:
components a moving subject leaves below 10 % of the frames are not background); the learned person matte
(key.person: MediaPipe Pose segmentation, its model inside the mediapipe 0.10.14 wheel); each followed by
key.cleanup (largest part, holes filled). Draws docs/key_pose2sim.jpg: every view's matte over frame 0, one row
per route; and docs/keypoints_pose2sim.jpg: the 33 body landmarks triangulated from the four views
(skeleton.keypoints) reprojected into each, beside each view's own landmarks.

    python bench/key_pose2sim.py [--frame 0]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from machine import describe, load_average  # noqa: E402

from nodegraph.testing import run_node  # noqa: E402

ROOT = Path(os.environ.get("VOLCAP_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")) / "pose2sim_single"
DOCS = Path(__file__).resolve().parent.parent / "docs"


def iou(a, b) -> float:
    a, b = np.asarray(a) > 127, np.asarray(b) > 127
    return float((a & b).sum() / max((a | b).sum(), 1))


def consensus(masks, cameras):
    """Per view the IoU of the matte with the silhouette of the hull all four mattes carve."""
    from nodegraph import NodeError

    try:
        bounds = run_node("bounds", {"masks": masks, "cameras": cameras})["bounds"]
    except NodeError:          # the mattes' cones do not meet: no hull at all
        return {"mean_iou": 0.0, "min_iou": 0.0}, None
    vol = run_node("hull", {"masks": masks, "cameras": cameras, "bounds": bounds},
                   {"resolution": 128, "floor": True})["volume"]
    mesh = run_node("mc", {"volume": vol}, {"largest": True})["mesh"]
    if len(mesh.faces) == 0:   # the mattes agree nowhere: no hull
        return {"mean_iou": 0.0, "min_iou": 0.0}, mesh
    score = run_node("eval.silhouette", {"mesh": mesh, "cameras": cameras, "masks": masks})["report"]
    return score, mesh


def opencv_pairs(kp, cams) -> np.ndarray:
    """The baseline a user would write: per landmark cv2.triangulatePoints on the two views that see it most
    confidently, from undistorted normalised points."""
    import cv2

    names = cams.names
    per = {n: np.array(c["points"]) for n, c in kp["cameras"].items() if c["found"]}
    norm = {}
    for n, p in per.items():
        c = cams[names.index(n)]
        norm[n] = cv2.undistortPoints(p[:, None, :2].astype(np.float64), c.K, c.dist)[:, 0, :]
    out = np.full((len(kp["landmarks"]), 3), np.nan)
    for j in range(len(out)):
        order = sorted(per, key=lambda n: -per[n][j, 2])[:2]
        if len(order) < 2:
            continue
        a, b = (cams[names.index(n)] for n in order)
        X = cv2.triangulatePoints(a.Rt, b.Rt, norm[order[0]][j:j + 1].T, norm[order[1]][j:j + 1].T)
        out[j] = X[:3, 0] / X[3, 0]
    return out


def reprojection(X, kp, cams, min_visibility=0.5) -> np.ndarray:
    """Pixel distances from each 3D point's projection to the landmark of every view that sees it."""
    errs = []
    for n, c in kp["cameras"].items():
        if not c["found"]:
            continue
        p = np.array(c["points"])
        uv = cams.project(np.nan_to_num(X), cams.names.index(n))[0]
        ok = (p[:, 2] >= min_visibility) & np.isfinite(X).all(1)
        errs.extend(np.linalg.norm(uv[ok] - p[ok, :2], axis=1))
    return np.array(errs)


def main():
    import cv2

    ap = argparse.ArgumentParser()
    ap.add_argument("--frame", type=int, default=0)
    args = ap.parse_args()
    print(describe())
    frames = list(range(0, 100, 5))
    t = time.perf_counter()
    caps = {f: run_node("capture", params={"path": str(ROOT)}, frame=f) for f in sorted(set(frames) | {args.frame})}
    cap = caps[args.frame]
    cams, names = cap["cameras"], cap["images"].names
    print(f"read {len(caps)} frames x 4 videos in {time.perf_counter() - t:.1f} s")
    plate = run_node("key.plate", {"images": [caps[f]["images"] for f in frames]}, {}, frames=frames)
    print("key.plate coverage (share of pixels that showed one background in half the frames):",
          {n: c["stable"] for n, c in plate["report"]["cameras"].items()})
    t = time.perf_counter()
    mix = run_node("capture.background", {}, {"path": str(ROOT), "background": "videos/cam{cam1:02d}.mp4",
                                                "frames": len(frames)})
    print(f"capture.background over the footage: {time.perf_counter() - t:.1f} s; several backgrounds:",
          {n: c["several_backgrounds"] for n, c in mix["report"]["cameras"].items()})
    routes = {
        "plate from the footage + key.difference":
            lambda: run_node("key.difference", {"images": cap["images"], "background": plate["background"]})["masks"],
        "mixture from the footage + key.difference":
            lambda: run_node("key.difference", {"images": cap["images"], "model": mix["model"]})["masks"],
        "key.person (MediaPipe Pose segmentation)":
            lambda: run_node("key.person", {"images": cap["images"]})["masks"],
    }
    results = {}
    for name, fn in routes.items():
        fn()
        t = time.perf_counter()
        raw = fn()
        ms = 1000 * (time.perf_counter() - t)
        masks = run_node("key.cleanup", {"masks": raw})["masks"]
        score, _ = consensus(masks, cams)
        results[name] = (masks, score, ms)
    person = results["key.person (MediaPipe Pose segmentation)"][0]
    print(f"\nframe {args.frame}: consensus = IoU of each view's matte with the 4-view hull's silhouette")
    print(f"{'route':44s} {'consensus mean':>14s} {'worst':>6s} {'area %':>7s} {'IoU vs person':>13s} {'ms (4 views)':>12s}")
    for name, (masks, score, ms) in results.items():
        area = 100 * np.mean([(m > 127).mean() for m in masks.masks])
        agree = np.mean([iou(a, b) for a, b in zip(masks.masks, person.masks)])
        print(f"{name:44s} {score['mean_iou']:14.3f} {score['min_iou']:6.3f} {area:7.2f} {agree:13.3f} {ms:12.0f}")
    rows = []
    for name, (masks, _, _) in results.items():
        tiles = []
        for v in range(len(names)):
            im = cap["images"].images[v][:, :1080].copy()
            m = masks.masks[v][:, :1080] > 127
            im[m] = (0.45 * im[m] + 0.55 * np.array([40, 220, 60])).astype(np.uint8)
            tile = cv2.resize(im, (270, 480), interpolation=cv2.INTER_AREA)
            cv2.putText(tile, names[v], (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2)
            tiles.append(tile)
        row = np.hstack(tiles)
        label = np.full((28, row.shape[1], 3), 24, np.uint8)
        cv2.putText(label, name, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1)
        rows.append(np.vstack([label, row]))
    DOCS.mkdir(exist_ok=True)
    cv2.imwrite(str(DOCS / "key_pose2sim.jpg"), np.vstack(rows)[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 85])
    print(f"\nwrote {DOCS / 'key_pose2sim.jpg'}")

    # the 33 landmarks triangulated from the 4 views (skeleton.keypoints), reprojected: green the 3D point, red
    # each view's own 2D landmark (their gap is the triangulation's disagreement)
    kp = run_node("key.person", {"images": cap["images"]})["keypoints"]
    run_node("skeleton.keypoints", {"keypoints": kp, "cameras": cams})
    t = time.perf_counter()
    pts = run_node("skeleton.keypoints", {"keypoints": kp, "cameras": cams})["points"]
    ms = 1000 * (time.perf_counter() - t)
    t = time.perf_counter()
    base = opencv_pairs(kp, cams)
    ms_cv = 1000 * (time.perf_counter() - t)
    rms = [r for r in pts["rms_px"] if r is not None]
    X = np.array([p if p is not None else [np.nan] * 3 for p in pts["points"]])
    print(f"skeleton.keypoints: {np.isfinite(X).all(1).sum()} of 33 landmarks in 3D, reprojection median "
          f"{np.median(rms):.1f} px, max {max(rms):.1f} px, {ms:.1f} ms")
    print(f"baseline cv2.triangulatePoints on the two most confident views (undistorted): reprojection over every "
          f"view that sees it, median {np.median(reprojection(base, kp, cams)):.1f} px, max "
          f"{np.max(reprojection(base, kp, cams)):.1f} px, {ms_cv:.1f} ms; ours on the same views: median "
          f"{np.median(reprojection(X, kp, cams)):.1f} px (the baseline fits two views exactly)")
    held = {"ours": [], "cv2 pair": []}      # leave one view out: triangulate from the other three, reproject into it
    for out_view in names:
        rest = {**kp, "cameras": {n: c for n, c in kp["cameras"].items() if n != out_view}}
        only = {**kp, "cameras": {out_view: kp["cameras"][out_view]}}
        ours = run_node("skeleton.keypoints", {"keypoints": rest, "cameras": cams})["points"]["points"]
        held["ours"].extend(reprojection(np.array([q if q is not None else [np.nan] * 3 for q in ours]), only, cams))
        held["cv2 pair"].extend(reprojection(opencv_pairs(rest, cams), only, cams))
    print("leave one view out (3 views triangulate, the 4th judges), px: " + "; ".join(
        f"{k} median {np.median(v):.1f}, p90 {np.percentile(v, 90):.1f}, max {np.max(v):.1f}" for k, v in held.items()))
    L = {n: i for i, n in enumerate(pts["landmarks"])}
    bones = [(f"{s}_{a}", f"{s}_{b}") for s in ("left", "right") for a, b in
             (("shoulder", "elbow"), ("elbow", "wrist"), ("hip", "knee"), ("knee", "ankle"), ("ankle", "heel"),
              ("heel", "foot_index"), ("shoulder", "hip"))] + [("left_shoulder", "right_shoulder"),
                                                                 ("left_hip", "right_hip")]
    X = np.array([p if p is not None else [np.nan] * 3 for p in pts["points"]])
    tiles = []
    for v, name in enumerate(names):
        im = cap["images"].images[v][:, :1080].copy()
        uv = cams.project(np.nan_to_num(X), v)[0]
        own = np.array(kp["cameras"][name]["points"] or np.zeros((33, 3)))
        for a, b in bones:
            if np.isfinite(X[L[a]]).all() and np.isfinite(X[L[b]]).all():
                cv2.line(im, tuple(int(c) for c in uv[L[a]]), tuple(int(c) for c in uv[L[b]]), (40, 230, 60), 5)
        for j in range(len(X)):
            if np.isfinite(X[j]).all():
                cv2.circle(im, tuple(int(c) for c in own[j, :2]), 7, (230, 40, 40), -1)
                cv2.circle(im, tuple(int(c) for c in uv[j]), 9, (40, 230, 60), 2)
        tile = cv2.resize(im, (360, 640), interpolation=cv2.INTER_AREA)
        cv2.putText(tile, name, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 2)
        tiles.append(tile)
    cv2.imwrite(str(DOCS / "keypoints_pose2sim.jpg"), np.hstack(tiles)[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 85])
    print(f"wrote {DOCS / 'keypoints_pose2sim.jpg'}")
    print(f"load average at the end: {load_average()}")


if __name__ == "__main__":
    main()
