"""Calibration importers and exporters: synthetic files of every format, round trips, bad input, and the
real datasets (cameras surround the object, the projected coarse hull covers the silhouettes)."""
import json
import re

import cv2
import numpy as np
import pytest

from nodes.common.cameras import Camera, Cameras
from rig import ring_rig
from nodegraph.errors import DataError
from nodes.common.bounds import auto_bounds, coarse_hull
from nodes.common.calibration import camera_from_P, load_cameras, save_colmap, save_nerf

W, H = 320, 240


def rig(dist=True) -> Cameras:
    cams = ring_rig(4, W, H, radius=4.0, z=lambda i, a: 1.5 + 0.2 * i, phase=0.3, center=(0, 0, 0),
                    target=(0.1, -0.2, 0.4), fov=55, name="view{i}",
                    dist=(lambda i: [-0.2, 0.05, 1e-3, -2e-3, 0.01 * (i % 2)]) if dist else None)
    for i, c in enumerate(cams):
        c.K[0, 2] += 3.25 * i          # principal points off-centre, fy != fx
        c.K[1, 1] *= 1.01
    return cams


def nums(*arrays) -> str:
    return " ".join(repr(float(x)) for a in arrays for x in np.concatenate([np.ravel(b) for b in (a if isinstance(a, list) else [a])]))


def points(n=200):
    return np.random.default_rng(0).uniform(-0.8, 0.8, (n, 3)) + [0.1, -0.2, 0.4]


def assert_same(a: Cameras, b: Cameras, tol=1e-6):
    assert len(a) == len(b)
    X = points()
    for v in range(len(a)):
        assert (a[v].width, a[v].height) == (b[v].width, b[v].height)
        ua, za = a.project(X, v)
        ub, zb = b.project(X, v)
        assert np.abs(ua - ub).max() < tol, f"view {v}: projections differ by {np.abs(ua - ub).max()} px"
        assert np.all(np.sign(za) == np.sign(zb))


# ------------------------------------------------------------------ exporters: round trips
def test_colmap_round_trip(tmp_path):
    cams = rig()
    save_colmap(cams, tmp_path)
    text = (tmp_path / "cameras.txt").read_text()
    assert "FULL_OPENCV" in text and " OPENCV " in text
    back = load_cameras(tmp_path)
    assert back.names == cams.names
    assert_same(cams, back)
    save_colmap(rig(dist=False), tmp_path / "plain")
    assert "PINHOLE" in (tmp_path / "plain" / "cameras.txt").read_text()
    assert_same(rig(dist=False), load_cameras(tmp_path / "plain" / "images.txt"))


def test_nerf_round_trip(tmp_path):
    cams = rig()
    save_nerf(cams, tmp_path / "transforms.json")
    back = load_cameras(tmp_path / "transforms.json")
    assert back.names == cams.names
    assert_same(cams, back)


def test_exporters_reject_what_they_cannot_write(tmp_path):
    bare = Cameras([Camera.from_P("p", rig()[0].P, W, H)])
    with pytest.raises(DataError, match="bare-P"):
        save_colmap(bare, tmp_path)
    skewed = rig(dist=False)
    skewed[1].K[0, 1] = 1.5
    with pytest.raises(DataError, match="view1.*skew"):
        save_nerf(skewed, tmp_path / "t.json")


# ------------------------------------------------------------------ importers on synthetic files
def test_colmap_models(tmp_path):
    """SIMPLE_PINHOLE / SIMPLE_RADIAL / RADIAL written by hand (corner pixel convention: +0.5)."""
    c = rig(dist=False)[0]
    f, cx, cy = c.K[0, 0], c.K[0, 2] + 0.5, c.K[1, 2] + 0.5
    from scipy.spatial.transform import Rotation

    qx, qy, qz, qw = Rotation.from_matrix(c.Rt[:, :3]).as_quat()
    t = c.Rt[:, 3]
    (tmp_path / "cameras.txt").write_text(f"# c\n1 SIMPLE_PINHOLE {W} {H} {f} {cx} {cy}\n2 SIMPLE_RADIAL {W} {H} {f} {cx} {cy} -0.1\n"
                                          f"3 RADIAL {W} {H} {f} {cx} {cy} -0.1 0.02\n")
    (tmp_path / "images.txt").write_text("".join(f"{i} {qw} {qx} {qy} {qz} {t[0]} {t[1]} {t[2]} {i} im{i}.jpg\n\n" for i in (1, 2, 3)))
    cams = load_cameras(tmp_path)
    assert cams.names == ["im1", "im2", "im3"]
    K = c.K.copy()
    K[1, 1] = K[0, 0]
    expect = [Camera("a", W, H, K, c.Rt), Camera("b", W, H, K, c.Rt, [-0.1]), Camera("c", W, H, K, c.Rt, [-0.1, 0.02])]
    assert_same(Cameras(expect), cams)
    (tmp_path / "cameras.txt").write_text(f"1 FISHEYE {W} {H} 1 2 3 4\n")
    with pytest.raises(DataError, match="FISHEYE"):
        load_cameras(tmp_path)


