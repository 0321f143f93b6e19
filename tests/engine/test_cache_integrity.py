"""Cache integrity (issue 12, item 5) and inputs that are not regular files (item 8): a damaged entry is never
published or read as a success, a garbage meta.json is not a hit, `cache verify` finds damage, and input
folders holding a FIFO or a link to /dev/zero are hashed without hanging."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np

import enginenodes  # registers the t.* nodes
from nodegraph.cache import Cache
from nodegraph.cli import main as cli
from nodegraph.executors import LocalExecutor
from nodegraph.graphfile import load_graph
from nodegraph.run import explain, run_graph

assert enginenodes.Source.type_name == "t.source"
HERE = Path(__file__).resolve().parent

CHAIN = """\
frames: 0:3
nodes:
  src:   {type: t.source, params: {value: 1.0, size: 64}}
  scale: {type: t.scale, in: {x: src.out}, params: {factor: 3}}
  plus:  {type: t.add, in: {a: scale.out}}
  total: {type: t.total, in: {x: plus.out}}
  write: {type: t.write, in: {x: plus.out}}
"""


def graph(tmp_path, text=CHAIN) -> Path:
    p = tmp_path / "g.yaml"
    p.write_text(textwrap.dedent(text))
    return p


def run(tmp_path, p, **kw):
    return run_graph(load_graph(p, **kw), Cache(tmp_path / "cache"), tmp_path / "out", LocalExecutor(1), progress=False)


def record(res, node, frame):
    return next(r for r in res.records if r["node"] == node and r["frame"] == frame)


def flip_bytes(path: Path, n=3):
    """Damage a file without changing its size (what bit rot or a bad copy does)."""
    data = bytearray(path.read_bytes())
    for i in range(n):
        k = len(data) - 1 - 7 * i
        data[k] ^= 0x5A
    path.write_bytes(bytes(data))


def test_flipped_bytes_in_a_cached_export_are_recomputed_not_published(tmp_path, capsys):
    p = graph(tmp_path)
    first = run(tmp_path, p)
    good = (tmp_path / "out" / "sum_000.txt").read_bytes()
    w0 = record(first, "write", 0)
    flip_bytes(Path(w0["cache_dir"]) / "files" / "files" / "sum_000.txt", 2)
    (tmp_path / "out" / "sum_000.txt").unlink()
    cache = Cache(tmp_path / "cache")
    rows = {(r["node"], r["frame"]): r for r in explain(load_graph(p), cache)}
    assert not rows[("write", 0)]["cached"] and "damaged" in " ".join(rows[("write", 0)]["changed"]), rows[("write", 0)]
    res = run(tmp_path, p)
    assert res.ok, res.failures
    r = record(res, "write", 0)
    assert r["status"] == "done" and any("damaged" in w for w in r["warnings"]), r
    assert (tmp_path / "out" / "sum_000.txt").read_bytes() == good
    assert record(res, "write", 1)["status"] == "cached"
    again = run(tmp_path, p)
    assert again.ok and again.counts() == {"cached": 13}


def test_flipped_bytes_in_a_cached_input_are_recomputed_before_use(tmp_path):
    p = graph(tmp_path)
    first = run(tmp_path, p)
    s0 = record(first, "src", 0)
    flip_bytes(Path(s0["cache_dir"]) / "out" / "array.npy")  # np.load still reads it: the data is wrong
    res = run(tmp_path, p, overrides=["scale.factor=4"])
    assert res.ok, res.failures
    assert record(res, "src", 0)["status"] == "done" and record(res, "src", 1)["status"] == "cached"
    from conftest import output

    np.testing.assert_array_equal(output(res, "scale", "out", 0), np.full(64, 4.0))


def test_damage_found_while_loading_is_reported_and_evicted(tmp_path):
    """Damage that appears after the run checked the entry (or in a worker) is caught by the loader."""
    p = graph(tmp_path)
    first = run(tmp_path, p)
    s0 = record(first, "src", 0)
    cache = Cache(tmp_path / "cache")
    flip_bytes(Path(s0["cache_dir"]) / "out" / "array.npy")
    from nodegraph import DataError
    from nodegraph.types import Array

    try:
        cache.load(s0["key"], "out", Array)
        raise AssertionError("damaged content was loaded")
    except DataError as exc:
        assert "damaged" in str(exc) and "out/array.npy" in str(exc), exc


def test_a_read_short_of_memory_or_file_handles_keeps_the_entry(tmp_path, monkeypatch):
    """A load that fails for the machine's want of file handles or memory is reported as such and the entry is kept
    (only damage evicts: the run's on_result evicts for a CorruptInput); a damaged file still is damage."""
    import errno

    from nodegraph import DataError, VolcapError
    from nodegraph.records import Ref, type_name
    from nodegraph.types import Array
    from nodegraph.worker import CorruptInput, _load_input

    first = run(tmp_path, graph(tmp_path))
    s0 = record(first, "src", 0)
    cache = Cache(tmp_path / "cache")
    ref = Ref(s0["key"], "out", type_name(Array))
    for short in (OSError(errno.EMFILE, "Too many open files"), MemoryError("Unable to allocate 48.0 MiB")):
        def load(folder, short=short):
            raise short
        monkeypatch.setattr(Array, "load", load)
        try:
            _load_input(cache, "x", ref, None)
            raise AssertionError("a failed load returned a value")
        except CorruptInput:
            raise AssertionError("a machine's shortage was taken for a damaged entry")
        except DataError:
            raise AssertionError("a machine's shortage was taken for a damaged entry")
        except VolcapError as exc:
            assert "cannot be read now" in str(exc) and "the entry is kept" in str(exc), exc
        assert cache.has(s0["key"])
    monkeypatch.setattr(Array, "load", lambda folder: (_ for _ in ()).throw(ValueError("bad header")))
    try:
        _load_input(cache, "x", ref, None)
        raise AssertionError("a failed load returned a value")
    except CorruptInput as exc:
        assert "cannot be read" in str(exc) and "bad header" in str(exc), exc


def test_garbage_meta_json_is_not_a_hit(tmp_path):
    p = graph(tmp_path)
    first = run(tmp_path, p)
    for node, text in (("src", "{not json"), ("plus", "[1, 2]"), ("write", '{"files": 7}')):
        (Path(record(first, node, 1)["cache_dir"]) / "meta.json").write_text(text)
    cache = Cache(tmp_path / "cache")
    assert not cache.has(record(first, "src", 1)["key"])
    res = run(tmp_path, p)
    assert res.ok, res.failures
    for node in ("src", "plus", "write"):
        assert record(res, node, 1)["status"] == "done", node
    assert run(tmp_path, p).counts() == {"cached": 13}


def test_cache_verify_command(tmp_path, capsys):
    p = graph(tmp_path)
    first = run(tmp_path, p)
    c = ["--cache", str(tmp_path / "cache")]
    assert cli([*c, "cache", "verify"]) == 0
    assert "13 entries checked, 0 damaged" in capsys.readouterr().out
    flip_bytes(Path(record(first, "plus", 2)["cache_dir"]) / "out" / "array.npy")
    (Path(record(first, "total", None)["cache_dir"]) / "meta.json").write_text("garbage")
    assert cli([*c, "cache", "verify"]) == 1
    out = capsys.readouterr().out
    assert f"damaged {record(first, 'plus', 2)['key']}" in out and "plus@2" in out and "out/array.npy" in out, out
    assert f"damaged {record(first, 'total', None)['key']}" in out and "meta.json" in out, out
    assert "13 entries checked, 2 damaged (removed)" in out
    assert cli([*c, "cache", "verify"]) == 0
    assert "11 entries checked, 0 damaged" in capsys.readouterr().out


def test_meta_records_a_content_hash_per_file(tmp_path):
    first = run(tmp_path, graph(tmp_path))
    meta = json.loads((Path(record(first, "write", 0)["cache_dir"]) / "meta.json").read_text())
    assert set(meta["hashes"]) == {"files/files/sum_000.txt"} and len(meta["hashes"]["files/files/sum_000.txt"]) == 32



def test_entries_hashed_with_older_hashes_are_still_checked(tmp_path):
    """New entries record XXH3-128 (``hash``: xxh3-128); an entry an older version wrote with SHA-256 (first 128
    bits) or BLAKE2b-128 is checked with that hash (unchanged: a hit; a flipped byte: damaged); a hash this version
    does not know makes the entry damaged (recomputed), not a crash."""
    import hashlib

    import xxhash

    import nodegraph.cache as C

    first = run(tmp_path, graph(tmp_path))
    s0 = record(first, "src", 0)
    entry = Path(s0["cache_dir"])
    meta = json.loads((entry / "meta.json").read_text())
    npy = entry / "out" / "array.npy"
    assert meta["hash"] == "xxh3-128"
    assert meta["hashes"]["out/array.npy"] == xxhash.xxh3_128_hexdigest(npy.read_bytes())
    good = npy.read_bytes()
    for name, digest in (("sha256-128", lambda b: hashlib.sha256(b).hexdigest()[:32]),
                         ("blake2b-128", lambda b: hashlib.blake2b(b, digest_size=16).hexdigest())):
        npy.write_bytes(good)
        old = dict(meta, hash=name, hashes={f: digest((entry / f).read_bytes()) for f in meta["hashes"]})
        (entry / "meta.json").write_text(json.dumps(old))
        (entry / C.CHECKED).unlink(missing_ok=True)
        assert Cache(tmp_path / "cache").verify(s0["key"], full=True) is None, name
        flip_bytes(npy)
        assert "does not match" in Cache(tmp_path / "cache").verify(s0["key"], full=True), name
    (entry / "meta.json").write_text(json.dumps(dict(old, hash="md4-9")))
    assert "md4-9" in Cache(tmp_path / "cache").verify(s0["key"], full=True)

# ---------------------------------------------------------------- item 8: FIFOs and devices in input folders
def test_fifo_and_dev_zero_in_an_input_folder_do_not_hang(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    (data / "a.bin").write_bytes(b"abc")
    os.mkfifo(data / "pipe")
    os.symlink("/dev/zero", data / "zeros")
    p = graph(tmp_path, "nodes:\n  d: {type: t.readdir, params: {path: data}}\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    args = ["--cache", str(tmp_path / "cache"), "run", str(p), "--out", str(tmp_path / "out"), "-q", "-j", "1"]
    code = f"import sys, enginenodes; from nodegraph.cli import main; sys.exit(main({args!r}))"
    try:
        proc = subprocess.run([sys.executable, "-c", code], env=env, cwd=HERE, capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired:
        raise AssertionError("run hung on a FIFO or /dev/zero in an input folder") from None
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    warned = [ln for ln in proc.stderr.splitlines() if ln.startswith("warning:") and "not regular files" in ln]
    assert warned and "pipe" in warned[0] and "zeros" in warned[0], proc.stderr


def test_checked_files_are_not_read_again_until_they_change(tmp_path, monkeypatch):
    """A file whose hash matched is trusted by (inode, size, mtime, ctime) until it changes: a re-run does not
    hash 150 MB of camera images per frame again, yet a rewrite that restores the old mtime is still caught."""
    import nodegraph.cache as C

    monkeypatch.setattr(C, "SETTLED_NS", 0)  # the test's files are seconds old
    p = graph(tmp_path)
    first = run(tmp_path, p)
    s0 = record(first, "src", 0)
    npy = Path(s0["cache_dir"]) / "out" / "array.npy"
    hashed = []
    real = C.file_hash
    monkeypatch.setattr(C, "file_hash", lambda f, *a: hashed.append(Path(f).name) or real(f, *a))
    from nodegraph.types import Array

    assert Cache(tmp_path / "cache").verify(s0["key"]) is None and hashed == ["array.npy"]
    hashed.clear()
    Cache(tmp_path / "cache").load(s0["key"], "out", Array)
    assert hashed == [], "an unchanged, checked file is not read again"
    st = npy.stat()
    flip_bytes(npy)
    os.utime(npy, ns=(st.st_atime_ns, st.st_mtime_ns))   # same size, same mtime: only the ctime moved
    assert "does not match" in Cache(tmp_path / "cache").verify(s0["key"])

    # damage no write made (a forged record standing in for bit rot under the same inode): reads trust the
    # record, `cache verify` reads every file
    s1 = record(first, "src", 1)
    npy = Path(s1["cache_dir"]) / "out" / "array.npy"
    flip_bytes(npy)
    st = npy.stat()
    (npy.parent.parent / C.CHECKED).write_text(json.dumps({"out/array.npy": [st.st_ino, st.st_size, st.st_mtime_ns,
                                                                            st.st_ctime_ns]}))
    assert Cache(tmp_path / "cache").verify(s1["key"]) is None
    assert "does not match" in Cache(tmp_path / "cache").verify(s1["key"], full=True)


def test_an_entrys_files_are_hashed_on_threads_with_the_same_digests(tmp_path):
    """file_hash gives the digests a plain read gives (an empty file too), in every algorithm an entry may record;
    verify hashes an entry's files on a few threads and still names the damaged one (and a missing one before any
    hash)."""
    import hashlib

    from nodegraph import cache as C

    class Many:
        name = "t.many"

        @staticmethod
        def save(value, folder):
            for i, b in enumerate(value):
                (folder / f"{i}.bin").write_bytes(b)

        @staticmethod
        def files(folder):
            return sorted(folder.iterdir())

    rng = np.random.default_rng(5)
    blobs = [b""] + [rng.integers(0, 256, int(n), dtype=np.uint8).tobytes() for n in rng.integers(1, 300_000, 7)]
    for name, make in C.HASHES.items():
        for i, b in enumerate(blobs):
            f = tmp_path / f"{name}_{i}.bin"
            f.write_bytes(b)
            with open(f, "rb") as fh:
                assert C.file_hash(f, name) == hashlib.file_digest(fh, make).hexdigest()[:32], (name, i)
    c = Cache(tmp_path / "cache")
    c.write("k" * 32, {"p": (Many, blobs)}, {})
    assert c.verify("k" * 32, full=True) is None
    d = c.object_dir("k" * 32)
    flip_bytes(d / "p" / "5.bin", 1)
    assert c.verify("k" * 32, full=True) == "p/5.bin does not match the content hash recorded when it was written"
    (d / "p" / "6.bin").unlink()
    assert c.verify("k" * 32, full=True) == "p/6.bin is missing"
