"""Dask distributed executor: the same work units, submitted to a Dask cluster.

- ``--executor dask`` starts a LocalCluster (``--workers N``, one thread each, spawned processes), or
  ``--scheduler tcp://HOST:PORT`` joins an existing cluster. The cache folder must then be on a filesystem
  every worker sees: it is the source of truth, results never travel through Dask.
- Each work unit (a frame's items, or one item: nodegraph/plan.py) is one task, with the units it reads from
  as dependencies; the payload is the unit's plain spec (params and artifact keys), never a live object, and
  only the per-item results travel back (values stay in the cache).
- A worker plugin runs the node packages' start-up hooks once per worker process (an OpenCL context...).
- A killed worker (OOM, node lost) makes Dask reschedule its tasks on another worker (up to the cluster's
  ``allowed-failures``); a node's own error is a result, not an exception, so it is never retried.
"""
from __future__ import annotations

import os

import dataclasses

from .errors import VolcapError
from .executors import unit_failed
from .records import Result, UnitSpec
from .worker import execute_unit, start_worker


def _run_unit(spec: UnitSpec, cache_root: str, *upstream: dict[str, Result]) -> dict[str, Result]:
    """Run a unit after the units it reads from; items of theirs that failed make their readers skip."""
    failed = dict(spec.failed)
    for results in upstream:
        for key, res in results.items():
            if res.status != "done":
                failed[key] = res.node or "?"
    return execute_unit(dataclasses.replace(spec, failed=failed), cache_root)


class _StartPlugin:
    """Worker plugin: runs the node packages' start-up hooks once when a worker starts (an OpenCL context...)."""

    name = "volcap-start"

    def setup(self, worker):
        start_worker()

    def teardown(self, worker):
        pass

    def transition(self, key, start, finish, **kwargs):
        pass


class DaskExecutor:
    name = "dask"

    def __init__(self, workers: int | None = None, scheduler: str | None = None):
        self.workers = workers or 2
        self.scheduler = scheduler

    def run(self, units, cache_root, on_result):
        try:
            from distributed import Client, LocalCluster, as_completed
        except ImportError:
            raise VolcapError("the dask executor needs `pip install \"dask[distributed]\"` (or volcap[dask])") from None
        cluster = None
        if self.scheduler:
            try:
                client = Client(self.scheduler, timeout="20s")
            except (OSError, ValueError, TypeError) as exc:  # unreachable, or an address Dask cannot parse
                raise VolcapError(f"cannot reach the Dask scheduler {self.scheduler}: {exc}") from None
        else:
            import dask

            from .executors import worker_threads

            # The nanny's pre-spawn environment is what a worker process starts with, and two of its defaults
            # cost us: MALLOC_TRIM_THRESHOLD_ (setting it switches off glibc's dynamic mmap threshold, so every
            # large NumPy temporary is a fresh mmap paid in page faults: the demo graph on one worker took 1.5x
            # a local process, skinning 2.3x) and OMP/MKL/OpenBLAS = 1 thread (read when NumPy loads, whatever
            # env= says later). Ours: glibc's default, thread pools at the worker's share of the cores. Nannies
            # read this once, when made: a restarted worker keeps it.
            # (The nanny writes these into this process's os.environ before it spawns: put ours back after.)
            threads = worker_threads(self.workers)
            pre = {**dask.config.get("distributed.nanny.pre-spawn-environ", {}), "MALLOC_TRIM_THRESHOLD_": None,
                   **threads}
            before = dict(os.environ)
            try:
                with dask.config.set({"distributed.nanny.pre-spawn-environ": pre}):
                    cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                                           dashboard_address=None, silence_logs=40, env=threads)
            finally:
                os.environ.clear()
                os.environ.update(before)
            client = Client(cluster)
        try:
            from distributed.diagnostics.plugin import WorkerPlugin

            plugin = type("VolcapStart", (_StartPlugin, WorkerPlugin), {})()
            client.register_plugin(plugin, name=_StartPlugin.name)
            futures = {}
            for u in units:  # dependency order: upstream futures exist before their readers
                ups = [futures[d] for d in u.deps if d in futures]
                futures[u.key] = client.submit(_run_unit, u.spec, cache_root, *ups, key=f"volcap-{u.label}-{u.key[:16]}",
                                               pure=False, retries=0)
            by_future = {f: k for k, f in futures.items()}
            by_key = {u.key: u for u in units}
            done_items: dict[str, str] = {}
            for fut in as_completed(list(futures.values())):
                key = by_future[fut]
                unit = by_key[key]
                try:
                    results = fut.result()
                except Exception as exc:  # KilledWorker after repeated worker deaths, lost scheduler...
                    ups = [s for d in unit.deps if d in by_key for s in by_key[d].spec.items]
                    bad = [s for s in ups if done_items.get(s.key, "failed") != "done"]
                    if bad:  # Dask passes an upstream exception on to its dependents: they never ran
                        results = {s.key: Result("skipped", error=f"upstream '{bad[0].node}' failed", node=s.node)
                                   for s in unit.spec.items}
                    else:
                        results = unit_failed(unit, f"{type(exc).__name__}: {exc}", cache_root)
                for item, res in results.items():
                    done_items[item] = res.status
                    on_result(item, res)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
