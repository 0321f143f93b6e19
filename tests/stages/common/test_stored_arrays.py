"""Stored arrays (nodes.common.types._load_array): the cache's .npy files read back memory-mapped, read-only, as
NumPy's own np.load(mmap_mode="r") reads them, the header np.save writes parsed directly and every other one by
NumPy; a damaged file is one clear DataError naming it."""
from __future__ import annotations

import numpy as np
import pytest

from nodegraph import DataError
from nodes.common.types import _load_array

CASES = {
    "hd_image": np.arange(1080 * 1920 * 3, dtype=np.uint64).astype(np.uint8).reshape(1080, 1920, 3),
    "float32": np.linspace(-1, 1, 12, dtype=np.float32).reshape(3, 4),
    "fortran": np.asfortranarray(np.arange(24, dtype=np.float64).reshape(2, 3, 4)),
    "scalar": np.array(5.25),
    "empty": np.zeros((0, 3), np.float32),
    "one_d_bool": np.array([True, False, True]),
    "big_endian": np.arange(7, dtype=">i4"),
    "unicode": np.array(["ab", "c"]),
    "complex": np.array([[1 + 2j, 3j]]),
    "empty_strings": np.zeros(3, dtype="S0"),        # saved as |S1
    # headers np.save writes that the direct reader leaves to NumPy's
    "structured": np.array([(1.5, 2)], dtype=[("a", "<f4"), ("b", "<i2")]),
    "datetime": np.array(["2026-12-07"], dtype="datetime64[D]"),
}
NUMPY_READS = {"structured", "datetime"}


@pytest.mark.parametrize("name", sorted(CASES))
def test_stored_arrays_read_back_as_numpy_reads_them(tmp_path, name):
    a = CASES[name]
    p = tmp_path / f"{name}.npy"
    np.save(p, a, allow_pickle=False)
    ref = np.load(p, mmap_mode="r" if a.size else None, allow_pickle=False)
    got = _load_array(p)
    assert got.dtype == ref.dtype and got.shape == ref.shape
    assert np.array_equal(np.asarray(got), np.asarray(ref))
    assert got.flags.f_contiguous == ref.flags.f_contiguous and got.flags.c_contiguous == ref.flags.c_contiguous
    assert not got.flags.writeable                 # nodes must not edit their inputs in place
    # the direct reader (a plain array over the map) for np.save's own headers; NumPy's memmap for the rest
    assert (type(got) is np.memmap) == (name in NUMPY_READS and a.size > 0)
    whole = _load_array(p, mapped=False)
    assert whole.flags.writeable and np.array_equal(whole, a)


def test_a_version_2_header_is_read_directly(tmp_path):
    a = np.arange(30, dtype=np.int16).reshape(5, 6)
    p = tmp_path / "v2.npy"
    with open(p, "wb") as f:
        np.lib.format.write_array(f, a, version=(2, 0))
    got = _load_array(p)
    assert type(got) is np.ndarray and got.dtype == a.dtype and np.array_equal(got, a) and not got.flags.writeable


def test_damaged_arrays_are_one_clear_error(tmp_path):
    p = tmp_path / "cut.npy"
    np.save(p, np.zeros((100, 100)))
    with open(p, "r+b") as f:
        f.truncate(1000)                            # the header survives, the data does not
    with pytest.raises(DataError, match=r"cut.npy: unreadable array .*promises 80000 bytes of data, the file holds 872"):
        _load_array(p)
    for name, value in (("objects", np.array([{"a": 1}], dtype=object)), ("no_objects", np.zeros(0, dtype=object))):
        q = tmp_path / f"{name}.npy"
        np.save(q, value, allow_pickle=True)
        with pytest.raises(DataError, match=f"{name}.npy: unreadable array"):
            _load_array(q)
    r = tmp_path / "garbage.npy"
    r.write_bytes(b"not an array at all")
    with pytest.raises(DataError, match="garbage.npy: unreadable array"):
        _load_array(r)
    e = tmp_path / "empty.npy"
    e.write_bytes(b"")
    with pytest.raises(DataError, match="empty.npy: unreadable array"):
        _load_array(e)
    with pytest.raises(DataError, match="missing.npy: unreadable array"):
        _load_array(tmp_path / "missing.npy")
    b = tmp_path / "badtype.npy"                    # a header of np.save's form with a type code NumPy does not know
    np.save(b, np.zeros(4, np.float32))
    raw = b.read_bytes()
    b.write_bytes(raw.replace(b"'<f4'", b"'<x4'"))
    with pytest.raises(DataError, match="badtype.npy: unreadable array"):
        _load_array(b)


