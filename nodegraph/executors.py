"""Executors run the work items that are not cached. Interface:

    executor.run(items, specs, cache_root, on_result)

``items`` are in dependency order, ``specs`` maps key -> plain-data spec (what ``worker.execute`` takes),
``on_result(key, result)`` is called in the calling thread once per item, with result["status"] one of
done / failed / skipped. An item whose input failed is skipped, never run; independent items go on.
"""
from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool

from .worker import execute, start_worker


class _DependencyTracker:
    """The ready set of a dependency graph, with failure propagation to descendants."""

    def __init__(self, items):
        self.items = {it.key: it for it in items}
        self.waiting = {it.key: {d for d in it.deps if d in self.items} for it in items}
        self.children: dict[str, list[str]] = {k: [] for k in self.items}
        for k, deps in self.waiting.items():
            for d in deps:
                self.children[d].append(k)
        self.ready = [it.key for it in items if not self.waiting[it.key]]

    def finished(self, key: str, ok: bool) -> list[str]:
        """Record an outcome; return the keys that can no longer run (descendants of a failure)."""
        if ok:
            for c in self.children[key]:
                if c not in self.waiting:  # already given up (another input failed)
                    continue
                self.waiting[c].discard(key)
                if not self.waiting[c]:
                    self.ready.append(c)
            return []
        doomed, stack = [], list(self.children[key])
        while stack:
            c = stack.pop()
            if c in self.waiting and c not in doomed:
                doomed.append(c)
                del self.waiting[c]
                stack.extend(self.children[c])
        return doomed


def _skip(tracker, key, on_result, reason_node):
    for d in tracker.finished(key, ok=False):
        on_result(d, {"status": "skipped", "error": f"upstream '{reason_node}' failed", "seconds": 0.0})


def worker_threads(workers: int) -> dict:
    """Environment for one of ``workers`` worker processes on this machine: thread pools (the OpenCL CPU
    device, OMP, and libraries reading VOLCAP_CV_THREADS) use their share of the cores instead of all of
    them, so processes do not oversubscribe. Values the user has set are kept."""
    share = str(max(1, (os.cpu_count() or 1) // max(1, workers)))
    env = {}
    for var in ("POCL_MAX_PTHREAD_COUNT", "OMP_NUM_THREADS", "VOLCAP_CV_THREADS"):
        env[var] = os.environ.get(var, share)
    return env


def _init_worker(env: dict):
    os.environ.update(env)
    start_worker()


class LocalExecutor:
    """Runs items in a local process pool (spawn: OpenCL must never be forked), or in this process when
    jobs == 1."""

    name = "local"

    def __init__(self, jobs: int | None = None):
        self.jobs = max(1, jobs or os.cpu_count() or 1)

    def run(self, items, specs, cache_root, on_result):
        tracker = _DependencyTracker(items)
        if self.jobs == 1 or len(items) == 1:
            while tracker.ready:
                key = tracker.ready.pop(0)
                res = execute(specs[key], cache_root)
                on_result(key, res)
                if res["status"] == "done":
                    tracker.finished(key, ok=True)
                else:
                    _skip(tracker, key, on_result, tracker.items[key].node)
            return
        ctx = multiprocessing.get_context("spawn")
        workers = min(self.jobs, len(items))
        init = {"initializer": _init_worker, "initargs": (worker_threads(workers),)}
        pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, **init)
        running = {}
        try:
            while tracker.ready or running:
                while tracker.ready and len(running) < self.jobs:
                    key = tracker.ready.pop(0)
                    with _sigint_ignored():  # workers start ignoring Ctrl-C: this process handles it
                        running[pool.submit(execute, specs[key], cache_root)] = key
                done, _ = wait(running, return_when=FIRST_COMPLETED)
                broken = False
                for fut in done:
                    key = running.pop(fut)
                    try:
                        res = fut.result()
                    except BrokenProcessPool:
                        broken = True
                        res = {"status": "failed", "seconds": 0.0,
                               "error": "the worker process died (killed, or out of memory); rerun to retry"}
                    except Exception as exc:  # pickling problems and the like
                        res = {"status": "failed", "seconds": 0.0, "error": f"{type(exc).__name__}: {exc}"}
                    on_result(key, res)
                    if res["status"] == "done":
                        tracker.finished(key, ok=True)
                    else:
                        _skip(tracker, key, on_result, tracker.items[key].node)
                if broken:  # the pool is unusable: fail what was in flight, start a new pool
                    for fut, key in list(running.items()):
                        on_result(key, {"status": "failed", "seconds": 0.0, "error": "worker pool broke; rerun to retry"})
                        _skip(tracker, key, on_result, tracker.items[key].node)
                    running.clear()
                    pool.shutdown(wait=False, cancel_futures=True)
                    pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, **init)
        except KeyboardInterrupt:  # stop the workers now; what they were writing stays in staging/
            for proc in list((getattr(pool, "_processes", None) or {}).values()):
                proc.terminate()
            raise
        finally:
            pool.shutdown(wait=True, cancel_futures=True)


@contextlib.contextmanager
def _sigint_ignored():
    """Ignore SIGINT while worker processes may be spawned: they inherit 'ignored' (a Python handler is
    not inherited), so Ctrl-C in a terminal reaches only this process, not every worker with a traceback."""
    try:
        old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:  # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


def make_executor(name: str, jobs: int | None = None, **options):
    if name == "local":
        return LocalExecutor(jobs)
    if name == "dask":
        from .dask_executor import DaskExecutor

        return DaskExecutor(workers=jobs, scheduler=options.get("scheduler"))
    from .errors import VolcapError

    raise VolcapError(f"unknown executor '{name}' (local or dask)")
