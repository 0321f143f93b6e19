"""Per-view host work on a few threads: the views of a frame are independent, and what they spend their time in
(NumPy's array loops, OpenCV, hashlib) releases the GIL, so a -j 1 run on a 2-core machine uses its second core
for them too (a node's PoCL kernels already use every core)."""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

_POOL: list = []


def threads() -> int:
    """Threads for per-view work: the process's share of the cores (VOLCAP_CV_THREADS, which the executors set
    per worker process), else all of them."""
    try:
        return max(1, int(os.environ.get("VOLCAP_CV_THREADS") or os.cpu_count() or 1))
    except ValueError:
        return max(1, os.cpu_count() or 1)


def map_views(fn, *iterables, count: int | None = None) -> list:
    """``[fn(*args) for args in zip(*iterables)]``, in order, on ``threads()`` threads (``count`` when given; in
    this thread when one); the first exception raised is raised here."""
    n = threads() if count is None else max(1, int(count))
    if n == 1:
        return [fn(*args) for args in zip(*iterables)]
    if not _POOL or _POOL[0][0] != n:
        _POOL[:] = [(n, ThreadPoolExecutor(n, thread_name_prefix="views"))]
    return list(_POOL[0][1].map(fn, *iterables))
