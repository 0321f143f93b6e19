"""Executors run the work units that are not up to date (nodegraph/plan.py, nodegraph/run.py). Interface:

    executor.run(units, cache_root, on_result)

``units`` are in dependency order; each has ``key``, ``deps`` (keys of the units it reads from), ``label`` and
``spec`` (a records.UnitSpec: what ``worker.execute_unit`` takes). ``on_result(item_key, result)`` is called in
the calling thread once per item, with a records.Result whose status is one of done / failed / skipped. A unit runs once every
unit it depends on has finished; an item whose input failed is skipped, never run; independent items go on.
"""
from __future__ import annotations

import contextlib
import dataclasses
import graphlib
import multiprocessing
import os
import signal
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool

from .records import Result, UnitSpec
from .worker import execute_unit, start_worker


_NEVER = "(never done)"   # what a unit on a dependency cycle waits for


class _DependencyTracker:
    """The ready set of a dependency graph of units (graphlib.TopologicalSorter): a unit is ready once every unit
    it reads from finished (successfully or not: which of its items then run is decided inside the unit, item by
    item). ``ready`` keeps the units' order among those ready."""

    def __init__(self, units):
        self.units = {u.key: u for u in units}
        self.index = {u.key: i for i, u in enumerate(units)}
        deps = {u.key: [d for d in u.deps if d in self.units] for u in units}
        while True:
            self.sorter = graphlib.TopologicalSorter(deps)
            try:
                self.sorter.prepare()
                break
            except graphlib.CycleError as exc:  # an engine bug: units on a cycle (and their readers) never start,
                for k in exc.args[1]:            # run.py reports them as failures
                    deps[k] = [_NEVER]
        self.ready = self._ready()
        self.failed_items: dict[str, str] = {}   # key -> node of the items that did not produce their outputs

    def launch(self, key: str) -> UnitSpec:
        """The unit's spec, told which items of other units failed."""
        return dataclasses.replace(self.units[key].spec, failed=dict(self.failed_items))

    def finished(self, key: str, results: dict[str, Result]):
        for item, res in results.items():
            if res.status != "done":
                self.failed_items[item] = res.node or "?"
        self.sorter.done(key)
        self.ready += self._ready()

    def _ready(self) -> list[str]:
        return sorted((k for k in self.sorter.get_ready() if k in self.units), key=self.index.get)


def unit_failed(unit, error: str, cache_root: str) -> dict[str, Result]:
    """Results of a unit whose worker never reported (killed, out of memory): the items whose kept outputs
    reached the cache before it died are done; an item reading one that did not finish is skipped; the others
    failed with ``error``."""
    from .cache import Cache

    cache = Cache(cache_root)
    out, bad = {}, {}
    for s in unit.spec.items:
        down = [k for k in s.input_keys() if k in bad]
        if s.kept and set(s.kept) <= (cache.stored(s.key) or set()):
            out[s.key] = Result("done", node=s.node)
        elif down:
            out[s.key] = Result("skipped", error=f"upstream '{bad[down[0]]}' failed", node=s.node)
            bad[s.key] = bad[down[0]]
        else:
            out[s.key] = Result("failed", error=error, node=s.node)
            bad[s.key] = s.node
    return out


def worker_threads(workers: int) -> dict:
    """Environment for one of ``workers`` worker processes on this machine: thread pools (the OpenCL CPU
    device, OMP, the BLAS under NumPy, and libraries reading VOLCAP_CV_THREADS) use their share of the cores
    instead of all of them, so processes do not oversubscribe. Values the user has set are kept. (Dask's
    nanny sets OMP/MKL/OpenBLAS to 1 thread before spawning a worker: one worker on a 2-core machine then ran
    its BLAS on one core; the Dask executor gives these values as its pre-spawn environment instead.)"""
    share = str(max(1, (os.cpu_count() or 1) // max(1, workers)))
    env = {}
    for var in ("POCL_MAX_PTHREAD_COUNT", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                "VOLCAP_CV_THREADS"):
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

    def run(self, units, cache_root, on_result, on_progress=None):
        """``on_progress(item key, done, total, what)``: a running item's Node.progress (in this process: as it
        is called; from the pool: polled twice a second from the file beside the item's log)."""
        from . import worker

        tracker = _DependencyTracker(units)

        def report(key, results):
            for item, res in results.items():
                on_result(item, res)
            tracker.finished(key, results)

        if self.jobs == 1 or len(units) == 1:
            saved, worker.PROGRESS_HOOK = worker.PROGRESS_HOOK, on_progress
            try:
                while tracker.ready:
                    key = tracker.ready.pop(0)
                    report(key, execute_unit(tracker.launch(key), cache_root))
            finally:
                worker.PROGRESS_HOOK = saved
            return
        seen: dict[str, tuple] = {}

        def poll():
            for key in running.values():
                for spec in tracker.units[key].spec.items:
                    got = worker.read_progress(spec.log)
                    if got is not None and seen.get(spec.key) != got:
                        seen[spec.key] = got
                        on_progress(spec.key, *got)

        ctx = multiprocessing.get_context("spawn")
        workers = min(self.jobs, len(units))
        init = {"initializer": _init_worker, "initargs": (worker_threads(workers),)}
        pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, **init)
        running = {}
        try:
            while tracker.ready or running:
                while tracker.ready and len(running) < self.jobs:
                    key = tracker.ready.pop(0)
                    with _sigint_ignored():  # workers start ignoring Ctrl-C: this process handles it
                        running[pool.submit(execute_unit, tracker.launch(key), cache_root)] = key
                # never an endless wait: a Ctrl-C that another thread of this process took is only flagged for
                # the main thread, which acts on it when it wakes (the cause of one CI timeout of the Ctrl-C test;
                # test_ctrl_c_taken_by_another_thread_stops_a_quiet_pool_run hangs without the timeout)
                done, _ = wait(running, return_when=FIRST_COMPLETED, timeout=0.5)
                if on_progress:
                    poll()
                broken = False
                for fut in done:
                    key = running.pop(fut)
                    try:
                        results = fut.result()
                    except BrokenProcessPool:
                        broken = True
                        results = unit_failed(tracker.units[key], "the worker process died (killed, or out of memory); rerun to retry", cache_root)
                    except Exception as exc:  # pickling problems and the like
                        results = unit_failed(tracker.units[key], f"{type(exc).__name__}: {exc}", cache_root)
                    report(key, results)
                if broken:  # the pool is unusable: fail what was in flight, start a new pool
                    for fut, key in list(running.items()):
                        report(key, unit_failed(tracker.units[key], "worker pool broke; rerun to retry", cache_root))
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
