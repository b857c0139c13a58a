"""The sweep engine on Ray: jobs as Ray tasks, locally or on a cluster (``pip install 'warpspring[cluster]'``).

With no address, :class:`RayEngine` starts Ray on this machine bound to the loopback address only: every
gRPC server of the session (GCS, raylet, workers, the runtime-env agent) listens on 127.0.0.1, and the
dashboard (with its job-submission API) is not started. Ray resolves a node's address to a remotely
reachable one unless clustering is off, so the engine switches it off for a local session
(``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``, the setting Ray itself uses on desktops) and checks the node's
address after start-up. With an address (``ray://`` or ``host:port``) it joins an existing cluster
unchanged; a Ray cluster has no authentication of its own unless its operator switches Ray's token
authentication on: run it on a private network only (Ray's security guidance).

Each job is a task asking for ``cpus_per_task`` CPUs and ``gpus_per_task`` GPUs (fractional to share a
GPU: a task with a GPU sees it as ``cuda:0``, one without sees none and runs on the CPU). A task whose
worker dies (killed, out of memory) is retried up to ``max_retries`` times; an exception raised by the job
itself is not retried (it is the job's result: the sweep records it as the variant's error). Before the
jobs, :meth:`RayEngine.warm_up` runs one task per node that compiles the kernels the jobs need into that
node's Warp kernel cache, so the tasks load them instead of compiling them again, once per worker process.

Local workers import the same copy of warpspring as the driver (its folder is put on their
``PYTHONPATH``); a cluster's nodes need warpspring installed, at the driver's version.
"""

from __future__ import annotations

import ipaddress
import os
from collections.abc import Callable, Iterator

from ..errors import ConfigError

#: Retries of a task whose worker process died.
MAX_RETRIES = 3
#: Ray's switch for clustering on desktops: off, a node takes the loopback address as its own.
_CLUSTER_SWITCH = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


def import_ray():
    """The ``ray`` module, or a ConfigError saying how to install it."""
    try:
        import ray
    except ImportError:
        raise ConfigError("running on Ray needs the cluster extra: pip install 'warpspring[cluster]' (or run without "
                          "Ray: warpspring sweep --no-ray)") from None
    return ray


def _call(fn: Callable, job, *shared):
    """A task's body: ``fn(job, *shared)`` in the worker (Ray resolves the shared objects' references)."""
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING  # no module-load lines in the workers' logs
    return fn(job, *shared)


def _warm(fn: Callable, jobs: list, *shared) -> str:
    """A node's warm-up: run each job once (compiling its kernels into the node's cache); the node's id."""
    import ray

    for job in jobs:
        _call(fn, job, *shared)
    return ray.get_runtime_context().get_node_id()


