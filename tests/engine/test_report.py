"""Run report and previews: a small synthetic graph run, its report.html opened in headless Chromium (every
node section present, every image loads), and a preview per data type on tiny values."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import tempfile
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

import enginenodes  # noqa: F401  (t.source for the long-sequence test)
from nodes.common.types import Bounds, CameraSet, Images, ImageSet, Masks, MaskSet, Mesh, MeshSequence, Skeleton, SkeletonData, TexturedMesh, Volume, VoxelGrid
from nodegraph import DataError, Files, Node, NodeError, Param, Table
from nodegraph.cache import Cache
from nodes.common.cameras import Cameras
from rig import ring_rig
from nodegraph.executors import LocalExecutor
from nodegraph.graphfile import load_graph
from nodegraph.preview import preview
from nodegraph.report import MAX_PREVIEW_FRAMES, write_report
from nodegraph.run import run_graph
from nodegraph.types import Array

W, H = 48, 40


def ring(n=4, radius=3.0) -> Cameras:
    """n cameras on a horizontal ring (z up) looking at the origin."""
    return ring_rig(n, W, H, radius=radius, z=0.6, fov=50, name="cam{i:03d}")


def sphere_masks(cams: Cameras, r: float) -> list[np.ndarray]:
    """Exact silhouettes of a sphere of radius r at the origin (pixel centre inside the projected disc)."""
    out = []
    for cam in cams:
        u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
        rays = np.linalg.solve(cam.K, np.stack([u.ravel(), v.ravel(), np.ones(u.size)]))
        d = (cam.Rt[:, :3].T @ rays).T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        c = cam.center
        b = d @ c
        hit = b * b - (c @ c - r * r) >= 0
        out.append((hit.reshape(H, W) * 255).astype(np.uint8))
    return out


# ---------------------------------------------------------------- test nodes (run in-process: jobs=1)
class Scene(Node):
    """A sphere growing with the frame number, seen by a 4-camera ring: images, masks, cameras, box."""

    type_name = "rp.scene"
    uses_frame = True
    outputs = {"images": Images, "masks": Masks, "cameras": CameraSet, "bounds": Bounds}

    def run(self, *, frame):
        cams = ring()
        masks = sphere_masks(cams, 0.5 + 0.1 * frame)
        images = [np.where(m[:, :, None] > 0, np.array([200, 60, 40], np.uint8), np.array([20, 160, 20], np.uint8)) for m in masks]
        return {"images": ImageSet(images, cams.names), "masks": MaskSet(masks, None, cams.names), "cameras": cams,
                "bounds": np.array([[-1.0, -1, -1], [1, 1, 1]])}


class Carve(Node):
    """NumPy visual hull on a small grid."""

    type_name = "rp.carve"
    inputs = {"masks": Masks, "cameras": CameraSet, "bounds": Bounds}
    outputs = {"volume": Volume}
    params = {"resolution": Param(int, 16)}

    def run(self, masks, cameras, bounds, *, resolution):
        grid = VoxelGrid(np.zeros((resolution,) * 3, np.uint8), bounds[0], bounds[1])
        pts = grid.centers().reshape(-1, 3)
        inside = np.ones(len(pts), bool)
        for i, m in enumerate(masks.masks):
            uv, _ = cameras.project(pts, i)
            u, v = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
            ok = (u >= 0) & (u < m.shape[1]) & (v >= 0) & (v < m.shape[0])
            inside &= ok & (m[np.clip(v, 0, m.shape[0] - 1), np.clip(u, 0, m.shape[1] - 1)] > 0)
        grid.occupancy = inside.reshape(grid.occupancy.shape).astype(np.uint8)
        return {"volume": grid}


class Surface(Node):
    """A sphere mesh matching the volume's extent, with a two-bone skeleton inside."""

    type_name = "rp.surface"
    inputs = {"volume": Volume}
    outputs = {"mesh": Mesh, "skeleton": Skeleton}

    def run(self, volume):
        pts = volume.centers()[volume.occupancy > 0]
        r = float(np.abs(pts).max()) if len(pts) else 0.1
        mesh = trimesh.creation.icosphere(subdivisions=2, radius=r)
        joints = np.array([[0, 0, -r * 0.8], [0, 0, 0], [0, 0, r * 0.8]])
        return {"mesh": mesh, "skeleton": SkeletonData(joints, [-1, 0, 1], ["hip", "spine", "head"])}


