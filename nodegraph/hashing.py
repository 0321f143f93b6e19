"""Content hashes for cache keys: canonical JSON of params, node implementation fingerprints, and input
files hashed by content (never by path) with a size+mtime shortcut kept in the cache folder."""
from __future__ import annotations

import hashlib
import json
import os
import stat
import time
from pathlib import Path

from .errors import DataError

RACY_NS = 2_000_000_000  # see FileHasher.file
MAX_INPUT_FILES = 500_000  # an input folder with more files is not a dataset but a file system
KEY_SCHEMA = 4  # bump when the key recipe or the form of entries changes; old entries then simply stop matching
# 2: images and masks stored as raw .npy (were PNG + EXR); entries hold only the kept ports
# 3: the environment (library versions, OpenCL device: nodegraph/environment.py) is part of every key
# 4: entries' files hashed with XXH3-128 (an older version sharing the cache would find the hash unknown, evict the
#    entry and write it again, and the two would take turns)


def digest(obj) -> str:
    """SHA-256 of the canonical JSON form of ``obj`` (sorted keys, no whitespace)."""
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), default=_default)
    return hashlib.sha256(text.encode()).hexdigest()


def _default(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"cannot hash {type(o).__name__}")


class FileHasher:
    """Hashes files and folders by content. Remembers (size, mtime_ns) -> hash per absolute path in
    ``db_path`` so unchanged files are not re-read; the path itself never enters a key."""

    def __init__(self, db_path: Path | None, exclude=()):
        self.db_path = db_path
        self.exclude = [Path(e).resolve() for e in exclude]   # folders an input folder must not contain (the cache)
        self.db: dict = {}
        self.dirty = False
        self.skipped: dict[str, list[str]] = {}  # input folder -> entries that are not regular files (not read)
        if db_path and db_path.exists():
            try:
                self.db = json.loads(db_path.read_text())
            except (OSError, ValueError):
                self.db = {}

    def file(self, p: Path) -> str:
        st = p.stat()
        sig = [st.st_size, st.st_mtime_ns]
        hit = self.db.get(str(p))
        if hit and hit[0] == sig:
            return hit[1]
        h = hashlib.sha256()
        with open(p, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
        # a file modified within the last seconds may change again without its size or mtime changing
        # (coarse timestamps): remember its hash only once it has settled
        if time.time_ns() - st.st_mtime_ns > RACY_NS:
            self.db[str(p)] = [sig, h.hexdigest()]
            self.dirty = True
        return h.hexdigest()

    def path(self, p: str | Path) -> str:
        """Content hash of a file, or of a folder's files (names and contents; hidden ones ignored,
        symlinked files and folders followed). Only regular files are read: a FIFO, socket or device (or a
        link to one, such as /dev/zero) would block or never end; in a folder such entries are recorded in
        ``skipped`` (their names enter the hash), as an input path they are a DataError."""
        p = Path(p)
        try:
            if p.is_file():
                return self.file(p)
            if p.exists() and not p.is_dir():
                raise DataError(f"input {p} is not a regular file or folder (a FIFO, socket or device?): it is not read")
            real = Path(os.path.realpath(p))
            for e in self.exclude:
                if e == real or real in e.parents:
                    raise DataError(f"input folder {p} contains the cache folder {e}, which changes with every run: "
                                    "give the data folder itself")
            entries, seen = [], set()
            for root, dirs, files in os.walk(p, followlinks=True):
                real = os.path.realpath(root)
                if real in seen:  # a link back up the tree
                    dirs[:] = []
                    continue
                seen.add(real)
                dirs[:] = sorted(d for d in dirs if not d.startswith("."))
                for name in sorted(files):
                    if name.startswith("."):
                        continue
                    if len(entries) >= MAX_INPUT_FILES:
                        raise DataError(f"input folder {p} holds more than {MAX_INPUT_FILES:,} files: give the data "
                                        "folder itself")
                    fp = Path(root) / name
                    rel = fp.relative_to(p).as_posix()
                    try:
                        mode = fp.stat().st_mode
                    except OSError:
                        entries.append([rel, "broken link"])
                        continue
                    if stat.S_ISREG(mode):
                        entries.append([rel, self.file(fp)])
                    else:
                        self.skipped.setdefault(str(p), []).append(rel)
                        entries.append([rel, "not a regular file"])
            return digest(entries)
        except OSError as exc:
            raise DataError(f"cannot read input {p} to hash it: {exc}") from None

    def save(self):
        if self.dirty and self.db_path:
            from .cache import atomic_write_text

            atomic_write_text(self.db_path, json.dumps(self.db))
            self.dirty = False
