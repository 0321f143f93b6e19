"""The capture node on a synthetic dataset written in the test, its errors, video frames, the bounds node,
and a golden check on the INRIA dancer."""
import os
import re

import cv2
import numpy as np
import pytest

from nodes.common.cameras import Cameras
from rig import ring_rig
from nodegraph.errors import DataError, NodeError
from nodegraph.testing import run_node
from nodegraph.types import Table
from nodes.common.calibration import save_colmap
from nodes.capture.load import load_capture

W, H = 64, 48
CENTRE, RADIUS = np.array([0.2, -0.1, 0.5]), 0.6


def sphere_rig(n=5) -> Cameras:
    return ring_rig(n, W, H, radius=3.0, z=1.0, target=CENTRE, fov=45, dist=[-0.05, 0, 0, 0, 0])


def sphere_mask(cams: Cameras, v: int) -> np.ndarray:
    """Analytic silhouette: pixels whose ray passes within RADIUS of the centre."""
    uu, vv = np.meshgrid(np.arange(W), np.arange(H))
    o, d = cams.rays(v, np.stack([uu.ravel(), vv.ravel()], 1))
    t = ((CENTRE - o) * d).sum(1)
    dist = np.linalg.norm(o + t[:, None] * d - CENTRE, axis=1)
    return np.where(dist < RADIUS, 255, 0).astype(np.uint8).reshape(H, W)


def write_dataset(root, cams):
    """cam{i}/rgb.png, cam{i}/mask.png, cam{i}/plate.png and a COLMAP model in sparse/."""
    save_colmap(cams, root / "sparse")
    for v, c in enumerate(cams):
        m = sphere_mask(cams, v)
        img = np.zeros((H, W, 3), np.uint8)
        img[:] = (40, 180, 60)
        plate = img.copy()
        img[m > 0] = (200, 50 + 10 * v, 30)
        (root / c.name).mkdir(parents=True)
        cv2.imwrite(str(root / c.name / "rgb.png"), img[:, :, ::-1])
        cv2.imwrite(str(root / c.name / "mask.png"), m)
        cv2.imwrite(str(root / c.name / "plate.png"), plate[:, :, ::-1])
    return dict(images="{name}/rgb.png", masks="{name}/mask.png", background="{name}/plate.png", calibration="sparse")


