"""Keying on real captures, at the numbers of issue 4: the green dome keyed from its images alone against
its shipped masks (graphs/datasets/thu_wd_human_key.yaml), the blue-screen dino against a careful hand
threshold (graphs/datasets/oxford_dino.yaml), and the background-plate room whose four difference-keyed
masks must carve one solid body (graphs/datasets/uu_infomcv_seated.yaml)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nodegraph.cache import Cache
from nodegraph.executors import LocalExecutor
from nodegraph.graphfile import load_graph
from nodegraph.run import run_graph
from nodes.capture.load import load_capture, read_image

ROOT = Path(__file__).resolve().parents[3]
GRAPHS = ROOT / "graphs" / "datasets"


def iou(a, b) -> float:
    a, b = np.asarray(a) > 127, np.asarray(b) > 127
    return float((a & b).sum() / max((a | b).sum(), 1))


def run_dataset_graph(name: str, tmp_path, data_dir, monkeypatch, overrides=(), frames=None):
    """Run graphs/datasets/NAME.yaml on the real data; return the run's records by node name (frame 0)."""
    monkeypatch.setenv("VOLCAP_DATA", str(data_dir))
    g = load_graph(GRAPHS / f"{name}.yaml", overrides=list(overrides), frames=frames)
    res = run_graph(g, Cache(tmp_path / "cache"), tmp_path / "out", LocalExecutor(1), progress=False)
    assert res.ok, res.failures
    return res


def exported_masks(res, node: str, frame: int = 0) -> list[np.ndarray]:
    """The PNG masks an export.masks node published for one frame, in camera order."""
    files = [Path(p) for r in res.records if r["node"] == node and r["frame"] == frame for p in r["published"]]
    assert files, f"node {node} published nothing for frame {frame}"
    by_cam = sorted(files, key=lambda p: int(p.parent.name) if p.parent.name.isdigit() else p.parent.name)
    return [read_image(p) for p in by_cam]


@pytest.mark.slow
@pytest.mark.realdata
def test_thu_chroma_key_matches_shipped_masks(dataset_run, real_capture):
    res = dataset_run("thu_wd_human_key", ("hull.resolution=64",))
    keyed = exported_masks(res, "mattes")
    shipped = real_capture("thu_wd_human")["masks"].masks
    assert len(keyed) == len(shipped) == 20
    scores = [iou(k, s) for k, s in zip(keyed, shipped)]
    assert np.mean(scores) >= 0.95, np.round(scores, 3)
    assert min(scores) >= 0.9, np.round(scores, 3)


def hand_blue_threshold(rgb: np.ndarray) -> np.ndarray:
    """The dataset's careful hand key (data README): B < (R + G) / 2, largest 8-connected blob."""
    import cv2

    c = rgb.astype(np.int32)
    m = (2 * c[..., 2] < c[..., 0] + c[..., 1]).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    return np.where(labels == 1 + np.argmax(stats[1:, cv2.CC_STAT_AREA]), 255, 0).astype(np.uint8)


@pytest.mark.slow
@pytest.mark.realdata
def test_oxford_dino_blue_key_matches_hand_threshold(tmp_path, data_dir, monkeypatch):
    res = run_dataset_graph("oxford_dino", tmp_path, data_dir, monkeypatch,
                            overrides=["bounds.resolution=32", "hull.resolution=32"])
    keyed = exported_masks(res, "mattes")
    images = load_capture(data_dir / "oxford_dino")["images"].images
    assert len(keyed) == len(images) == 36
    scores = [iou(k, hand_blue_threshold(im)) for k, im in zip(keyed, images)]
    assert np.mean(scores) >= 0.98, np.round(scores, 3)
    assert min(scores) >= 0.97, np.round(scores, 3)  # views 30 and 33 were 0.78 before


