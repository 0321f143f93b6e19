"""nodes.common.views.map_views: per-view work on threads gives the serial result, in order."""
from __future__ import annotations

import numpy as np
import pytest

from nodes.common import views


@pytest.mark.parametrize("threads", ["1", "2", "3"])
def test_map_views_keeps_order_and_raises(monkeypatch, threads):
    monkeypatch.setenv("VOLCAP_CV_THREADS", threads)
    assert views.threads() == int(threads)
    arrays = [np.full(1000, i, np.float32) for i in range(13)]
    got = views.map_views(lambda a, k: float(a.sum()) * k, arrays, range(13))
    assert got == [1000.0 * i * i for i in range(13)]

    def boom(i):
        if i == 5:
            raise ValueError("view 5")
        return i

    with pytest.raises(ValueError, match="view 5"):
        views.map_views(boom, range(9))


def test_map_views_count_overrides_the_workers_share(monkeypatch):
    """``count``: that many threads whatever the worker's share (export.volumetric runs last, on every core)."""
    import threading

    monkeypatch.setenv("VOLCAP_CV_THREADS", "1")
    names = views.map_views(lambda i: threading.current_thread().name, range(4))
    assert all(n == threading.current_thread().name for n in names)           # one: in this thread
    barrier = threading.Barrier(2, timeout=10)                                  # two at once, or it times out
    got = views.map_views(lambda i: (barrier.wait() if i < 2 else 0, i)[1], range(6), count=2)
    assert got == list(range(6))