def test_capture_node_on_synthetic_dataset(tmp_path):
    cams = sphere_rig()
    patterns = write_dataset(tmp_path, cams)
    out = run_node("capture", params={"path": str(tmp_path), **patterns, "world": "dataset"}, roundtrip=True)
    assert out["cameras"].names == cams.names and out["world"]["frame"] == "dataset"
    X = np.random.default_rng(0).normal(CENTRE, 0.3, (50, 3))
    for v in range(len(cams)):
        assert np.abs(out["cameras"].project(X, v)[0] - cams.project(X, v)[0]).max() < 1e-6
        assert np.array_equal(out["masks"].masks[v], sphere_mask(cams, v))
        assert tuple(out["images"].images[v][H // 2, 2]) == (40, 180, 60)
        assert tuple(out["background"].images[v][H // 2, W // 2]) == (40, 180, 60)
        assert 0.05 < (out["masks"].masks[v] > 0).mean() < 0.6


def test_capture_errors_name_the_problem(tmp_path):
    cams = sphere_rig()
    patterns = write_dataset(tmp_path, cams)
    with pytest.raises(DataError, match="frame 1 out of range"):
        load_capture(tmp_path, 1, **patterns)
    (tmp_path / "cam2" / "mask.png").unlink()
    with pytest.raises(DataError, match="camera 2 'cam2'.*mask.png not found"):
        load_capture(tmp_path, 0, **patterns)
    cv2.imwrite(str(tmp_path / "cam2" / "mask.png"), np.zeros((H, W), np.uint8))
    (tmp_path / "cam3" / "rgb.png").write_bytes(b"not a png")
    with pytest.raises(DataError, match="cam3/rgb.png: unreadable"):
        load_capture(tmp_path, 0, **patterns)
    cv2.imwrite(str(tmp_path / "cam3" / "rgb.png"), np.zeros((H // 2, W // 2, 3), np.uint8))
    with pytest.raises(DataError, match="camera 3 'cam3'.*32x24 but the calibration is for 64x48"):
        load_capture(tmp_path, 0, **patterns)
    cv2.imwrite(str(tmp_path / "cam3" / "rgb.png"), np.zeros((H, W, 3), np.uint8))
    (tmp_path / "cam5").mkdir()
    cv2.imwrite(str(tmp_path / "cam5" / "rgb.png"), np.zeros((H, W, 3), np.uint8))
    with pytest.raises(DataError, match="6 camera folders .* 5 cameras"):
        load_capture(tmp_path, 0, **patterns)
    with pytest.raises(NodeError, match="pattern '{camera}/rgb.png'"):
        load_capture(tmp_path, 0, **{**patterns, "images": "{camera}/rgb.png"})
    with pytest.raises(DataError, match="not found"):
        load_capture(tmp_path / "nowhere")


def test_generic_folder_matches_images_by_camera_name(tmp_path):
    """An unknown layout: calibration + images/ matched by camera name; when only some images are named
    after cameras, the missing camera is named (matching the rest by order would swap views silently)."""
    cams = sphere_rig(3)
    save_colmap(cams, tmp_path)
    (tmp_path / "images").mkdir()
    for v, c in enumerate(cams):
        cv2.imwrite(str(tmp_path / "images" / f"{c.name}.png"), np.full((H, W, 3), 50 + v, np.uint8))
    out = load_capture(tmp_path)
    assert [int(im[0, 0, 0]) for im in out["images"].images] == [50, 51, 52]
    (tmp_path / "images" / "cam1.png").rename(tmp_path / "images" / "zz_extra.png")
    with pytest.raises(DataError, match="no image named after camera\\(s\\) 1 'cam1'"):
        load_capture(tmp_path)
    for i, f in enumerate(sorted((tmp_path / "images").iterdir())):   # no file named after a camera: by order
        f.rename(tmp_path / "images" / f"view_{i}.png")
    assert [int(im[0, 0, 0]) for im in load_capture(tmp_path)["images"].images] == [50, 52, 51]


def test_mask_size_error_names_both_files(tmp_path):
    cams = sphere_rig(3)
    patterns = write_dataset(tmp_path, cams)
    cv2.imwrite(str(tmp_path / "cam1" / "mask.png"), np.zeros((H, W - 4), np.uint8))
    with pytest.raises(DataError, match=r"camera 1 'cam1': mask \S*cam1/mask.png is 60x48 but the image \S*cam1/rgb.png is 64x48"):
        load_capture(tmp_path, 0, **patterns)


def test_image_files_come_back_rgb(tmp_path):
    """read_image turns the file's BGR / BGRA into RGB / RGBA (16-bit to its high byte), grey stays grey."""
    from nodes.capture import load as L

    rng = np.random.default_rng(1)
    for name, img in (("c3.png", rng.integers(0, 256, (37, 53, 3), dtype=np.uint8)),
                      ("c4.png", rng.integers(0, 256, (37, 53, 4), dtype=np.uint8)),
                      ("g.png", rng.integers(0, 256, (37, 53), dtype=np.uint8)),
                      ("w16.png", rng.integers(0, 65536, (9, 11, 3), dtype=np.uint16))):
        assert cv2.imwrite(str(tmp_path / name), img)
        got = L.read_image(tmp_path / name)
        want = (img >> 8).astype(np.uint8) if img.dtype == np.uint16 else img
        want = want if want.ndim == 2 else want[:, :, [2, 1, 0, 3][: want.shape[2]]]
        assert got.dtype == np.uint8 and got.flags["C_CONTIGUOUS"] and np.array_equal(got, want), name
    # a colour video, read a frame at a time and as plate frames (decoded front to back): red stays red
    vw = cv2.VideoWriter(str(tmp_path / "red.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 10, (64, 48))
    for _ in range(4):
        vw.write(np.full((48, 64, 3), (20, 60, 230), np.uint8))        # BGR: a red with a little green and blue
    vw.release()
    plates, picked = L._plates(tmp_path, "red.mp4", [(0, "c")], {}, 2)
    for im in (L.read_image(tmp_path / "red.mp4", 1), plates[0].images[0]):
        mean = im.reshape(-1, 3).mean(axis=0)
        assert np.all(np.abs(mean - (230, 60, 20)) < 12), mean


def test_video_frames_and_star_patterns(tmp_path):
    """Frame N of a video pattern is the N-th frame; '*' patterns index sorted files."""
    cams = sphere_rig(2)
    save_colmap(cams, tmp_path)
    for c in cams:
        (tmp_path / c.name).mkdir()
        vw = cv2.VideoWriter(str(tmp_path / c.name / "video.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10, (W, H))
        for f in range(4):
            vw.write(np.full((H, W, 3), 40 * f + 20, np.uint8))
            cv2.imwrite(str(tmp_path / c.name / f"still_{f:03d}.png"), np.full((H, W, 3), 40 * f + 20, np.uint8))
        vw.release()
    for f in range(4):
        vid = load_capture(tmp_path, f, images="{name}/video.avi", calibration=".")
        still = load_capture(tmp_path, f, images="{name}/still_*.png", calibration=".")
        assert abs(int(vid["images"].images[1].mean()) - (40 * f + 20)) <= 2
        assert int(still["images"].images[1].mean()) == 40 * f + 20
    with pytest.raises(DataError, match="frame 4 out of range"):
        load_capture(tmp_path, 4, images="{name}/video.avi", calibration=".")
    with pytest.raises(DataError, match="frame 4 out of range: 4 frames"):
        load_capture(tmp_path, 4, images="{name}/still_*.png", calibration=".")


def _bar_video(path, frames=30, offset=10):
    """An MPEG-4 video (keyframes 12 apart: the frames between are predicted) whose frame f shows a bar f + 1
    blocks wide."""
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10, (W, H))
    for f in range(frames):
        img = np.zeros((H, W, 3), np.uint8)
        img[:, : 2 * f + 2] = (7 * f + offset) % 256
        vw.write(img)
    vw.release()
    cap, out = cv2.VideoCapture(str(path)), []
    while True:
        ok, img = cap.read()
        if not ok:
            return out
        out.append(np.ascontiguousarray(img[:, :, ::-1]))


def test_video_frames_in_any_order_are_the_frames_decoded_front_to_back(tmp_path, monkeypatch):
    """A video stays open and decodes on from where it stopped (one decode per frame of a run, not a seek from the
    keyframe): frames asked in any order (on, back, far ahead: a seek) are exactly those of one front-to-back
    decode, also between keyframes; after a frame that fails to decode the next one is sought; a rewritten file
    is opened again; frames outside the video name the file."""
    from nodes.capture import load as L

    path = tmp_path / "take.mp4"
    ref = _bar_video(path)
    assert len(ref) == 30 and len({r.tobytes() for r in ref}) == 30
    monkeypatch.setattr(L, "FORWARD", 3)
    seeks, fail = [], []
    real = cv2.VideoCapture

    class Counting:
        def __init__(self, *a):
            self.cap = real(*a)

        def set(self, prop, value):
            seeks.append(value)
            return self.cap.set(prop, value)

        def grab(self):
            return False if fail and not fail.pop() else self.cap.grab()

        def __getattr__(self, name):
            return getattr(self.cap, name)

    monkeypatch.setattr(cv2, "VideoCapture", Counting)
    for f in (0, 1, 2, 5, 6, 3, 17, 16, 4, 29):       # on, on, on (+2), on, back, far (+10), back, back, far
        assert np.array_equal(L.read_image(path, f), ref[f]), f
    assert seeks == [3, 17, 16, 4, 29]
    fail.append(False)                                 # the next grab fails: frame 27 is not decoded ...
    L.read_image(path, 20)
    with pytest.raises(DataError, match="take.mp4: frame 23 could not be decoded"):
        L.read_image(path, 23)
    assert np.array_equal(L.read_image(path, 24), ref[24]) and seeks[-1] == 24     # ... and the next is sought
    _bar_video(path, offset=90)                        # the same name, new content (a new mtime: another version)
    os.utime(path, ns=(1, 10**18))
    assert np.array_equal(L.read_image(path, 5), _bar_video(tmp_path / "again.mp4", offset=90)[5])
    with pytest.raises(DataError, match=r"take.mp4: frame 30 out of range \(the video has 30 frames\)"):
        L.read_image(path, 30)
    with pytest.raises(DataError, match=r"take.mp4: frame -1 out of range"):
        L.read_image(path, -1)
    with pytest.raises(DataError, match="gone.mp4: unreadable video"):
        L.read_image(tmp_path / "gone.mp4", 0)


def test_video_readers_shared_by_threads_and_evicted(tmp_path, monkeypatch):
    """Threads reading frames of two videos while each lookup evicts the other's reader (one kept open): every
    frame is the right one (an evicted reader is opened again, not read closed)."""
    from concurrent.futures import ThreadPoolExecutor

    from nodes.capture import load as L

    refs = {name: _bar_video(tmp_path / name, offset=k * 100) for k, name in enumerate(("a.mp4", "b.mp4"))}
    monkeypatch.setattr(L, "OPEN_VIDEOS", 1)
    rng = np.random.default_rng(5)
    asks = [(name, int(f)) for name, f in zip(rng.choice(list(refs), 200), rng.integers(0, 30, 200))]

    def read(ask):
        return np.array_equal(L.read_image(tmp_path / ask[0], ask[1]), refs[ask[0]][ask[1]])

    with ThreadPoolExecutor(4) as pool:
        assert all(pool.map(read, asks))
    assert len(L._readers) == 1


def test_bounds_node_auto_and_explicit():
    cams = sphere_rig(6)
    from nodes.common.types import MaskSet

    masks = MaskSet([sphere_mask(cams, v) for v in range(len(cams))])
    b = run_node("bounds", {"masks": masks, "cameras": cams}, {"margin": 0.0}, roundtrip=True)["bounds"]
    # the box holds the sphere and is not much larger than a visual hull of 6 views can be
    assert np.all(b[0] < CENTRE - RADIUS + 0.02) and np.all(b[1] > CENTRE + RADIUS - 0.02), b
    assert np.all(b[1] - b[0] < 2 * RADIUS * 1.35), b
    e = run_node("bounds", params={"bbox": [0, 0, 0, 1, 2, 3]})["bounds"]
    np.testing.assert_array_equal(e, [[0, 0, 0], [1, 2, 3]])
    with pytest.raises(NodeError, match="xmax > xmin"):
        run_node("bounds", params={"bbox": [0, 0, 0, 1, -2, 3]})
    with pytest.raises(NodeError, match="do not intersect|fewer than two"):
        run_node("bounds", {"masks": MaskSet([np.zeros((H, W), np.uint8)] * 6), "cameras": cams})
    cropped = MaskSet([m if v != 4 else m[:, : W // 2] for v, m in enumerate(masks.masks)])
    with pytest.raises(NodeError, match="bounds: mask of camera 'cam4' is 32x48 but the camera is 64x48"):
        run_node("bounds", {"masks": cropped, "cameras": cams})


@pytest.mark.realdata
def test_capture_golden_inria_dancer(data_dir, golden):
    """Cameras, image sizes and mask areas of the dancer, as projections of fixed world points."""
    cap = load_capture(data_dir / "inria_dancer")
    cams = cap["cameras"]
    pts = np.array([[0.3, -1.4, 0.0], [0.3, -1.4, 1.7], [0.0, -1.0, 0.9], [0.7, -1.8, 0.9]])
    table = {c.name: {"size": [c.width, c.height], "uv": np.round(cams.project(pts, v)[0], 4).tolist(),
                      "mask_pixels": int((cap["masks"].masks[v] > 0).sum()), "center": np.round(c.center, 6).tolist()}
             for v, c in enumerate(cams)}
    golden.check("capture_dancer", table, Table, rtol=1e-6, atol=1e-3)


@pytest.mark.realdata
def test_utrecht_video_matches_extracted_frames(data_dir):
    """Frame 100 decoded from video.avi equals the PNG extracted by the dataset's curator; plates present."""
    cap = load_capture(data_dir / "uu_infomcv_seated", frame=100)
    assert cap["masks"] is None and len(cap["background"]) == 4
    assert cap["fps"] == 50.0                       # the videos' rate (SOURCE.md: 50 fps), in the capture's world table
    for v, name in enumerate(cap["cameras"].names):
        png = cv2.imread(str(data_dir / "uu_infomcv_seated" / name / "frames" / "video_0100.png"))[:, :, ::-1]
        assert np.array_equal(cap["images"].images[v], png)
        plate = cv2.imread(str(data_dir / "uu_infomcv_seated" / name / "frames" / "background_0000.png"))[:, :, ::-1]
        assert np.array_equal(cap["background"].images[v], plate)


def test_cameras_named_by_relative_path_keep_their_own_images(tmp_path):
    """COLMAP names images by their path below the image folder: cam0/0001.png and cam1/0001.png are two cameras.
    Named by file stem they were both '0001': the set accepted it, the cached images came back as two copies of
    the second image and export.masks wrote one file for two cameras."""
    from nodes.common.cameras import Camera
    from nodes.common.types import ImageSet, MaskSet

    base = sphere_rig(3)
    cams = Cameras([Camera(f"cam{v}/0001", c.width, c.height, c.K, c.Rt, c.dist) for v, c in enumerate(base)])
    save_colmap(cams, tmp_path)
    for v in range(3):
        (tmp_path / "images" / f"cam{v}").mkdir(parents=True)
        cv2.imwrite(str(tmp_path / "images" / f"cam{v}" / "0001.png"), np.full((H, W, 3), 50 + v, np.uint8))
        (tmp_path / "masks" / f"cam{v}").mkdir(parents=True)
        cv2.imwrite(str(tmp_path / "masks" / f"cam{v}" / "0001.png"), np.full((H, W), 255 * (v % 2), np.uint8))
    out = run_node("capture", params={"path": str(tmp_path)}, roundtrip=True)
    assert out["cameras"].names == ["cam0/0001", "cam1/0001", "cam2/0001"]
    assert out["images"].names == out["cameras"].names
    assert [int(im[0, 0, 0]) for im in out["images"].images] == [50, 51, 52]
    assert [int(m[0, 0]) for m in out["masks"].masks] == [0, 255, 0]
    files = run_node("export.masks", {"masks": out["masks"]}, {"path": "m/{camera}.png"})["files"]
    assert sorted(files) == ["m/cam0/0001.png", "m/cam1/0001.png", "m/cam2/0001.png"]
    one = np.zeros((H, W), np.uint8)
    with pytest.raises(DataError, match=r"camera names must be unique: '0001' \(2x\) of 3"):
        Cameras([Camera("0001", c.width, c.height, c.K, c.Rt, c.dist) for c in base[:2]] + [base[2]])
    with pytest.raises(DataError, match="camera names must be unique: 'a' \\(2x\\)"):
        ImageSet([np.zeros((H, W, 3), np.uint8)] * 2, ["a", "a"])
    with pytest.raises(DataError, match="camera names must be unique: 'a' \\(2x\\)"):
        MaskSet([one, one], names=["a", "a"])


def write_ptext_dataset(root, cams):
    """A P-matrix text file (calib.txt, no names, no sizes) and images/image_{i}.jpg, masks/image_{i}.png: a
    folder of no known layout."""
    lines = [f"{len(cams)}"]
    for v in range(len(cams)):
        lines.append(" ".join(f"{x:.12g}" for x in cams[v].P.ravel()))
    (root / "calib.txt").write_text("\n".join(lines) + "\n")
    (root / "images").mkdir()
    (root / "masks").mkdir()
    for v in range(len(cams)):
        img = np.full((H, W, 3), 20 * v + 10, np.uint8)
        cv2.imwrite(str(root / "images" / f"image_{v}.jpg"), img)
        cv2.imwrite(str(root / "masks" / f"image_{v}.png"), sphere_mask(cams, v))


@pytest.mark.parametrize("param, pattern", [
    ("images", "images/*.jpg"),
    ("images", "images/image_0.jpg"),
    ("masks", "masks/*.png"),
    ("background", "images/image_0.jpg"),
])
def test_pattern_without_camera_field_is_refused(tmp_path, param, pattern):
    """'*' means frames: a pattern without {cam}, {cam1} or {name} gives every camera the same file."""
    cams = sphere_rig(4)
    write_ptext_dataset(tmp_path, cams)
    given = {"images": "images/image_{cam}.jpg", "calibration": "calib.txt", param: pattern}
    msg = (f"param '{param}': the pattern '{pattern}' has no camera field, so all 4 cameras would read the same "
           f"file; add {{cam}} (camera index from 0, e.g. {{cam:03d}}), {{cam1}} (from 1) or {{name}} (camera name)")
    with pytest.raises(NodeError, match=re.escape(msg)):
        load_capture(tmp_path, 0, **given)


def test_pattern_without_camera_field_suggests_one(tmp_path):
    cams = sphere_rig(3)
    write_ptext_dataset(tmp_path, cams)
    with pytest.raises(NodeError, match=re.escape("'*' in a pattern means frames, not cameras); e.g. 'images/image_{cam}.jpg'")):
        load_capture(tmp_path, 0, images="images/*.jpg", calibration="calib.txt")
    one = sphere_rig(1)
    single = tmp_path / "single"
    single.mkdir()
    write_ptext_dataset(single, one)
    assert load_capture(single, 0, images="images/*.jpg", calibration="calib.txt")["cameras"].names == ["cam000"]


def test_one_pattern_is_completed_from_the_folder(tmp_path):
    """calibration= alone, or images= alone, on a folder that loads by itself: the other is auto-detected."""
    cams = sphere_rig(4)
    write_ptext_dataset(tmp_path, cams)
    auto = load_capture(tmp_path)
    for given in ({"calibration": "calib.txt"}, {"images": "images/image_{cam}.jpg"},
                  {"calibration": "calib.txt", "masks": "masks/image_{cam}.png"}):
        got = load_capture(tmp_path, 0, **given)
        assert got["cameras"].names == auto["cameras"].names, given
        for v in range(len(cams)):
            assert np.array_equal(got["images"].images[v], auto["images"].images[v]), given
            assert np.array_equal(got["masks"].masks[v], auto["masks"].masks[v]), given


def test_capture_takes_an_encoder_crop_and_says_so(tmp_path, caplog):
    """An image up to 15 px narrower or shorter than its calibration (a video encoder's crop to a multiple of 8 or
    16, pose2sim's 1080 of 1088) is the calibrated view less its last columns and rows: the camera is cropped, K
    kept, and a warning names it. Larger, or 16 px and more, is refused."""
    cams = sphere_rig()
    patterns = write_dataset(tmp_path, cams)
    img = cv2.imread(str(tmp_path / "cam1" / "rgb.png"))
    mask = cv2.imread(str(tmp_path / "cam1" / "mask.png"), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(tmp_path / "cam1" / "rgb.png"), img[:, : W - 8])
    cv2.imwrite(str(tmp_path / "cam1" / "mask.png"), mask[:, : W - 8])
    plate = cv2.imread(str(tmp_path / "cam1" / "plate.png"))
    cv2.imwrite(str(tmp_path / "cam1" / "plate.png"), plate[:, : W - 8])    # the same encoder
    out = load_capture(tmp_path, 0, **patterns)
    got = out["cameras"][1]
    assert (got.width, got.height) == (W - 8, H) and np.allclose(got.K, cams[1].K)
    assert np.array_equal(out["masks"].masks[1], sphere_mask(cams, 1)[:, : W - 8])
    assert f"camera 'cam1': image {W - 8}x{H}, calibration {W}x{H}: taken as the calibrated image less its last 8" \
           in caplog.text
    for bad in (np.zeros((H, W + 8, 3), np.uint8), img[:, : W - 16]):
        cv2.imwrite(str(tmp_path / "cam1" / "rgb.png"), bad)
        with pytest.raises(DataError, match=f"camera 1 'cam1'.*{bad.shape[1]}x{H} but the calibration is for {W}x{H}"):
            load_capture(tmp_path, 0, **patterns)
