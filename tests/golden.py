"""Golden-file harness: compare a node's output with a stored, reviewed expected file.

    def test_hull_golden(golden):
        out = run_node("hull", {...}, {...})
        golden.check("hull_sphere", out["volume"], Volume)              # exact for volumes
        golden.check("key_chroma", out["masks"], Masks, iou=0.995)      # masks: exact unless iou= given

Tolerances per type (override with keyword arguments):
    Masks   exact pixels, or mean IoU >= iou
    Volume  exact occupancy and bbox (or max abs difference <= atol for soft volumes)
    Mesh    vertex and face counts within count_rtol, symmetric Hausdorff <= hausdorff (absolute units)
    Table   numbers within rtol / atol, everything else equal
    Images  every pixel within atol (max over channels), or all but a fraction frac; mean difference <= mean
    Array   allclose(rtol, atol)
    Skeleton  same parents and names, joints within atol (default 1e-9), weights / motion within atol
Regenerate deliberately with ``pytest --update-golden``; the run lists every file it rewrote so the diff
can be reviewed before committing. Golden folders live in tests/golden/NAME/ in the type's own format.
"""
from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np

from nodegraph import types as E
from nodes.common import types as T

GOLDEN_DIR = Path(__file__).parent / "golden"


class Golden:
    def __init__(self, update: bool, rewritten: list):
        self.update = update
        self.rewritten = rewritten

    def check(self, name: str, value, dtype: type[E.DataType], **tol):
        folder = GOLDEN_DIR / name
        if self.update:
            if folder.exists():
                shutil.rmtree(folder)
            folder.mkdir(parents=True)
            save(value, folder, dtype)
            self.rewritten.append(name)
            return
        assert folder.is_dir(), f"no golden file for '{name}' in {GOLDEN_DIR}: create it with pytest --update-golden and review it"
        expected = load(folder, dtype)
        compare(value, expected, dtype, name, **tol)


# Golden images and masks are PNG (soft alpha EXR), viewable and small, whatever form the cache uses.
def save(value, folder: Path, dtype):
    import cv2

    if issubclass(dtype, T.Masks):
        for i, (n, m) in enumerate(zip(value.names, value.masks)):
            cv2.imwrite(str(folder / f"{n}.png"), np.asarray(m))
            if value.alpha is not None:
                T.write_exr(folder / f"{n}.alpha.exr", value.alpha[i])
        (folder / "names.json").write_text(json.dumps({"names": value.names, "alpha": value.alpha is not None}))
    elif issubclass(dtype, T.Images):
        for n, im in zip(value.names, value.images):
            cv2.imwrite(str(folder / f"{n}.png"), np.asarray(im)[:, :, ::-1])
        (folder / "names.json").write_text(json.dumps(value.names))
    else:
        dtype.save(value, folder)


def load(folder: Path, dtype):
    import cv2

    if issubclass(dtype, T.Masks):
        meta = json.loads((folder / "names.json").read_text())
        masks = [cv2.imread(str(folder / f"{n}.png"), cv2.IMREAD_GRAYSCALE) for n in meta["names"]]
        alpha = [T.read_exr(folder / f"{n}.alpha.exr") for n in meta["names"]] if meta["alpha"] else None
        return T.MaskSet(masks, alpha, meta["names"])
    if issubclass(dtype, T.Images):
        names = json.loads((folder / "names.json").read_text())
        return T.ImageSet([cv2.imread(str(folder / f"{n}.png"), cv2.IMREAD_COLOR)[:, :, ::-1] for n in names], names)
    return dtype.load(folder)


