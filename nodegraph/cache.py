"""Content-addressed artifact store.

Layout under the cache root:
    objects/ab/abcdef.../        one work item's kept outputs, complete iff the folder exists
        meta.json                key components, output types, the stored ports' files, wall time, a content
                                 hash of every file
        PORT/...                 each kept output in its type's on-disk form (an item's other outputs
                                 lived only in memory: they are not in its entry)
    staging/                     folders being written (renamed into objects/ when complete; `gc` removes
                                 leftovers older than 6 hours, so it never pulls one from a running write)
    filehash.json                size+mtime -> content hash of external input files
    imports.json                 what each node module imports, by content hash (nodegraph/fingerprint.py)
    index/                       last key per graph node and frame (for `explain`)

A work item's outputs are written into a staging folder and renamed into place in one step, so a run
killed mid-write leaves no half artifact: the item simply is not cached and the next run recomputes it.

Content verification: ``write`` records a 128-bit content hash of every stored file in meta.json (``hash`` names it:
XXH3-128; entries written before record SHA-256's first 128 bits or BLAKE2b-128, still checked with those); ``load`` checks
the files it reads against them (DataError "damaged"), ``verify`` checks a whole entry, and an entry whose
meta.json is not a readable record is not a hit. A damaged entry is evicted and recomputed (run.py checks
what a run will read before it starts; `cache verify` checks everything).

A file whose hash matched is remembered in its entry's ``checked.json`` by (inode, size, mtime, ctime): later
reads trust it without reading it again while all four are unchanged (any write to the file, and any copy of
it, changes its ctime, which nobody can set back). A file is remembered only once its ctime is a few seconds
old (coarse timestamps: a write in the same tick would keep it). Damage that no write made (bit rot under an
unchanged inode) is the file system's to catch; `cache verify` hashes every file whatever is remembered.
"""
from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import stat
import tempfile
import time
import uuid
from pathlib import Path

import xxhash

from .errors import DataError, VolcapError


def _umask() -> int:
    """The process umask, read without changing it where the system tells (Linux: /proc/self/status)."""
    try:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1], 8) for line in f if line.startswith("Umask:"))
    except (OSError, StopIteration, ValueError, IndexError):
        mask = os.umask(0o022)
        os.umask(mask)
        return mask


def _short_of(exc: BaseException) -> bool:
    """Whether a read failed for want of memory or file handles (MemoryError, EMFILE, ENFILE, ENOMEM), which
    says nothing about the file."""
    return isinstance(exc, MemoryError) or (isinstance(exc, OSError) and exc.errno in (errno.EMFILE, errno.ENFILE,
                                                                                        errno.ENOMEM))