def test_middlebury_par(tmp_path):
    cams = rig(dist=False)
    lines = [str(len(cams))] + [f"{c.name}.png " + nums([c.K, c.Rt[:, :3], c.Rt[:, 3]]) for c in cams]
    (tmp_path / "x_par.txt").write_text("\n".join(lines) + "\n")
    for c in cams:
        cv2.imwrite(str(tmp_path / f"{c.name}.png"), np.zeros((H, W), np.uint8))
    assert_same(cams, load_cameras(tmp_path / "x_par.txt"))


def test_p_text_decomposes_physical_and_keeps_bare(tmp_path):
    cams = rig(dist=False)
    rows = ["# P matrices", str(len(cams))] + [nums(-2.5 * c.P) for c in cams]
    (tmp_path / "P.txt").write_text("\n".join(rows) + "\n")
    back = load_cameras(tmp_path / "P.txt", image_sizes=(W, H))
    assert all(c.metric for c in back), "a physical P decomposes into K [R|t]"
    assert_same(cams, back)
    for a, b in zip(cams, back):
        np.testing.assert_allclose(b.K / b.K[2, 2], a.K, rtol=1e-9, atol=1e-7)
        np.testing.assert_allclose(b.center, a.center, atol=1e-9)
    # a mirrored, skewed frame (like the Oxford dino) stays a bare P and still projects the same
    M = np.diag([1.0, -0.7, 1.0])
    M[0, 1] = 0.05
    odd = Cameras([Camera.from_P(c.name, c.P @ np.block([[M, np.zeros((3, 1))], [np.zeros((1, 3)), 1]]), W, H) for c in cams])
    c0 = camera_from_P("odd", odd[0].P, W, H)
    assert not c0.metric
    assert np.allclose(Cameras([c0]).project(points(), 0)[0], odd.project(points(), 0)[0])


def test_opencv_filestorage(tmp_path):
    cams = rig()
    for i, c in enumerate(cams):
        fs = cv2.FileStorage(str(tmp_path / f"cam{i}.yml"), cv2.FILE_STORAGE_WRITE)
        fs.write("camera_matrix", c.K)
        fs.write("distortion_coefficients", c.dist.reshape(1, 5))
        if i % 2:
            fs.write("rvec", cv2.Rodrigues(c.Rt[:, :3])[0])
        else:
            fs.write("R", c.Rt[:, :3])
        fs.write("T", c.Rt[:, 3].reshape(3, 1))
        fs.write("image_width", W)
        fs.write("image_height", H)
        fs.release()
    back = Cameras([load_cameras(tmp_path / f"cam{i}.yml")[0] for i in range(4)])
    assert_same(cams, back)
    # a list of P matrices in one XML file
    fs = cv2.FileStorage(str(tmp_path / "ps.xml"), cv2.FILE_STORAGE_WRITE)
    plain = rig(dist=False)
    for i, c in enumerate(plain):
        fs.write(f"P{i}", c.P)
    fs.release()
    assert_same(plain, load_cameras(tmp_path / "ps.xml", image_sizes=[(W, H)] * 4))