class Score(Node):
    """Per-view silhouette IoU of the volume's projection against the masks."""

    type_name = "rp.score"
    inputs = {"volume": Volume, "masks": Masks, "cameras": CameraSet}
    outputs = {"table": Table}

    def run(self, volume, masks, cameras):
        pts = volume.centers()[volume.occupancy > 0]
        ious = []
        for i, m in enumerate(masks.masks):
            uv, _ = cameras.project(pts, i)
            drawn = np.zeros_like(m)
            u, v = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
            ok = (u >= 0) & (u < m.shape[1]) & (v >= 0) & (v < m.shape[0])
            drawn[v[ok], u[ok]] = 255
            drawn = cv2.dilate(drawn, np.ones((3, 3), np.uint8))
            a, b = drawn > 0, m > 0
            ious.append(float((a & b).sum() / max((a | b).sum(), 1)))
        return {"table": {"iou_per_view": ious, "iou_mean": float(np.mean(ious)), "voxels": int(len(pts))}}


class Export(Node):
    """Publishes the voxel count as a text file; refuses frame 2 (to show a failure in the report)."""

    type_name = "rp.export"
    uses_frame = True
    publishes = True
    inputs = {"table": Table}
    outputs = {"files": Files}

    def run(self, table, *, frame):
        if frame == 2:
            raise NodeError("frame 2 is refused on purpose")
        return {"files": {f"voxels_{frame:03d}.txt": f"{table['voxels']}\n".encode()}}


class Metric(Node):
    """A per-frame table from an array (for the long-sequence test)."""

    type_name = "rp.metric"
    inputs = {"x": Array}
    outputs = {"table": Table}

    def run(self, x):
        return {"table": {"mean": float(x.mean()), "max": float(x.max())}}


GRAPH = """\
frames: 0:3
nodes:
  scene:  {type: rp.scene}
  carve:  {type: rp.carve, in: {masks: scene.masks, cameras: scene.cameras, bounds: scene.bounds}}
  surface: {type: rp.surface, in: {volume: carve.volume}}
  score:  {type: rp.score, in: {volume: carve.volume, masks: scene.masks, cameras: scene.cameras}}
  export: {type: rp.export, in: {table: score.table}}
"""


def run_to(tmp_path: Path, text: str) -> Path:
    g = tmp_path / "g.yaml"
    g.write_text(textwrap.dedent(text))
    out = tmp_path / "out"
    run_graph(load_graph(g).keep_all(), Cache(tmp_path / "cache"), out, LocalExecutor(1), progress=False)
    return out


def chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        if shutil.which(name):
            return shutil.which(name)
    pytest.fail("headless Chromium not found (install it: `apt-get install -y chromium`; .ci/run does)")


def chromium_run(args: list[str], timeout=90) -> subprocess.CompletedProcess:
    profile = tempfile.mkdtemp(prefix="volcap-chromium-")
    try:
        return subprocess.run([chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                               "--disable-background-networking", "--disable-component-update", "--disable-sync",
                               "--hide-scrollbars", f"--user-data-dir={profile}", *args],
                              capture_output=True, text=True, timeout=timeout)
    finally:
        shutil.rmtree(profile, ignore_errors=True)


IMG_CHECK = """<script>
window.addEventListener('load', () => {
  const pre = document.createElement('pre'); pre.id = 'imgcheck';
  pre.textContent = JSON.stringify([...document.images].map(i => [i.getAttribute('src'), i.complete, i.naturalWidth]));
  document.body.appendChild(pre);
});
</script>"""


def browser_check(report: Path) -> tuple[list, str]:
    """Load a copy of the report (beside it, so relative links hold) with a script that records each image's
    naturalWidth after load; return (src, complete, naturalWidth) rows and the DOM."""
    probe = report.with_name("report_probe.html")
    probe.write_text(report.read_text().replace("</body>", IMG_CHECK + "</body>"))
    res = chromium_run(["--virtual-time-budget=10000", "--dump-dom", probe.as_uri()])
    probe.unlink()
    m = re.search(r'<pre id="imgcheck">(.*?)</pre>', res.stdout, re.S)
    assert m, f"no image check in the DOM: chromium rc {res.returncode}\n{res.stderr[-2000:]}"
    import html
    return json.loads(html.unescape(m.group(1))), res.stdout