def test_windowed_images_paste_into_the_last_block_once_nothing_holds_it():
    """Images read back as their windows' pixels are pasted into the last frame's block when no image of that frame
    is held any more (only what the last windows wrote outside the new ones is zeroed), else into a new one: 300
    random frames of three cameras (windows anywhere, empty, whole; a camera now and then without a window; a frame
    kept alive every third time) give the images a fresh zeroed paste gives, the reused block about half the time;
    a held frame stays as it was."""
    from nodes.common import types as T

    rng = np.random.default_rng(0)
    shapes = [(40, 50, 3), (30, 20, 3), (10, 10, 3)]

    def fresh(crops, windows):
        out = []
        for a, sh, w in zip(crops, shapes, windows):
            if w is None:
                out.append(a)
                continue
            im = np.zeros(sh, np.uint8)
            im[w[1]:w[3], w[0]:w[2]] = a
            out.append(im)
        return out

    reused, held = 0, None
    for t in range(300):
        windows = []
        for h, w, _ in shapes:
            x0, y0 = int(rng.integers(0, w + 1)), int(rng.integers(0, h + 1))
            windows.append((x0, y0, int(rng.integers(x0, w + 1)), int(rng.integers(y0, h + 1))))
        if t % 7 == 0:
            windows[2] = None
        crops = [rng.integers(1, 256, (w[3] - w[1], w[2] - w[0], 3) if w else sh, dtype=np.uint8)
                 for w, sh in zip(windows, shapes)]
        before = T._PasteBlock.last
        got = T._pasted(crops, shapes, windows)
        reused += T._PasteBlock.last is before
        assert all(np.array_equal(a, b) for a, b in zip(got, fresh(crops, windows))), t
        assert not any(im.flags.writeable for im, w in zip(got, windows) if w is not None)
        if t % 3 == 0:
            held, held_copy = got, [im.copy() for im in got]
        elif held is not None:
            assert all(np.array_equal(a, b) for a, b in zip(held, held_copy)), t
        del got
    assert 100 < reused < 250, reused


# ---------------------------------------------------------------- meshes (Mesh.save / Mesh.load: binary PLY)
def _meshes():
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2)
    rng = np.random.default_rng(3)
    return {
        "sphere": trimesh.Trimesh(sphere.vertices.astype(np.float32), sphere.faces, process=False),
        "random_float64": trimesh.Trimesh(rng.normal(size=(40, 3)), rng.integers(0, 40, (60, 3)), process=False),
        "empty": trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), process=False),
        "points_only": trimesh.Trimesh(rng.normal(size=(5, 3)), np.zeros((0, 3), np.int64), process=False),
        "vertex_colours": trimesh.Trimesh(sphere.vertices, sphere.faces, process=False,
                                          vertex_colors=rng.integers(0, 255, (len(sphere.vertices), 4))),
    }


@pytest.mark.parametrize("name", sorted(_meshes()))
def test_stored_meshes_read_back_as_trimesh_reads_them(tmp_path, name):
    import trimesh

    from nodes.common.types import Mesh

    m = _meshes()[name]
    Mesh.save(m, tmp_path)
    got = Mesh.load(tmp_path)
    ref = trimesh.load(tmp_path / "mesh.ply", process=False, force="mesh")   # any PLY reader reads our file
    assert got.vertices.dtype == np.float64 and got.faces.dtype == ref.faces.dtype
    if len(m.faces):       # (trimesh's reader drops the vertices of a mesh without faces; ours keeps them)
        assert np.array_equal(got.vertices, ref.vertices) and np.array_equal(got.faces, ref.faces)
    assert np.array_equal(got.vertices, np.asarray(m.vertices, np.float32).astype(np.float64))
    assert np.array_equal(got.faces, m.faces)
    assert got.visual.kind == ref.visual.kind == m.visual.kind        # colours: trimesh's writer and reader
    if m.visual.kind == "vertex":
        assert np.array_equal(got.visual.vertex_colors, m.visual.vertex_colors)


def test_meshes_trimesh_wrote_still_load(tmp_path):
    """Cache entries written before the direct writer (trimesh's PLY, with its comment line) read the same."""
    from nodes.common.types import Mesh

    m = _meshes()["sphere"]
    m.export(tmp_path / "mesh.ply")
    got = Mesh.load(tmp_path)
    assert np.array_equal(got.vertices, m.vertices) and np.array_equal(got.faces, m.faces) and not got.metadata


def test_the_direct_ply_reader_leaves_other_files_to_trimesh(tmp_path):
    """Only the exact plain layout is read directly: a polygon, a short file or another header gives None."""
    from nodes.common.types import _PLY_FACE, _read_plain_ply, _write_plain_ply

    p = tmp_path / "mesh.ply"
    _write_plain_ply(p, np.eye(3), [[0, 1, 2]])
    v, f = _read_plain_ply(p)
    assert v.dtype == np.float64 and f.dtype == np.int64
    assert np.array_equal(v, np.eye(3)) and np.array_equal(f, [[0, 1, 2]])
    data = p.read_bytes()
    p.write_bytes(data[:-1])                                               # cut short
    assert _read_plain_ply(p) is None
    p.write_bytes(data + b"\0")                                            # a byte too many
    assert _read_plain_ply(p) is None
    quad = bytearray(data)
    quad[-_PLY_FACE.itemsize] = 4                                          # a face that says it has 4 corners
    p.write_bytes(bytes(quad))
    assert _read_plain_ply(p) is None
    p.write_bytes(data.replace(b"property float z", b"property float w"))
    assert _read_plain_ply(p) is None
    p.write_bytes(data.replace(b"binary_little_endian 1.0", b"binary_little_endian 1x0"))
    assert _read_plain_ply(p) is None
