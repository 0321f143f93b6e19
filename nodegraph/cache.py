"""Content-addressed artifact store.

Layout under the cache root:
    objects/ab/abcdef.../        one work item's kept outputs, complete iff the folder exists
        meta.json                key components, output types, the stored ports' files, wall time
        PORT/...                 each kept output in its type's on-disk form (an item's other outputs
                                 lived only in memory: they are not in its entry)
    staging/                     folders being written (renamed into objects/ when complete; `gc` removes
                                 leftovers older than 6 hours, so it never pulls one from a running write)
    filehash.json                size+mtime -> content hash of external input files
    imports.json                 what each node module imports, by content hash (nodegraph/fingerprint.py)
    index/                       last key per graph node and frame (for `explain`)

A work item's outputs are written into a staging folder and renamed into place in one step, so a run
killed mid-write leaves no half artifact: the item simply is not cached and the next run recomputes it.
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
import uuid
from pathlib import Path

from .errors import DataError


def atomic_write_bytes(path: Path, data: bytes):
    """Write a file so that readers see the old content or the new, never a part (temp file + rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str):
    atomic_write_bytes(path, text.encode())


class Cache:
    def __init__(self, root: str | Path):
        self.root = Path(root).resolve()
        self.objects = self.root / "objects"
        self.staging = self.root / "staging"

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

    def has(self, key: str) -> bool:
        return (self.object_dir(key) / "meta.json").is_file()

    def stored(self, key: str) -> set[str] | None:
        """The output ports stored in ``key``'s entry (a port whose value was None counts), or None when there is
        no readable entry."""
        try:
            return set(json.loads((self.object_dir(key) / "meta.json").read_text()).get("files", {}))
        except (OSError, ValueError, AttributeError):
            return None

    def meta(self, key: str) -> dict:
        try:
            return json.loads((self.object_dir(key) / "meta.json").read_text())
        except (OSError, ValueError) as exc:
            raise DataError(f"cache entry {key} is unreadable ({exc}); run `cache gc` or delete it") from None

    def load(self, key: str, port: str, dtype):
        folder = self.object_dir(key) / port
        files = self.meta(key).get("files", {})
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
        try:
            return dtype.load(folder)
        except DataError:
            raise
        except Exception as exc:
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
            meta = dict(meta, key=key, files=files, types=types, created=time.time())
            (stage / "meta.json").write_text(json.dumps(meta, indent=1, sort_keys=True))
            final = self.object_dir(key)
            final.parent.mkdir(parents=True, exist_ok=True)
            old = self.stored(key)
            if old is not None and not set(files) <= old:  # more ports than the entry there: replace it
                self.evict(key)
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
            stale = not meta.is_file()
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
        d = self.object_dir(key)
        if d.is_dir():
            self.staging.mkdir(parents=True, exist_ok=True)
            trash = self.staging / f"evicted.{key}.{uuid.uuid4().hex[:8]}"
            try:
                os.rename(d, trash)
            except OSError:
                return
            shutil.rmtree(trash, ignore_errors=True)

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