# ---------------------------------------------------------------- the report
@pytest.mark.slow
def test_report_opens_in_chromium_with_every_node_and_image(tmp_path):
    out = run_to(tmp_path, GRAPH)
    report = write_report(out)
    assert report == out / "report.html"
    page = report.read_text()
    for node in ("scene", "carve", "surface", "score", "export"):
        assert f'data-node="{node}"' in page
    srcs = re.findall(r'<img src="([^"]+)"', page)
    # graph + per frame: scene images/masks/cameras (bounds folded into cameras), carve volume,
    # surface mesh/skeleton, score table, export files (frames 0, 1); + the score-over-frames plot
    assert len(srcs) == 1 + 3 * 3 + 3 + 3 * 2 + 3 + 2 + 1, srcs
    assert "preview failed" not in page
    assert "frame 2 is refused on purpose" in page
    rec = {(r["node"], r["frame"]): r for r in json.loads((out / "run.json").read_text())["items"]}
    assert Path(rec[("export", 2)]["log"]).is_file()
    assert 'href="logs/export/2.log"' in page
    assert 'href="voxels_000.txt"' in page and (out / "voxels_000.txt").read_text().strip().isdigit()

    rows, dom = browser_check(report)
    assert sorted(r[0] for r in rows) == sorted(srcs)
    broken = [r for r in rows if not (r[1] and r[2] > 0)]
    assert not broken, f"images that did not load: {broken}"
    for node in ("scene", "carve", "surface", "score", "export"):
        assert f'id="node-{node}"' in dom

    shot = tmp_path / "report.png"
    res = chromium_run(["--window-size=1200,1600", f"--screenshot={shot}", report.as_uri()])
    assert shot.is_file(), res.stderr[-2000:]
    img = cv2.imread(str(shot))
    assert img.shape[:2] == (1600, 1200)
    assert img.std() > 20  # a drawn page, not a blank one


@pytest.mark.slow
def test_report_samples_long_sequences_and_plots_metrics(tmp_path):
    out = run_to(tmp_path, """\
        frames: 0:20
        nodes:
          src:    {type: t.source, params: {value: 1.0, size: 3}}
          metric: {type: rp.metric, in: {x: src.out}}
        """)
    page = write_report(out).read_text()
    for node in ("src", "metric"):
        frames = set(re.findall(rf'src="report/{node}/(\d+)_', page))
        assert len(frames) == MAX_PREVIEW_FRAMES, frames
        assert {"0", "19"} <= frames
    assert (out / "report" / "metric" / "metrics_table.png").is_file()
    assert "<details><summary>20 work items</summary>" in page
    # the metrics table shows the sampled frames' values: mean of frame 19 is 1 + 19
    assert re.search(r"<th>mean</th>(<td>[^<]*</td>)*<td>20</td>", page)


def test_report_without_run_record_names_the_folder(tmp_path):
    with pytest.raises(DataError, match=re.escape(str(tmp_path / "run.json"))):
        write_report(tmp_path)


# ---------------------------------------------------------------- previews per type
def saved(tmp_path: Path, dtype, value, name: str) -> Path:
    folder = tmp_path / name
    folder.mkdir()
    dtype.save(value, folder)
    return folder


def draw(dtype_name, folder, tmp_path, size=320, **kw) -> np.ndarray:
    png = preview(dtype_name, folder, tmp_path / f"{folder.name}.png", size=size, **kw)
    assert png is not None
    img = cv2.imread(str(png))[:, :, ::-1]
    assert img.shape[1] <= size
    return img


def test_preview_images_contact_sheet_keeps_each_camera_in_its_tile(tmp_path):
    colours = [(255, 0, 0), (0, 255, 0), (0, 0, 255), (255, 255, 255)]
    images = ImageSet([np.full((30, 40, 3), c, np.uint8) for c in colours])
    img = draw("Images", saved(tmp_path, Images, images, "images"), tmp_path, size=200)
    assert img.shape == (150, 200, 3)  # 2 x 2 tiles of 100 x 75
    for (r, c), colour in zip([(0, 0), (0, 1), (1, 0), (1, 1)], colours):
        assert tuple(img[r * 75 + 60, c * 100 + 50]) == colour


def test_preview_masks_overlay_on_images_and_alone(tmp_path):
    m = np.zeros((40, 40), np.uint8)
    m[10:30, 10:30] = 255
    masks = saved(tmp_path, Masks, MaskSet([m]), "masks")
    images = saved(tmp_path, Images, ImageSet([np.full((40, 40, 3), 200, np.uint8)]), "images")
    over = draw("Masks", masks, tmp_path, size=80, companions={"Images": images})
    assert tuple(over[40, 40]) == (200, 200, 200)       # foreground kept
    assert over[2 * 2 + 20, 2 * 2].max() == 70           # background darkened (200 * 0.35)
    assert (over[..., 0] > 200).sum() > 0 and (over[..., 1] < 80).sum() > 0   # red outline
    alone = draw("Masks", masks, tmp_path, size=80)
    assert tuple(alone[40, 40]) == (255, 255, 255) and tuple(alone[70, 10]) == (0, 0, 0)