def test_per_camera_folders_and_inria_xml(tmp_path):
    cams = rig()
    for c in cams:
        d = tmp_path / "set" / c.name
        d.mkdir(parents=True)
        fs = cv2.FileStorage(str(d / "config.xml"), cv2.FILE_STORAGE_WRITE)
        fs.write("CameraMatrix", c.K)
        fs.write("DistortionCoeffs", c.dist.reshape(1, 5))
        fs.write("Rotation", cv2.Rodrigues(c.Rt[:, :3])[0])
        fs.write("Translation", c.Rt[:, 3].reshape(3, 1))
        fs.release()
    back = load_cameras(tmp_path / "set", image_sizes=(W, H))
    assert back.names == cams.names
    assert_same(cams, back)
    plain = rig(dist=False)
    (tmp_path / "inria").mkdir()
    for i, c in enumerate(plain):
        (tmp_path / "inria" / f"cam{i:02d}.xml").write_text("<camera>\n" + nums(c.P) + "\n</camera>\n")
    assert_same(plain, load_cameras(tmp_path / "inria", image_sizes=(W, H)))


def test_tsinghua_idr_matlab(tmp_path):
    cams = rig()
    blocks = []
    for i, c in enumerate(cams):
        c.dist[2:] = 0  # the Tsinghua format has k1 k2 only
        blocks.append(f"{i}\n" + "\n".join(nums(r) for r in c.K) + f"\n{nums(c.dist[:2])}\n"
                      + "\n".join(nums(r) for r in c.Rt) + "\n")
    (tmp_path / "calibParamsI.txt").write_text("\n".join(blocks))
    assert_same(cams, load_cameras(tmp_path / "calibParamsI.txt", image_sizes=(W, H)))

    plain = rig(dist=False)
    scale = np.diag([0.5, 0.5, 0.5, 1.0])
    scale[:3, 3] = [0.1, -0.2, 0.4]
    arrays = {}
    for i, c in enumerate(plain):
        arrays[f"world_mat_{i}"] = np.vstack([c.P, [0, 0, 0, 1]])
        arrays[f"scale_mat_{i}"] = scale
    np.savez(tmp_path / "cameras_sphere.npz", **arrays)
    idr = load_cameras(tmp_path / "cameras_sphere.npz", image_sizes=(W, H))
    X = points()
    Xn = (X - scale[:3, 3]) / 0.5                     # IDR cameras live in the normalised (unit sphere) frame
    for v in range(4):
        assert np.abs(idr.project(Xn, v)[0] - plain.project(X, v)[0]).max() < 1e-6
        assert idr[v].metric

    from scipy.io import savemat

    cell = np.empty((1, 4), dtype=object)
    for i, c in enumerate(plain):
        cell[0, i] = c.P
    savemat(tmp_path / "Ps.mat", {"P": cell})
    assert_same(plain, load_cameras(tmp_path / "Ps.mat", image_sizes=(W, H)))


# ------------------------------------------------------------------ bad input
def test_nan_is_rejected(tmp_path):
    cams = rig(dist=False)
    rows = [nums(c.P) for c in cams]
    rows[2] = rows[2].replace(rows[2].split()[5], "nan", 1)
    (tmp_path / "P.txt").write_text("\n".join(rows))
    with pytest.raises(DataError, match="NaN"):
        load_cameras(tmp_path / "P.txt", image_sizes=(W, H))
    save_nerf(cams, tmp_path / "t.json")
    doc = json.loads((tmp_path / "t.json").read_text())
    doc["frames"][1]["transform_matrix"][0][0] = float("nan")
    (tmp_path / "t.json").write_text(json.dumps(doc))
    with pytest.raises(DataError, match="frame 1.*NaN"):
        load_cameras(tmp_path / "t.json")


@pytest.mark.parametrize("name, text, fmt, match", [
    ("garbage.xml", "hello, not xml", "auto", "garbage.xml: unreadable opencv calibration"),
    ("k.yml", "%YAML:1.0\nK: 3\n", "auto", "k.yml: unreadable opencv calibration"),
    ("e_par.txt", "", "middlebury", "e_par.txt: unreadable middlebury"),
    ("c_par.txt", "x\n", "middlebury", "c_par.txt: unreadable middlebury"),
    ("transforms.json", "[1, 2]", "auto", "transforms.json: unreadable nerf"),
    ("transforms.json", '{"camera_angle_x": "wide", "frames": [{"transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]}]}',
     "auto", "transforms.json: unreadable nerf"),
    ("transforms.json", '{"camera_angle_x": 0.7, "w": NaN, "h": 10, "frames": [{"transform_matrix": [[1,0,0,0]]}]}',
     "auto", "transforms.json: unreadable nerf"),
    ("cameras_sphere.npz", "not a zip", "auto", "cameras_sphere.npz: unreadable idr"),
    ("calibParamsI.txt", "0\n900 0 512\n0 abc 384\n0 0 1\n0 0\n1 0 0 0\n0 1 0 0\n0 0 1 0\n", "auto",
     "calibParamsI.txt: not a whitespace-separated list of numbers"),
])
def test_malformed_calibration_is_a_data_error(tmp_path, name, text, fmt, match):
    """Files a reader cannot parse give a DataError naming the file (no ValueError/SystemError/...)."""
    (tmp_path / name).write_text(text)
    with pytest.raises(DataError, match=match):
        load_cameras(tmp_path / name, fmt=fmt, image_sizes=(W, H))