def compare(actual, expected, dtype, name, **tol):
    if issubclass(dtype, T.Masks):
        assert len(actual.masks) == len(expected.masks), f"{name}: {len(actual.masks)} masks, golden has {len(expected.masks)}"
        ious = []
        for a, e in zip(actual.masks, expected.masks):
            assert a.shape == e.shape, f"{name}: mask shape {a.shape} vs golden {e.shape}"
            a, e = a > 127, e > 127
            union = np.logical_or(a, e).sum()
            ious.append(1.0 if union == 0 else np.logical_and(a, e).sum() / union)
        need = tol.get("iou", 1.0)
        assert min(ious) >= need, f"{name}: mask IoU vs golden min {min(ious):.5f} < {need}"
    elif issubclass(dtype, T.Volume):
        assert actual.occupancy.shape == expected.occupancy.shape, f"{name}: volume shape {actual.occupancy.shape} vs golden {expected.occupancy.shape}"
        np.testing.assert_allclose(actual.bbox_min, expected.bbox_min, atol=1e-9, err_msg=f"{name}: bbox_min")
        np.testing.assert_allclose(actual.bbox_max, expected.bbox_max, atol=1e-9, err_msg=f"{name}: bbox_max")
        atol = tol.get("atol", 0)
        diff = np.abs(actual.occupancy.astype(np.float64) - expected.occupancy.astype(np.float64))
        assert diff.max() <= atol, f"{name}: {int((diff > atol).sum())} voxels differ from golden (atol {atol})"
    elif issubclass(dtype, T.Mesh):
        rtol = tol.get("count_rtol", 0.0)
        for what in ("vertices", "faces"):
            na, ne = len(getattr(actual, what)), len(getattr(expected, what))
            assert abs(na - ne) <= rtol * ne, f"{name}: {na} {what}, golden has {ne} (tolerance {rtol:.1%})"
        h = hausdorff(actual.vertices, expected.vertices)
        limit = tol.get("hausdorff", 1e-6)
        assert h <= limit, f"{name}: Hausdorff distance to golden {h:.3g} > {limit}"
    elif issubclass(dtype, E.Table):
        _compare_json(actual, expected, name, tol.get("rtol", 1e-6), tol.get("atol", 1e-9))
    elif issubclass(dtype, E.Array):
        np.testing.assert_allclose(actual, expected, rtol=tol.get("rtol", 1e-6), atol=tol.get("atol", 0), err_msg=name)
    elif issubclass(dtype, T.Skeleton):
        assert list(actual.parents) == list(expected.parents), f"{name}: parents {actual.parents} vs golden {expected.parents}"
        assert list(actual.names) == list(expected.names), f"{name}: names {actual.names} vs golden {expected.names}"
        atol = tol.get("atol", 1e-9)
        for what in ("joints", "weights", "rotations", "translations"):
            a, e = getattr(actual, what), getattr(expected, what)
            assert (a is None) == (e is None), f"{name}: {what} present in one of actual / golden only"
            if e is not None:
                np.testing.assert_allclose(a, e, rtol=0, atol=atol, err_msg=f"{name}: {what}")
    elif issubclass(dtype, T.Images):
        assert list(actual.names) == list(expected.names), f"{name}: images {actual.names} != {expected.names}"
        for n, a, e in zip(actual.names, actual.images, expected.images, strict=True):
            assert a.shape == e.shape, f"{name}/{n}: shape {a.shape} != {e.shape}"
            d = np.abs(a.astype(int) - e.astype(int)).max(axis=-1)
            atol, frac = tol.get("atol", 0), tol.get("frac", 0.0)
            over = float(np.mean(d > atol))
            assert over <= frac, (f"{name}/{n}: {over:.2%} of pixels differ by more than {atol} (allowed {frac:.2%}; "
                                  f"up to {d.max()})")
            if "mean" in tol:
                assert d.mean() <= tol["mean"], f"{name}/{n}: mean pixel difference {d.mean():.2f} > {tol['mean']}"
    else:
        raise TypeError(f"no golden comparison for {dtype.name}")


def hausdorff(a: np.ndarray, b: np.ndarray) -> float:
    from scipy.spatial import cKDTree

    if len(a) == 0 or len(b) == 0:
        return math.inf if len(a) != len(b) else 0.0
    return float(max(cKDTree(b).query(a)[0].max(), cKDTree(a).query(b)[0].max()))


def _compare_json(a, e, path, rtol, atol):
    if isinstance(e, dict):
        assert isinstance(a, dict) and set(a) == set(e), f"{path}: keys {sorted(a) if isinstance(a, dict) else a} vs golden {sorted(e)}"
        for k in e:
            _compare_json(a[k], e[k], f"{path}.{k}", rtol, atol)
    elif isinstance(e, list):
        assert isinstance(a, list) and len(a) == len(e), f"{path}: list length differs from golden"
        for i, (x, y) in enumerate(zip(a, e)):
            _compare_json(x, y, f"{path}[{i}]", rtol, atol)
    elif isinstance(e, (int, float)) and not isinstance(e, bool):
        assert math.isclose(a, e, rel_tol=rtol, abs_tol=atol), f"{path}: {a} vs golden {e}"
    else:
        assert a == e, f"{path}: {a!r} vs golden {e!r}"
