"""Content hashes for cache keys: canonical JSON of params, node implementation fingerprints, and input
files hashed by content (never by path) with a size+mtime shortcut kept in the cache folder."""
from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path

from .errors import DataError

RACY_NS = 2_000_000_000  # see FileHasher.file
KEY_SCHEMA = 2  # bump when the key recipe or the form of entries changes; old entries then simply stop matching
# 2: images and masks stored as raw .npy (were PNG + EXR); entries hold only the kept ports


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

    def __init__(self, db_path: Path | None):
        self.db_path = db_path
        self.db: dict = {}
        self.dirty = False
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
        symlinked files and folders followed)."""
        p = Path(p)
        try:
            if p.is_file():
                return self.file(p)
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
                    fp = Path(root) / name
                    rel = fp.relative_to(p).as_posix()
                    entries.append([rel, self.file(fp) if fp.exists() else "broken link"])
            return digest(entries)
        except OSError as exc:
            raise DataError(f"cannot read input {p} to hash it: {exc}") from None

    def save(self):
        if self.dirty and self.db_path:
            from .cache import atomic_write_text

            atomic_write_text(self.db_path, json.dumps(self.db))
            self.dirty = False