def test_zero_focal_length_and_float32_overflow_are_rejected(tmp_path):
    """fx = 0 divides by zero in every projection; 1e39 is inf once packed as float32 for the kernels."""
    cams = rig(dist=False)
    for bad, match in (("0.0", "calibParamsI.txt: camera '1': focal lengths fx=0,"),
                       ("1e39", "calibParamsI.txt: camera '1': calibration value 1e\\+39 is out of float32 range")):
        blocks = [f"{i}\n" + "\n".join(nums(r) for r in c.K) + "\n0 0\n" + "\n".join(nums(r) for r in c.Rt) + "\n"
                  for i, c in enumerate(cams)]
        blocks[1] = blocks[1].replace(repr(float(cams[1].K[0, 0])), bad, 1)
        (tmp_path / "calibParamsI.txt").write_text("\n".join(blocks))
        with pytest.raises(DataError, match=match):
            load_cameras(tmp_path / "calibParamsI.txt", image_sizes=(W, H))
    save_nerf(cams, tmp_path / "t.json")                 # the same file without the bad value loads
    assert_same(cams, load_cameras(tmp_path / "t.json"))


def test_ambiguous_folder_and_unknown_files(tmp_path):
    save_colmap(rig(), tmp_path)
    save_nerf(rig(), tmp_path / "transforms.json")
    assert_same(rig(), load_cameras(tmp_path))          # two calibrations that agree are fine
    other = rig()
    other[2].Rt[0, 3] += 0.05
    save_nerf(other, tmp_path / "transforms.json")
    with pytest.raises(DataError, match="disagree"):
        load_cameras(tmp_path)
    assert_same(other, load_cameras(tmp_path, fmt="nerf"))
    (tmp_path / "notes.dat").write_text("hello")
    with pytest.raises(DataError, match="unknown calibration format"):
        load_cameras(tmp_path / "notes.dat")
    with pytest.raises(DataError, match="not found"):
        load_cameras(tmp_path / "missing")
    (tmp_path / "short.txt").write_text("1 2 3 4 5 6 7 8 9 10 11 12\n1 2 3\n")
    with pytest.raises(DataError, match="short.txt:2"):
        load_cameras(tmp_path / "short.txt", fmt="ptext", image_sizes=(W, H))
    (tmp_path / "ok.txt").write_text(nums(rig()[0].P) + "\n")
    with pytest.raises(DataError, match="image sizes"):
        load_cameras(tmp_path / "ok.txt")


# ------------------------------------------------------------------ real data
def blue_key(img):
    """Oxford dino: B < (R + G) / 2, largest blob (the recipe in its SOURCE.md)."""
    r, g, b = (img[:, :, k].astype(np.int32) for k in range(3))
    fg = (2 * b < r + g).astype(np.uint8)
    fg[:, 715:] = 0
    n, lab, stats, _ = cv2.connectedComponentsWithStats(fg, connectivity=8)
    return np.where(lab == 1 + np.argmax(stats[1:, cv2.CC_STAT_AREA]), 255, 0).astype(np.uint8)


def dark_key(img):
    """Middlebury: grey > 0.19, dilate 10, erode 7 (its README's recipe)."""
    fg = (cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) > 0.19 * 255).astype(np.uint8) * 255
    fg = cv2.dilate(fg, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (21, 21)))
    return cv2.erode(fg, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (15, 15)))