def atomic_write_bytes(path: Path, data: bytes):
    """Write a file so that readers see the old content or the new, never a part (temp file + rename). The file
    gets the mode a plain open() gives (0o666 less the umask), not mkstemp's private 0o600."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str):
    atomic_write_bytes(path, text.encode())


HASH_NAME = "xxh3-128"          # what new entries record; entries written with the others are still checked
HASHES = {"xxh3-128": xxhash.xxh3_128, "sha256-128": hashlib.sha256,
          "blake2b-128": lambda: hashlib.blake2b(digest_size=16)}
CHECKED = "checked.json"        # per entry: file -> [inode, size, mtime_ns, ctime_ns] when its hash last matched
SETTLED_NS = 2_000_000_000      # files younger than this are not remembered (coarse timestamps)


def _read_checked(entry: Path) -> dict:
    try:
        checked = json.loads((entry / CHECKED).read_text())
    except (OSError, ValueError):
        return {}
    return checked if isinstance(checked, dict) else {}


def file_hash(path: Path, name: str = HASH_NAME) -> str:
    """The content hash ``name`` (a key of HASHES) of a file, 128 bits in hex: any flipped bit changes it. XXH3-128
    (xxhash): the hash checks stored files against damage (bit rot, a cut or overwritten file), not against someone
    who can write into the cache folder anyway, so it need not be cryptographic: 25 GB/s against SHA-256's 1.05 (in
    hardware, SHA-NI) on the 2-core Intel Xeon, where SHA-256 took 28 ms for the ~29 MB a frame of 24 HD views keeps
    of its despilled images, once when written and again when first read. Read, not memory-mapped: a page the disk
    cannot give back (or a file cut while it is hashed) is then an OSError the caller reports ("cannot be read"),
    not a SIGBUS that kills the process. (The reads and the hash run outside the GIL: files hashed on two threads,
    ``_hash_all``, take half the time.)"""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, HASHES[name]).hexdigest()[:32]   # 128 bits, as BLAKE2b-128 recorded


def _hash_all(folder: Path, names: list[str], name: str = HASH_NAME, errors: bool = False) -> dict:
    """file -> file_hash of the files ``names`` under ``folder``; several at once on a few threads when they are
    many (the hashing runs outside the GIL: a frame of 24 views' images, masks and alpha on both cores of a 2-core
    machine). ``errors``: a file that cannot be read maps to its OSError instead of raising it."""
    def one(f):
        try:
            return file_hash(folder / f, name)
        except OSError as exc:
            if not errors:
                raise
            return exc

    if len(names) < 4:
        return {f: one(f) for f in names}
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(min(4, os.cpu_count() or 1)) as pool:
        return dict(zip(names, pool.map(one, names)))


def _valid_meta(meta) -> bool:
    """A meta.json record the cache can use: a mapping whose 'files' maps ports to lists of paths (or None)."""
    if not isinstance(meta, dict) or not isinstance(meta.get("files"), dict):
        return False
    if not all(v is None or (isinstance(v, list) and all(isinstance(f, str) for f in v)) for v in meta["files"].values()):
        return False
    return isinstance(meta.get("hashes", {}), dict)


class Cache:
    def __init__(self, root: str | Path):
        self.root = Path(root).resolve()
        self.objects = self.root / "objects"
        self.staging = self.root / "staging"
        self.verified: set[str] = set()   # keys whose whole content was checked by this object (see verify)
        self._metas: dict[str, dict] = {}

    def prepare(self):
        """Create the cache folders, or raise DataError saying why the cache cannot be used."""
        try:
            for d in (self.objects, self.staging):
                d.mkdir(parents=True, exist_ok=True)
            probe = tempfile.NamedTemporaryFile(dir=self.staging, prefix=".probe.")
            probe.close()
        except OSError as exc:
            raise DataError(f"cache folder {self.root} cannot be used: {exc.strerror or exc} "
                            "(choose another with --cache or $VOLCAP_CACHE)") from None

    def object_dir(self, key: str) -> Path:
        return self.objects / key[:2] / key

    def _read_meta(self, key: str) -> dict | None:
        """meta.json of ``key`` when it is a valid record, else None. Valid records are remembered by this object
        (an entry never changes once in place; evict and write forget it)."""
        meta = self._metas.get(key)
        if meta is None:
            try:
                meta = json.loads((self.object_dir(key) / "meta.json").read_text())
            except (OSError, ValueError):
                return None
            if not _valid_meta(meta):
                return None
            self._metas[key] = meta
        return meta

    def has(self, key: str) -> bool:
        """Whether ``key`` is stored: its folder holds a readable meta.json record (garbage is not a hit)."""
        return self._read_meta(key) is not None

    def stored(self, key: str) -> set[str] | None:
        """The output ports stored in ``key``'s entry (a port whose value was None counts), or None when there is
        no readable entry."""
        meta = self._read_meta(key)
        return None if meta is None else set(meta["files"])

    def meta(self, key: str) -> dict:
        meta = self._read_meta(key)
        if meta is not None:
            return meta
        try:
            json.loads((self.object_dir(key) / "meta.json").read_text())
        except (OSError, ValueError) as exc:
            raise DataError(f"cache entry {key} is unreadable ({exc}); run `cache gc` or delete it") from None
        raise DataError(f"cache entry {key} is damaged: meta.json is not a cache record")

    def _check_files(self, key: str, meta: dict, files: list[str], full: bool = False) -> str | None:
        """What is wrong with ``files`` of the entry (missing, or content not matching meta.json), or None.
        Files remembered in checked.json as unchanged since their hash last matched are not read (``full``:
        hash every file)."""
        d = self.object_dir(key)
        hashes = meta.get("hashes")
        algo = meta.get("hash", "blake2b-128")   # entries before the name was recorded used BLAKE2b
        if hashes is not None and algo not in HASHES:
            return f"its content hash '{algo}' is not one this version knows ({', '.join(HASHES)})"
        checked = {} if full else _read_checked(d)
        learned = {}
        sigs = {}            # the files to hash, with their stat signatures before the hash
        for f in files:
            try:
                st = (d / f).stat()
            except OSError:
                st = None
            if st is None or not stat.S_ISREG(st.st_mode):
                return f"{f} is missing"
            if hashes is None:   # entries written before content hashes can only be checked for presence
                continue
            sig = [st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns]
            if checked.get(f) != sig:
                sigs[f] = sig
        got = _hash_all(d, list(sigs), algo, errors=True)   # an entry's files on a few threads
        for f, sig in sigs.items():
            if isinstance(got[f], OSError):
                return f"{f} cannot be read ({got[f].strerror or got[f]})"
            if hashes.get(f) != got[f]:
                return f"{f} does not match the content hash recorded when it was written"
            if time.time_ns() - sig[3] > SETTLED_NS:
                learned[f] = sig
        if learned:
            checked = _read_checked(d) if full else checked
            checked.update(learned)
            try:
                if d.is_dir():   # not re-created after an eviction
                    atomic_write_text(d / CHECKED, json.dumps(checked))
            except OSError:   # a read-only cache is still usable: its files are hashed on every read
                pass
        return None

    def verify(self, key: str, full: bool = False) -> str | None:
        """Check a whole entry: None when meta.json is a record and every file it lists is there with the
        content it was written with, else what is wrong (the caller evicts it). ``full``: read every file, also
        those remembered as unchanged since they were last checked."""
        try:
            meta = self.meta(key)
        except DataError:
            return "meta.json is missing or not a cache record"
        problem = self._check_files(key, meta, [f for files in meta["files"].values() for f in files or []], full)
        if problem is None:
            self.verified.add(key)
        return problem

    def load(self, key: str, port: str, dtype):
        folder = self.object_dir(key) / port
        meta = self.meta(key)
        files = meta["files"]
        if port not in files:
            raise DataError(f"cache entry {key} does not hold output '{port}' ({dtype.name}): it was kept in memory "
                            "when the entry was written")
        listed = files[port]
        if listed is None and not folder.is_dir():
            return None  # an optional output that was None
        missing = [f for f in listed or [] if not (self.object_dir(key) / f).is_file()]
        if listed is None or missing:
            raise DataError(f"cache entry {key}/{port} ({dtype.name}) is incomplete: "
                            f"{missing[0] if missing else port + '/'} is missing")
        if key not in self.verified:
            problem = self._check_files(key, meta, listed)
            if problem:
                raise DataError(f"cache entry {key}/{port} ({dtype.name}) is damaged: {problem}")
        try:
            return dtype.load(folder)
        except DataError:
            raise
        except Exception as exc:
            if _short_of(exc):   # the machine's limit, not the entry's damage: a DataError would have it evicted
                raise VolcapError(f"cache entry {key}/{port} ({dtype.name}) cannot be read now: {type(exc).__name__}: "
                                  f"{exc} (this machine ran short; the entry is kept, rerun when it has room)") from None
            raise DataError(f"cache entry {key}/{port} ({dtype.name}) cannot be read: {type(exc).__name__}: {exc}") from None

    def write(self, key: str, outputs: dict, meta: dict) -> Path:
        """Save ``outputs`` (port -> (dtype, value or None)) atomically under ``key``. An existing entry (with
        fewer ports kept) is replaced in one step."""
        self.staging.mkdir(parents=True, exist_ok=True)
        stage = self.staging / f"{key}.{os.getpid()}.{uuid.uuid4().hex[:8]}"
        stage.mkdir()
        try:
            files, types = {}, {}
            for port, (dtype, value) in outputs.items():
                types[port] = dtype.name
                if value is None:
                    files[port] = None
                    continue
                d = stage / port
                d.mkdir()
                dtype.save(value, d)
                files[port] = [p.relative_to(stage).as_posix() for p in dtype.files(d)]
            hashes = _hash_all(stage, [f for listed in files.values() for f in listed or []])
            meta = dict(meta, key=key, files=files, types=types, created=time.time(), hash=HASH_NAME, hashes=hashes)
            (stage / "meta.json").write_text(json.dumps(meta, indent=1, sort_keys=True))
            final = self.object_dir(key)
            final.parent.mkdir(parents=True, exist_ok=True)
            self._metas.pop(key, None)
            self.verified.discard(key)
            old = self.stored(key)
            if final.exists() and (old is None or not set(files) <= old):  # damaged (garbage meta.json), or more
                self.evict(key)                                             # ports than the entry there: replace it
            try:
                os.rename(stage, final)
            except OSError:
                if not self.has(key):  # not a concurrent writer of the same key: a real failure
                    raise
                shutil.rmtree(stage, ignore_errors=True)
            return final
        except BaseException:
            shutil.rmtree(stage, ignore_errors=True)
            raise

    def entries(self):
        """(key, meta, size in bytes) of every complete entry."""
        if not self.objects.is_dir():
            return
        for d in sorted(self.objects.glob("*/*")):
            try:
                meta = json.loads((d / "meta.json").read_text())
            except (OSError, ValueError):
                continue
            if not _valid_meta(meta):
                continue
            size = sum(f.stat().st_size for f in d.rglob("*") if f.is_file())
            yield d.name, meta, size

    def gc(self, max_age_days: float | None = None) -> tuple[int, int]:
        """Remove staging leftovers and incomplete entries; with ``max_age_days``, also entries not used
        for that long. Returns (entries removed, bytes freed)."""
        removed = freed = 0
        now = time.time()
        for d in list(self.staging.glob("*")) if self.staging.is_dir() else []:
            if now - _newest_mtime(d) < STAGING_GRACE_S:  # another run may be writing it right now
                continue
            freed += _size(d)
            shutil.rmtree(d, ignore_errors=True)
            removed += 1
        for d in list(self.objects.glob("*/*")) if self.objects.is_dir() else []:
            meta = d / "meta.json"
            stale = not self.has(d.name)
            if not stale and max_age_days is not None:
                stale = now - meta.stat().st_mtime > max_age_days * 86400
            if stale:
                freed += _size(d)
                shutil.rmtree(d, ignore_errors=True)
                removed += 1
        return removed, freed

    def touch(self, key: str):
        """Mark an entry as used now (gc --max-age keeps recently used entries)."""
        try:
            os.utime(self.object_dir(key) / "meta.json")
        except OSError:
            pass

    def evict(self, key: str):
        """Remove one entry (e.g. found corrupt): moved aside in one step, then deleted."""
        self._metas.pop(key, None)
        self.verified.discard(key)
        d = self.object_dir(key)
        if d.is_dir():
            self.staging.mkdir(parents=True, exist_ok=True)
            trash = self.staging / f"evicted.{key}.{uuid.uuid4().hex[:8]}"
            try:
                os.rename(d, trash)
            except OSError:
                return
            shutil.rmtree(trash, ignore_errors=True)

    def verify_all(self):
        """Check every entry (also those whose meta.json is garbage); yields (key, meta or None, problem or
        None). The caller decides what to do with the damaged ones (``cache verify`` evicts them)."""
        if not self.objects.is_dir():
            return
        for d in sorted(self.objects.glob("*/*")):
            if not d.is_dir():
                continue
            key = d.name
            problem = self.verify(key, full=True)
            try:
                meta = self.meta(key)
            except DataError:
                meta = None
            yield key, meta, problem

    def clear(self):
        if self.root.exists() and not self.root.is_dir():
            raise DataError(f"cache folder {self.root} is a file, not a cache")
        for sub in ("objects", "staging", "index"):
            shutil.rmtree(self.root / sub, ignore_errors=True)
        (self.root / "filehash.json").unlink(missing_ok=True)
        (self.root / "imports.json").unlink(missing_ok=True)


STAGING_GRACE_S = 6 * 3600  # gc leaves younger staging folders alone: a running write may own them


def _newest_mtime(d: Path) -> float:
    try:
        return max([d.stat().st_mtime] + [f.stat().st_mtime for f in d.rglob("*")])
    except OSError:  # vanished while we looked: its writer finished or removed it
        return time.time()


def _size(d: Path) -> int:
    return sum(f.stat().st_size for f in d.rglob("*") if f.is_file()) if d.is_dir() else 0
