"""Which image belongs to which camera (issue 12, items 1, 2, 9, 10, 11): images are paired with cameras by
name, else by the number in their names (never by text order), what stays ambiguous is refused, a camera
or an image left without its partner is an error or a named subset, and the pairing is logged."""
from __future__ import annotations

import logging
import os
import shutil

import cv2
import numpy as np
import pytest

from nodegraph.errors import DataError
from nodes.capture.load import load_capture
from nodes.common.calibration import save_colmap
from rig import ring_rig

W, H = 48, 32


def rig(n):
    return ring_rig(n, W, H, radius=3.0, z=0.8, fov=50)


def write_P_filestorage(path, cams, name="viff{i:03d}_matrix"):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for i, c in enumerate(cams):
        fs.write(name.format(i=i), c.P)
    fs.release()


def write_image(path, value):
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.full((H, W, 3), value, np.uint8))


def values(out) -> list[int]:
    return [int(im[0, 0, 0]) for im in out["images"].images]


class Logged(logging.Handler):
    def __init__(self):
        super().__init__(logging.DEBUG)
        self.lines = []

    def emit(self, record):
        self.lines.append((record.levelno, record.getMessage()))


@pytest.fixture
def log():
    lg = logging.getLogger("test.capture")
    h = Logged()
    lg.addHandler(h)
    lg.setLevel(logging.DEBUG)
    lg.h = h
    yield lg
    lg.removeHandler(h)


# ---------------------------------------------------------------- item 1: natural order, by number
def test_images_pair_with_cameras_by_the_number_in_their_names(tmp_path, log):
    """image_0 .. image_11 with P matrices viff000 .. viff011: text order (image_0, image_1, image_10, ...)
    paired image_10 with viff002."""
    cams = rig(12)
    write_P_filestorage(tmp_path / "calib.xml", cams)
    for i in range(12):
        write_image(tmp_path / "images" / f"image_{i}.png", 10 * i)
    out = load_capture(tmp_path, log=log)
    assert out["cameras"].names == [f"viff{i:03d}_matrix" for i in range(12)]
    assert values(out) == [10 * i for i in range(12)]
    warned = [m for lv, m in log.h.lines if lv == logging.WARNING]
    assert warned and "by the number in their names" in warned[0] and "image_10.png -> viff010_matrix" in " ".join(
        m for _, m in log.h.lines), log.h.lines


@pytest.mark.parametrize("names, needle", [
    (["a.png", "b.png", "c.png"], "cannot tell which image belongs to which camera"),
    (["image_1.png", "image_01.png", "image_2.png"], "cannot tell which image belongs to which camera"),
    (["img_1_4.png", "img_2_5.png", "img_3_6.png"], "cannot tell which image belongs to which camera"),
    (["image_0.png", "image_1.png", "image_7.png"], "image_7.png"),
])
def test_ambiguous_pairings_are_refused(tmp_path, names, needle):
    cams = rig(3)
    write_P_filestorage(tmp_path / "calib.xml", cams)
    for i, n in enumerate(names):
        write_image(tmp_path / "images" / n, 10 * i)
    with pytest.raises(DataError, match=needle.replace(".", r"\.")):
        load_capture(tmp_path)


def test_star_pattern_frames_follow_natural_order(tmp_path):
    """Frame N of a '*' pattern is the N-th file in natural order: 0.png 1.png 2.png ... 10.png (child_rope)."""
    cams = rig(2)
    save_colmap(cams, tmp_path / "sparse")
    for c in cams:
        for f in range(12):
            write_image(tmp_path / c.name / f"{f}.png", 20 * f)
    for f in (2, 10, 11):
        out = load_capture(tmp_path, f, images="{name}/*.png", calibration="sparse")
        assert values(out) == [20 * f] * 2, f