def plate_key(img, plate):
    """Utrecht: |frame - plate| summed over RGB > 60, open, close, largest blob, holes filled."""
    fg = (np.abs(img.astype(np.int32) - plate).sum(2) > 60).astype(np.uint8) * 255
    fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    fg = cv2.morphologyEx(fg, cv2.MORPH_CLOSE, np.ones((7, 7), np.uint8))
    n, lab, stats, _ = cv2.connectedComponentsWithStats(fg)
    fg = np.where(lab == 1 + np.argmax(stats[1:, cv2.CC_STAT_AREA]), 255, 0).astype(np.uint8)
    cnts, _ = cv2.findContours(fg, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    return cv2.drawContours(fg, cnts, -1, 255, cv2.FILLED)


def hull_coverage(masks, cams, box, resolution=64, tolerance_px=3):
    """Per view: fraction of the silhouette covered by the projected coarse hull (voxel centres splatted
    with their projected footprint + tolerance_px for calibration and mask noise)."""
    occ = coarse_hull(masks, cams, box, resolution)
    vs = (box[1] - box[0]) / np.array(occ.shape)
    X = box[0] + (np.argwhere(occ) + 0.5) * vs
    corners = np.array([[i, j, k] for i in (-.5, .5) for j in (-.5, .5) for k in (-.5, .5)]) * vs
    out = []
    for v, m in enumerate(masks):
        uv, _ = cams.project(X, v)
        foot = max(np.abs(cams.project(X[::97] + c, v)[0] - uv[::97]).max() for c in corners)
        img = np.zeros_like(m)
        px = np.rint(uv).astype(int)
        ok = (px[:, 0] >= 0) & (px[:, 0] < m.shape[1]) & (px[:, 1] >= 0) & (px[:, 1] < m.shape[0])
        img[px[ok, 1], px[ok, 0]] = 255
        r = int(np.ceil(foot)) + tolerance_px
        img = cv2.dilate(img, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
        out.append(((img > 0) & (m > 0)).sum() / max(1, (m > 0).sum()))
    return occ, np.array(out)


def surround(cams: Cameras, centre) -> float:
    """Largest azimuth gap (degrees) of the camera centres around the axis normal to their best-fit plane."""
    C = cams.centers - cams.centers.mean(0)
    normal = np.linalg.svd(C)[2][2]
    e1 = np.linalg.svd(C)[2][0]
    e2 = np.cross(normal, e1)
    d = cams.centers - centre
    az = np.sort(np.degrees(np.arctan2(d @ e2, d @ e1)))
    return float(np.max(np.diff(np.concatenate([az, [az[0] + 360]]))))


DATASETS = {  # name: (silhouettes, max azimuth gap, occupied voxel range at 64^3 in the auto box)
    "thu_wd_human": ("masks", 60, (2000, 60000)),
    "inria_dancer": ("masks", 90, (2000, 60000)),
    "nerf_lego": ("masks", 90, (5000, 150000)),
    "oxford_dino": ("blue", 20, (2000, 150000)),
    "middlebury_templeSR": ("dark", 60, (5000, 200000)),
    "uu_infomcv_seated": ("plate", 240, (5000, 200000)),
}


@pytest.mark.slow
@pytest.mark.realdata
@pytest.mark.parametrize("name", list(DATASETS))
def test_real_dataset_calibration(name, data_dir):
    from nodes.capture.load import load_capture

    kind, max_gap, count = DATASETS[name]
    cap = load_capture(data_dir / name)
    cams, imgs = cap["cameras"], cap["images"].images
    masks = {"masks": lambda: cap["masks"].masks, "blue": lambda: [blue_key(i) for i in imgs],
             "dark": lambda: [dark_key(i) for i in imgs],
             "plate": lambda: [plate_key(i, p) for i, p in zip(imgs, cap["background"].images)]}[kind]()
    box = auto_bounds(masks, cams)
    centre = box.mean(0)
    for v in range(len(cams)):          # the object is in front of every camera and inside its image
        uv, z = cams.project(centre[None], v)
        assert z[0] > 0 and 0 <= uv[0, 0] < cams[v].width and 0 <= uv[0, 1] < cams[v].height, f"{name} view {v}"
    assert surround(cams, centre) < max_gap, f"{name}: cameras leave a gap of {surround(cams, centre):.0f} degrees"
    occ, cov = hull_coverage(masks, cams, box)
    assert count[0] < occ.sum() < count[1], f"{name}: {occ.sum()} voxels"
    if kind == "dark":
        # no shipped silhouettes and a recipe that keeps shadows: compare with the README box instead
        readme = np.array([[-0.073568, 0.021728, -0.012445], [0.028855, 0.181892, 0.062736]])
        assert np.all(box[0] < readme[0] + 0.01) and np.all(box[1] > readme[1] - 0.01), box
        occ_readme = coarse_hull(masks, cams, readme, 64)
        frac = occ_readme.mean()
        assert abs(frac - 0.291) < 0.03, f"{name}: {frac:.3f} of the README box occupied (SOURCE.md: 29.1 %)"
    else:
        assert cov.min() >= 0.93, f"{name}: projected hull covers {np.round(cov, 3).tolist()} of the silhouettes"


# ------------------------------------------------------------------ Qualisys .qca
def qca_text(cams: Cameras, left=0, top=0) -> str:
    """A Qualisys calibration XML for ``cams``, encoded as read_qualisys documents it (centre in mm, rotation
    columns row by row with the y and z axes flipped, intrinsics in 1/64 px relative to the sensor)."""
    f = lambda x: repr(float(x))  # noqa: E731
    rows = []
    for c in cams:
        R, C = c.Rt[:, :3], c.center * 1000.0
        M = np.diag([1.0, -1.0, -1.0]) @ R            # A = M^T, R = (A diag(1,-1,-1))^T
        rs = " ".join(f'r{a + 1}{b + 1}="{f(M[a, b])}"' for a in range(3) for b in range(3))
        k1, k2, p1, p2, k3 = (f(v) for v in c.dist)
        rows.append(f'''    <camera active="1" serial="{c.name}" viewrotation="0">
      <fov_video bottom="{top + c.height - 1}" left="{left}" right="{left + c.width - 1}" top="{top}"/>
      <transform {rs} x="{f(C[0])}" y="{f(C[1])}" z="{f(C[2])}"/>
      <intrinsic centerPointU="{f((c.K[0, 2] + left) * 64)}" centerPointV="{f((c.K[1, 2] + top) * 64)}"
        focalLengthU="{f(c.K[0, 0] * 64)}" focalLengthV="{f(c.K[1, 1] * 64)}" radialDistortion1="{k1}"
        radialDistortion2="{k2}" radialDistortion3="{k3}" skew="0.000000" tangentalDistortion1="{p1}"
        tangentalDistortion2="{p2}"/>
    </camera>''')
    return ("<?xml version='1.0' encoding='ASCII'?>\n<calibration type=\"regular\">\n  <cameras>\n"
            + "\n".join(rows) + "\n  </cameras>\n</calibration>\n")


def test_qualisys_round_trip(tmp_path):
    """K, R, t, distortion and size come back within 1e-9 from a .qca written for known cameras (also with a
    cropped field of view: the principal point is relative to fov_video's top-left)."""
    cams = rig()
    for left, top, fname in ((0, 0, "Calib.qca.txt"), (16, 8, "crop.qca")):
        (tmp_path / fname).write_text(qca_text(cams, left, top))
        back = load_cameras(tmp_path / fname)
        assert back.names == cams.names
        for a, b in zip(cams, back):
            assert (a.width, a.height) == (b.width, b.height)
            for x, y in ((a.K, b.K), (a.Rt, b.Rt), (a.dist, b.dist)):
                assert np.abs(x - y).max() < 1e-9, (a.name, x, y)
    xml = tmp_path / "qtm.xml"          # an .xml holding a Qualisys calibration is recognised too
    xml.write_text(qca_text(cams))
    assert_same(cams, load_cameras(xml), tol=1e-9)
    (tmp_path / "calibration").mkdir()   # and a dataset folder's calibration/*.qca.txt
    (tmp_path / "calibration" / "Calib.qca.txt").write_text(qca_text(cams))
    assert_same(cams, load_cameras(tmp_path / "calibration" / ".."), tol=1e-9)


def nth(text: str, old: str, new: str, n: int) -> str:
    """``text`` with the n-th (0-based) occurrence of ``old`` replaced by ``new``."""
    parts = text.split(old)
    return old.join(parts[: n + 1]) + new + old.join(parts[n + 1:])


@pytest.mark.parametrize("edit, match", [
    (lambda t: nth(t, "<transform", "<transformX", 0), r"camera 0 'view0': no <transform>"),
    (lambda t: nth(t, ' x="', ' x="12abc', 1), r"camera 1 'view1': <transform> x=\"12abc"),
    (lambda t: re.sub(r'focalLengthU="[^"]*"', 'focalLengthU="nan"', t, count=1), r"camera 0 'view0': <intrinsic> contains NaN"),
    (lambda t: nth(t, ' centerPointV="', ' centerPointW="', 2), r"camera 2 'view2': <intrinsic> has no attribute centerPointV"),
    (lambda t: t.replace("</calibration>", ""), r"unreadable Qualisys XML"),
])
def test_qualisys_malformed(tmp_path, edit, match):
    """A missing element or attribute, or a value that is not a number, is one DataError naming the file and
    the camera."""
    p = tmp_path / "bad.qca.txt"
    p.write_text(edit(qca_text(rig())))
    with pytest.raises(DataError, match=r"bad\.qca\.txt: " + match):
        load_cameras(p)


def qualisys_cameras(data_dir):
    return load_cameras(data_dir / "pose2sim_single" / "calibration" / "Calib.qca.txt")


@pytest.mark.realdata
def test_qualisys_real_pose2sim(data_dir):
    """pose2sim_single's Calib.qca.txt: 4 portrait cameras round the treadmill, about 1.7-2.1 m high, each
    looking at the origin (in front, inside the image), with the world's +Z pointing up in every image."""
    cams = qualisys_cameras(data_dir)
    assert cams.names == ["cam01", "cam02", "cam03", "cam04"]
    assert all((c.width, c.height) == (1088, 1920) for c in cams)
    C = cams.centers
    dist3, heights = np.linalg.norm(C, axis=1), C[:, 2]
    # measured: 3.06, 3.17, 4.44, 4.44 m from the origin (2.40-4.02 m horizontally); 1.69-2.09 m high
    assert np.all((2.7 < dist3) & (dist3 < 4.6)), dist3
    assert np.all((1.65 < heights) & (heights < 2.15)), heights
    for v, c in enumerate(cams):
        uv, z = cams.project(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), v)
        assert np.all(z > 0), (c.name, z)
        assert 0 <= uv[0, 0] < c.width and 0 <= uv[0, 1] < c.height, (c.name, uv[0])
        assert uv[1, 1] < uv[0, 1] - 100, f"{c.name}: 1 m above the origin is not higher in the image ({uv})"
        fwd = c.Rt[2, :3]                       # optical axis within 30 degrees of the origin's direction
        assert fwd @ (-c.center) / np.linalg.norm(c.center) > np.cos(np.radians(30)), c.name


@pytest.mark.realdata
def test_qualisys_real_pose2sim_capture(data_dir, caplog):
    """The capture pairs the videos with the Qualisys cameras by name; cam03/cam04's frame 0 has the
    calibrated 1088x1920 size, but cam01/cam02's videos are 1080x1920 (SOURCE.md) against a 1088x1920 field
    of view. Within a video encoder's 16 px the capture takes them as the calibrated view less its last columns
    (K kept) and says so: of the three readings, crop at the right, centred crop and a scale to 1080, the crop at
    the right fits best (the 4-view hull of the person mattes: mean silhouette IoU 0.888 vs 0.878 and 0.884).
    Farther than 16 px it refuses."""
    from nodes.capture.load import load_capture, read_image

    root = data_dir / "pose2sim_single"
    cams = qualisys_cameras(data_dir)
    for c in cams[2:]:
        img = read_image(root / "videos" / f"{c.name}.mp4", 0)
        assert img.shape[:2] == (c.height, c.width), c.name
    out = load_capture(root, images="videos/{name}.mp4", calibration="calibration/Calib.qca.txt")
    assert "camera 'cam01': image 1080x1920, calibration 1088x1920: taken as the calibrated image less its last 8 " \
           "columns" in caplog.text
    got = out["cameras"]
    assert [(c.width, c.height) for c in got] == [(1080, 1920), (1080, 1920), (1088, 1920), (1088, 1920)]
    assert all(np.allclose(g.K, c.K) for g, c in zip(got, cams))