@pytest.mark.realdata
def test_uu_difference_key_carves_one_body(tmp_path, data_dir, monkeypatch):
    from scipy import ndimage

    res = run_dataset_graph("uu_infomcv_seated", tmp_path, data_dir, monkeypatch, overrides=["hull.resolution=64"],
                            frames="0:1")
    masks = exported_masks(res, "mattes")
    assert len(masks) == 4
    for m in masks:  # one seated person (and chair) per view, not the room
        assert 0.01 < (m > 127).mean() < 0.15
    npz = [Path(p) for r in res.records if r["node"] == "voxels" for p in r["published"]]
    vol = np.load(npz[0])
    occ = vol["occupancy"] > 0
    labels, n = ndimage.label(occ)
    sizes = np.bincount(labels.ravel())[1:]
    assert sizes.max() >= 0.999 * occ.sum(), sorted(sizes)[-3:]  # one body; at most a few stray voxels
    assert (sizes > 0.001 * occ.sum()).sum() == 1
    assert 0.03 < occ.mean() < 0.3, occ.mean()  # the SOURCE.md check found 20% at 64^3
    idx = np.argwhere(labels == 1 + np.argmax(sizes))
    extent_mm = 1000 * (idx.max(0) - idx.min(0) + 1) * (vol["bbox_max"] - vol["bbox_min"]) / np.array(occ.shape)
    assert 500 < extent_mm[0] < 1400 and 500 < extent_mm[1] < 1400, extent_mm  # person + chair on the floor
    assert 1200 < extent_mm[2] < 2100, extent_mm  # seated height plus the four-view ghost elongation
    lo = vol["bbox_min"] + idx.min(0) * (vol["bbox_max"] - vol["bbox_min"]) / np.array(occ.shape)
    assert -0.1 - 1e-9 <= lo[2] < 0.02, lo   # the world frame: metres, +Z up, on the floor (the 4-view hull reaches
                                             # 84 mm below it, SOURCE.md; the box stops it at 0.1 m)


@pytest.mark.realdata
def test_uu_plate_from_footage_differs_from_the_shipped_plate_where_the_subject_sits(data_dir):
    """Utrecht's seated person barely moves: key.plate's median over 10 frames matches the shipped plate except on
    5-13 % of the pixels, most of them (>= 65 %) on the subject (its difference-key mask, dilated 7 px); the rest
    is the light of another recording. The report cannot tell a still subject from background: stable > 0.99."""
    import cv2

    from nodegraph.testing import run_node

    frames = list(range(0, 420, 42))
    caps = [run_node("capture", params={"path": str(data_dir / "uu_infomcv_seated")}, frame=f) for f in frames]
    out = run_node("key.plate", {"images": [c["images"] for c in caps]}, {}, frames=frames)
    keyed = run_node("key.difference", {"images": caps[0]["images"], "background": caps[0]["background"]})["masks"]
    for v, name in enumerate(caps[0]["images"].names):
        ours, shipped = (x.images[v].astype(int) for x in (out["background"], caps[0]["background"]))
        diff = np.abs(ours - shipped).max(-1) > 12
        subject = cv2.dilate((keyed.masks[v] > 127).astype(np.uint8), np.ones((15, 15), np.uint8)) > 0
        assert 0.02 < diff.mean() < 0.15 and (diff & subject).sum() / diff.sum() >= 0.65, (name, diff.mean())
        assert out["report"]["cameras"][name]["stable"] > 0.99


@pytest.mark.realdata
def test_uu_mixture_from_the_plate_video_keys_less_of_the_empty_room(data_dir):
    """capture.background on Utrecht's empty-room videos (24 of ~132 frames): on empty frames it did not learn from,
    no pixel is keyed (one plate frame: up to 0.03 %); on the footage the ceiling (top 30 %, no subject) keys less
    than against the one shipped plate in every view (the footage is another recording: shift covers edges)."""
    from nodegraph.testing import run_node
    from nodes.capture.load import load_capture, read_image
    from nodes.common.types import ImageSet

    root = data_dir / "uu_infomcv_seated"
    out = run_node("capture.background", {}, {"path": str(root)})
    used = out["report"]["frames_used"]
    assert len(used) == 24 and used[-1] >= 120
    cap = load_capture(root, 0)
    names = cap["images"].names
    for f in (67, 101, 130):
        assert f not in used
        empty = ImageSet([read_image(root / n / "background.avi", f)[..., :3].copy() for n in names], names)
        mix = run_node("key.difference", {"images": empty, "model": out["model"]})["masks"]
        assert max((m > 127).mean() for m in mix.masks) < 1e-4
    one = run_node("key.difference", {"images": cap["images"], "background": cap["background"]})["masks"]
    mix = run_node("key.difference", {"images": cap["images"], "model": out["model"]})["masks"]
    for v, name in enumerate(names):
        top = slice(0, int(0.3 * one.masks[v].shape[0]))
        assert (mix.masks[v][top] > 127).mean() < (one.masks[v][top] > 127).mean(), name
        assert 0.01 < (mix.masks[v] > 127).mean() < 0.1, name