@pytest.mark.slow
@pytest.mark.realdata
def test_oxford_dino_relaid_out_pairs_every_view(tmp_path, data_dir, log):
    """The issue's case: images/image_0 .. image_35 + an OpenCV FileStorage of viff000_matrix .. viff035_matrix."""
    from scipy.io import loadmat

    src = data_dir / "oxford_dino"
    Ps = [np.asarray(p, np.float64) for p in loadmat(src / "dino_Ps.mat")["P"].ravel()]
    fs = cv2.FileStorage(str(tmp_path / "calib.xml"), cv2.FILE_STORAGE_WRITE)
    for i, P in enumerate(Ps):
        fs.write(f"viff{i:03d}_matrix", P)
    fs.release()
    (tmp_path / "images").mkdir()
    for i in range(36):
        os.symlink(src / "images" / f"viff.{i:03d}.png", tmp_path / "images" / f"image_{i}.png")
    out = load_capture(tmp_path, log=log)
    ref = load_capture(src)
    assert len(out["cameras"]) == 36
    for i in range(36):
        assert np.array_equal(out["images"].images[i], ref["images"].images[i]), i
        np.testing.assert_allclose(out["cameras"][i].P / np.abs(out["cameras"][i].P).max(),
                                   ref["cameras"][i].P / np.abs(ref["cameras"][i].P).max(), atol=1e-9)


# ---------------------------------------------------------------- item 2: a camera or an image without its partner
def write_inria(root, cams):
    """calibration/<name>.xml (INRIA <camera> P), images/<name>_0001.png, silhouettes/silh_<name>_0001.pbm."""
    (root / "calibration").mkdir(parents=True)
    for i, c in enumerate(cams):
        (root / "calibration" / f"{c.name}.xml").write_text("<camera>" + " ".join(repr(float(x)) for x in c.P.ravel()) + "</camera>\n")
        write_image(root / "images" / f"{c.name}_0001.png", 10 * i)
        (root / "silhouettes").mkdir(exist_ok=True)
        cv2.imwrite(str(root / "silhouettes" / f"silh_{c.name}_0001.pbm"), np.full((H, W), 255, np.uint8))


def test_missing_calibration_file_is_an_error_not_a_camera_fewer(tmp_path):
    cams = rig(5)
    write_inria(tmp_path, ring_rig(5, W, H, radius=3.0, z=0.8, fov=50, name="cam{i:02d}"))
    assert len(load_capture(tmp_path)["cameras"]) == len(cams)
    (tmp_path / "calibration" / "cam02.xml").unlink()
    with pytest.raises(DataError, match=r"images/cam02_0001\.png.*no camera"):
        load_capture(tmp_path)


def test_image_without_a_camera_is_an_error(tmp_path):
    cams = rig(3)
    save_colmap(cams, tmp_path)
    for i, c in enumerate(cams):
        write_image(tmp_path / "images" / f"{c.name}.png", 10 * i)
    write_image(tmp_path / "images" / "cam3.png", 99)
    with pytest.raises(DataError, match=r"cam3\.png.*no camera"):
        load_capture(tmp_path)


@pytest.mark.realdata
def test_inria_dancer_with_a_calibration_file_missing(tmp_path, data_dir):
    src = data_dir / "inria_dancer"
    for sub in ("images", "silhouettes", "calibration"):
        (tmp_path / sub).mkdir()
        for f in (src / sub).iterdir():
            os.symlink(f, tmp_path / sub / f.name)
    (tmp_path / "calibration" / "cam03.xml").unlink()
    with pytest.raises(DataError, match=r"cam03_00023_0000008550\.png.*no camera"):
        load_capture(tmp_path)


# ---------------------------------------------------------------- item 10: IDR / NeuS, image/, more cameras than images
def write_idr(root, cams, image_names, mask_dir="mask"):
    arrays = {}
    for i, c in enumerate(cams):
        W4 = np.eye(4)
        W4[:3] = c.P
        S = np.diag([0.5, 0.5, 0.5, 1.0])
        S[:3, 3] = [0.1, -0.2, 0.05]
        arrays[f"world_mat_{i}"] = W4
        arrays[f"scale_mat_{i}"] = S
        arrays[f"world_mat_inv_{i}"] = np.linalg.inv(W4)
    np.savez(root / "cameras_sphere.npz", **arrays)
    for i in image_names:
        write_image(root / "image" / f"{i:03d}.png", 5 * i)
        if mask_dir:
            (root / mask_dir).mkdir(exist_ok=True)
            m = np.zeros((H, W), np.uint8)
            m[:, : 2 * i + 1] = 255
            cv2.imwrite(str(root / mask_dir / f"{i:03d}.png"), m)


