"""Dask distributed executor: the same work items, submitted to a Dask cluster.

- ``--executor dask`` starts a LocalCluster (``--workers N``, one thread each, spawned processes), or
  ``--scheduler tcp://HOST:PORT`` joins an existing cluster. The cache folder must then be on a filesystem
  every worker sees: it is the source of truth, results never travel through Dask.
- Each work item is one task keyed by its cache key, with its upstream tasks as dependencies; the payload
  is the item's plain spec (params and artifact keys), never a live object.
- A worker plugin runs the node packages' start-up hooks once per worker process (an OpenCL context...).
- A killed worker (OOM, node lost) makes Dask reschedule its tasks on another worker (up to the cluster's
  ``allowed-failures``); a node's own error is a result, not an exception, so it is never retried.
"""
from __future__ import annotations

from .errors import VolcapError
from .worker import execute, start_worker


def _run_item(spec: dict, cache_root: str, *upstream: dict) -> dict:
    for up in upstream:
        if up.get("status") != "done":
            return {"status": "skipped", "error": up.get("skip_reason") or f"upstream '{up.get('node')}' failed",
                    "seconds": 0.0, "node": spec["node"], "skip_reason": up.get("skip_reason") or f"upstream '{up.get('node')}' failed"}
    res = execute(spec, cache_root)
    res["node"] = spec["node"]
    return res


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

    def run(self, items, specs, cache_root, on_result):
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
            from .executors import worker_threads

            cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                                   dashboard_address=None, silence_logs=40, env=worker_threads(self.workers))
            client = Client(cluster)
        try:
            from distributed.diagnostics.plugin import WorkerPlugin

            plugin = type("VolcapStart", (_StartPlugin, WorkerPlugin), {})()
            client.register_plugin(plugin, name=_StartPlugin.name)
            futures = {}
            for it in items:  # dependency order: upstream futures exist before their consumers
                ups = [futures[d] for d in it.deps if d in futures]
                futures[it.key] = client.submit(_run_item, specs[it.key], cache_root, *ups,
                                                key=f"volcap-{it.node}-{it.key}", pure=False, retries=0)
            by_future = {f: k for k, f in futures.items()}
            deps = {it.key: [d for d in it.deps if d in futures] for it in items}
            names = {it.key: it.node for it in items}
            status: dict[str, str] = {}
            for fut in as_completed(list(futures.values())):
                key = by_future[fut]
                try:
                    res = fut.result()
                except Exception as exc:  # KilledWorker after repeated worker deaths, lost scheduler...
                    bad = [d for d in deps[key] if status.get(d, "failed") != "done"]
                    if bad:  # Dask passes an upstream exception on to its dependents: they never ran
                        res = {"status": "skipped", "seconds": 0.0, "error": f"upstream '{names[bad[0]]}' failed"}
                    else:
                        res = {"status": "failed", "seconds": 0.0, "error": f"{type(exc).__name__}: {exc}"}
                status[key] = res["status"]
                res.pop("node", None)
                res.pop("skip_reason", None)
                on_result(key, res)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