@pytest.mark.parametrize("no_vtk", [False, True])
def test_preview_volume_draws_the_occupied_voxels(tmp_path, monkeypatch, no_vtk):
    if no_vtk:
        monkeypatch.setenv("VOLCAP_PREVIEW_NO_VTK", "1")
    occ = np.zeros((12, 12, 12), np.uint8)
    occ[3:9, 3:9, 3:9] = 1
    folder = saved(tmp_path, Volume, VoxelGrid(occ, [0, 0, 0], [1, 1, 1]), "volume")
    img = draw("Volume", folder, tmp_path)
    background = np.median(img.reshape(-1, 3), axis=0)
    drawn = np.abs(img.astype(int) - background).sum(axis=2) > 30
    assert 0.02 < drawn.mean() < 0.6
    empty = saved(tmp_path, Volume, VoxelGrid(np.zeros((4, 4, 4), np.uint8), [0, 0, 0], [1, 1, 1]), "empty")
    assert draw("Volume", empty, tmp_path).shape[1] == 320  # says "empty volume" instead of failing


def test_preview_textured_mesh_shows_its_texture(tmp_path):
    box = trimesh.creation.box()
    plain = draw("Mesh", saved(tmp_path, Mesh, box, "plain"), tmp_path)
    textured = box.copy()
    textured.visual = trimesh.visual.TextureVisuals(uv=np.full((len(box.vertices), 2), 0.5),
                                                    image=__import__("PIL.Image").Image.new("RGB", (4, 4), (0, 0, 255)))
    tex = draw("TexturedMesh", saved(tmp_path, TexturedMesh, textured, "textured"), tmp_path)
    blue = lambda im: ((im[..., 2].astype(int) - im[..., 0]) > 60).mean()  # noqa: E731
    assert blue(tex) > 0.05 and blue(plain) < 0.001


def test_preview_skeleton_over_mesh_and_sequence(tmp_path):
    sk = SkeletonData(np.array([[0, 0, -0.5], [0, 0, 0], [0, 0, 0.5]]), [-1, 0, 1], ["a", "b", "c"])
    mesh = saved(tmp_path, Mesh, trimesh.creation.icosphere(radius=0.7), "mesh")
    img = draw("Skeleton", saved(tmp_path, Skeleton, sk, "skeleton"), tmp_path, companions={"Mesh": mesh})
    red = (img[..., 0].astype(int) - img[..., 2] > 80).mean()
    assert red > 0.001  # joints
    seq = [trimesh.creation.icosphere(radius=r) for r in (0.5, 0.7, 0.9)]
    assert draw("MeshSequence", saved(tmp_path, MeshSequence, seq, "seq"), tmp_path).std() > 10


def test_preview_cameras_bounds_table_array_files(tmp_path):
    cams = saved(tmp_path, CameraSet, ring(), "cameras")
    box = saved(tmp_path, Bounds, np.array([[-1.0, -1, -1], [1, 1, 1]]), "bounds")
    with_box = draw("Cameras", cams, tmp_path, companions={"Bounds": box})
    assert ((with_box[..., 1].astype(int) - with_box[..., 0]) > 60).sum() > 50   # the green box
    assert draw("Bounds", box, tmp_path).std() > 5
    table = saved(tmp_path, Table, {"iou_per_view": [0.9, 0.8, 0.95], "mean": 0.88}, "table")
    assert ((draw("Table", table, tmp_path)[..., 2].astype(int) - 100) > 60).mean() > 0.01  # blue bars
    assert preview("Table", saved(tmp_path, Table, {"note": "text only"}, "texttable"), tmp_path / "t.png") is None
    assert draw("Array", saved(tmp_path, Array, np.arange(10.0), "arr1"), tmp_path).std() > 5
    assert draw("Array", saved(tmp_path, Array, np.eye(8), "arr2"), tmp_path).std() > 5
    assert draw("Files", saved(tmp_path, Files, {"a.txt": b"1", "d/b.bin": b"22"}, "files"), tmp_path).shape[0] == 40


def test_preview_bad_input_names_the_folder(tmp_path):
    folder = tmp_path / "broken"
    folder.mkdir()
    (folder / "volume.npz").write_bytes(b"not a zip")
    with pytest.raises(DataError, match="broken"):
        preview("Volume", folder, tmp_path / "x.png")
    with pytest.raises(DataError, match="no preview for data type 'Nope'"):
        preview("Nope", folder, tmp_path / "x.png")


def test_table_records_become_per_view_series():
    from nodegraph.preview import numeric_series, record_labels

    table = {"mean_iou": 0.6, "views": [{"name": "cam0", "iou": 0.5, "ok": True}, {"name": "cam1", "iou": 0.7, "ok": False}]}
    scalars, lists = numeric_series(table)
    assert scalars == {"mean_iou": 0.6} and lists == {"views.iou": [0.5, 0.7]}
    assert record_labels(table, "views.iou") == ["cam0", "cam1"]