def test_idr_with_explicit_patterns(tmp_path):
    cams = rig(4)
    write_idr(tmp_path, cams, range(4))
    out = load_capture(tmp_path, images="image/{name}.png", masks="mask/{name}.png", calibration="cameras_sphere.npz")
    assert out["cameras"].names == ["000", "001", "002", "003"] and values(out) == [0, 5, 10, 15]
    X = np.array([[0.1, 0.2, 0.3], [-0.2, 0.1, 0.0]])
    for v in range(4):
        u_ref, _ = cams.project(X * 0.5 + [0.1, -0.2, 0.05], v)  # scale_mat: normalised sphere -> world
        np.testing.assert_allclose(out["cameras"].project(X, v)[0], u_ref, atol=1e-6)


def test_idr_layout_is_found_automatically_with_more_cameras_than_images(tmp_path, log):
    cams = rig(6)
    write_idr(tmp_path, cams, [0, 2, 3, 5])
    out = load_capture(tmp_path, log=log)
    assert out["cameras"].names == ["000", "002", "003", "005"] and values(out) == [0, 10, 15, 25]
    assert [int((m > 0).sum(axis=1)[0]) for m in out["masks"].masks] == [1, 5, 7, 11]
    warned = " ".join(m for lv, m in log.h.lines if lv == logging.WARNING)
    assert "2 of the 6 cameras have no image" in warned and "001" in warned and "004" in warned, log.h.lines


# ---------------------------------------------------------------- item 11: a masks pattern alone
def test_masks_pattern_alone_is_used(tmp_path):
    cams = rig(3)
    save_colmap(cams, tmp_path)
    for i, c in enumerate(cams):
        write_image(tmp_path / "images" / f"{c.name}.png", 10 * i)
        m = np.zeros((H, W), np.uint8)
        m[: i + 2] = 255
        (tmp_path / "segm").mkdir(exist_ok=True)
        cv2.imwrite(str(tmp_path / "segm" / f"{c.name}_mask.png"), m)
    out = load_capture(tmp_path, masks="segm/{name}_mask.png")
    assert [int((m > 0).sum()) // W for m in out["masks"].masks] == [2, 3, 4]
    with pytest.raises(DataError, match=r"segm/cam0\.png not found"):
        load_capture(tmp_path, masks="segm/{name}.png")
    bg = load_capture(tmp_path, background="images/{name}.png")["background"]
    assert [int(b[0, 0, 0]) for b in bg.images] == [0, 10, 20]


# ---------------------------------------------------------------- item 9: an all-zero P names the file
def test_all_zero_projection_matrix_names_the_file(tmp_path):
    cams = rig(4)
    lines = [" ".join(repr(float(x)) for x in c.P.ravel()) for c in cams]
    lines[2] = " ".join(["0"] * 12)
    (tmp_path / "cameras_P.txt").write_text("\n".join(lines) + "\n")
    for i in range(4):
        write_image(tmp_path / "images" / f"viff.{i:03d}.png", i)
    with pytest.raises(DataError, match=r"cameras_P\.txt:3: .*projection matrix is all zero"):
        load_capture(tmp_path)
    shutil.rmtree(tmp_path / "images")
    (tmp_path / "cameras_P.txt").unlink()
    write_inria(tmp_path, ring_rig(4, W, H, radius=3.0, z=0.8, fov=50, name="cam{i:02d}"))
    (tmp_path / "calibration" / "cam01.xml").write_text("<camera>" + " 0" * 12 + "</camera>\n")
    with pytest.raises(DataError, match=r"calibration/cam01\.xml: .*projection matrix is all zero"):
        load_capture(tmp_path)


def test_fifo_among_the_images_is_not_read(tmp_path):
    cams = rig(3)
    save_colmap(cams, tmp_path)
    for i, c in enumerate(cams):
        write_image(tmp_path / "images" / f"{c.name}.png", 10 * i)
    os.mkfifo(tmp_path / "images" / "zz.png")
    assert values(load_capture(tmp_path)) == [0, 10, 20]
    seq = tmp_path / "seq"
    save_colmap(cams, seq)
    for c in cams:
        for f in range(3):
            write_image(seq / c.name / f"{f}.png", f)
    os.mkfifo(seq / "cam1" / "1a.png")
    assert values(load_capture(seq, 2, images="{name}/*.png", calibration=".")) == [2, 2, 2]
