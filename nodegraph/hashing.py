"""Content hashes for cache keys: canonical JSON of params, node implementation fingerprints, and input
files hashed by content (never by path) with a size+mtime shortcut kept in the cache folder."""
from __future__ import annotations

import hashlib
import json
import os
from functools import lru_cache
from pathlib import Path

KEY_SCHEMA = 1  # bump when the key recipe changes; old entries then simply stop matching


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


@lru_cache(maxsize=None)
def implementation_fingerprint(cls) -> str:
    from .node import implementation_sources

    return digest(implementation_sources(cls))[:16]


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
        self.db[str(p)] = [sig, h.hexdigest()]
        self.dirty = True
        return h.hexdigest()

    def path(self, p: str | Path) -> str:
        p = Path(p)
        if p.is_file():
            return self.file(p)
        entries = []
        for root, dirs, files in os.walk(p):
            dirs[:] = sorted(d for d in dirs if not d.startswith("."))
            for name in sorted(files):
                if name.startswith("."):
                    continue
                fp = Path(root) / name
                entries.append([fp.relative_to(p).as_posix(), self.file(fp)])
        return digest(entries)

    def save(self):
        if self.dirty and self.db_path:
            from .cache import atomic_write_text

            atomic_write_text(self.db_path, json.dumps(self.db))
            self.dirty = False