class RayEngine:
    """Runs jobs as Ray tasks.

    Args:
        address: a running cluster's address (``ray://host:10001``, ``host:6379`` or ``auto``); ``None``
            starts a local Ray on this machine, bound to 127.0.0.1, without dashboard, stopped by
            :meth:`close`.
        workers: tasks in flight at once (local: also the CPUs Ray may use); default: every CPU.
        cpus_per_task: CPUs each task asks for.
        gpus_per_task: GPUs each task asks for (0: runs on the CPU; 0.25: four tasks share a GPU).
        max_retries: retries of a task whose worker died.

    Raises:
        ConfigError: Ray is not installed, a bad option, or a local node that did not bind to loopback.
    """

    name = "ray"

    def __init__(self, address: str | None = None, *, workers: int | None = None, cpus_per_task: float = 1.0,
                 gpus_per_task: float = 0.0, max_retries: int = MAX_RETRIES):
        if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
            raise ConfigError(f"workers must be an integer >= 1, got {workers!r}")
        if not (cpus_per_task > 0 and gpus_per_task >= 0):
            raise ConfigError(f"a task needs cpus_per_task > 0 and gpus_per_task >= 0, got {cpus_per_task!r}, "
                              f"{gpus_per_task!r}")
        if address is None:
            os.environ[_CLUSTER_SWITCH] = "0"  # read when Ray is imported ...
        ray = import_ray()
        self.ray, self.address, self.workers = ray, address, workers
        self.options = dict(num_cpus=cpus_per_task, num_gpus=gpus_per_task, max_retries=max_retries,
                            retry_exceptions=False)
        self._started = False
        if ray.is_initialized():
            raise ConfigError("Ray is running in this process already: the sweep starts and stops its own session")
        if address is None:
            from ray._private import ray_constants

            ray_constants.ENABLE_RAY_CLUSTER = False  # ... or set here when it was imported before
            root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
            path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH", "")) if p)
            ray.init(address="local", num_cpus=workers or os.cpu_count(), include_dashboard=False,
                     log_to_driver=False, logging_level="WARNING", runtime_env={"env_vars": {"PYTHONPATH": path}})
            self._started = True
            host = ray.util.get_node_ip_address()
            if not _loopback(host):
                self.close()
                raise ConfigError(f"the local Ray node took the address {host}, not the loopback address: refusing to "
                                  "run a session reachable from other machines")
        else:
            try:
                ray.init(address=address, log_to_driver=False, logging_level="WARNING")
            except (ConnectionError, ValueError, RuntimeError) as exc:
                raise ConfigError(f"cannot connect to the Ray cluster at {address}: {' '.join(str(exc).split())}") \
                    from None
            self._started = True

    def describe(self) -> str:
        nodes = [n for n in self.ray.nodes() if n.get("Alive")]
        cpus = int(sum(n.get("Resources", {}).get("CPU", 0) for n in nodes))
        gpus = sum(n.get("Resources", {}).get("GPU", 0) for n in nodes)
        where = "local Ray" if self.address is None else f"Ray at {self.address}"
        return f"{where} ({len(nodes)} node{'s' if len(nodes) != 1 else ''}, {cpus} CPUs{f', {gpus:g} GPUs' if gpus else ''})"

    def run(self, fn: Callable, jobs: list, *, shared: tuple = (), on_error: Callable | None = None
            ) -> Iterator[tuple[int, object]]:
        """Yield (job index, ``fn(job, *shared)``) as tasks finish, at most ``workers`` in flight. A task
        that failed for good (its job raised, or its worker died more than ``max_retries`` times) gives
        ``on_error(job, exception)``, or raises when ``on_error`` is ``None``."""
        ray = self.ray
        task = ray.remote(_call).options(**self.options)
        refs = [ray.put(s) for s in shared]  # sent once, not with every task
        limit = self.workers or len(jobs) or 1
        waiting = list(enumerate(jobs))[::-1]
        running: dict = {}
        while waiting or running:
            while waiting and len(running) < limit:
                i, job = waiting.pop()
                running[task.remote(fn, job, *refs)] = (i, job)
            [ref], _ = ray.wait(list(running), num_returns=1)
            i, job = running.pop(ref)
            try:
                value = ray.get(ref)
            except Exception as exc:  # RayTaskError (the job raised) or WorkerCrashedError after the retries
                if on_error is None:
                    raise
                value = on_error(job, exc)
            yield i, value

    def warm_up(self, fn: Callable, jobs: list, *, shared: tuple = ()) -> None:
        """Run ``jobs`` once on every alive node (one task pinned to each), compiling their kernels into the
        node's Warp kernel cache before the real tasks start."""
        if not jobs:
            return
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        ray = self.ray
        refs = [ray.put(s) for s in shared]
        tasks = []
        for node in ray.nodes():
            if node.get("Alive") and node.get("Resources", {}).get("CPU", 0) >= self.options["num_cpus"]:
                strategy = NodeAffinitySchedulingStrategy(node_id=node["NodeID"], soft=False)
                tasks.append(ray.remote(_warm).options(**self.options, scheduling_strategy=strategy)
                             .remote(fn, jobs, *refs))
        ray.get(tasks)

    def close(self) -> None:
        """Stop the local Ray (or leave the cluster)."""
        if self._started:
            self.ray.shutdown()
            self._started = False

    def __enter__(self) -> RayEngine:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _loopback(host: str) -> bool:
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        return host == "localhost"
    mapped = getattr(address, "ipv4_mapped", None)
    return (mapped or address).is_loopback


def listening_beyond_loopback(pids) -> list[str]:
    """The sockets listening on an address other than the loopback one, among the processes ``pids`` and
    their children: "name (pid) on address:port" each (needs psutil)."""
    import psutil

    found = []
    seen = set()
    for pid in pids:
        try:
            root = psutil.Process(pid)
            processes = [root] + root.children(recursive=True)
        except psutil.NoSuchProcess:
            continue
        for p in processes:
            if p.pid in seen:
                continue
            seen.add(p.pid)
            try:
                connections = p.net_connections(kind="inet")
                name = p.name()
            except (psutil.NoSuchProcess, psutil.AccessDenied):
                continue
            for c in connections:
                if c.status == psutil.CONN_LISTEN and not _loopback(c.laddr.ip):
                    found.append(f"{name} ({p.pid}) on {c.laddr.ip}:{c.laddr.port}")
    return found

