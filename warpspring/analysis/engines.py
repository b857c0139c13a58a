"""Engines: how a study's jobs are run, and :func:`map_jobs`, which runs a list of them in order.

An engine runs jobs (``fn(job, *shared)``, each a tuple of plain data) and yields their results as they
arrive: :class:`LocalEngine` runs them one after the other in this process;
:class:`warpspring.analysis.sweep_ray.RayEngine` runs them as Ray tasks (retried when a worker dies, the
kernel cache warmed once per node). Both give the same results, timings aside. Sweeps
(:func:`warpspring.analysis.sweep.run_sweep`), the trade study (``run_study(engine=...)``) and the
stability map (``run_map(engine=...)``) run their plans through them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator


class LocalEngine:
    """Runs jobs one after the other in this process (no Ray)."""

    name = "local"

    def describe(self) -> str:
        return "this process"

    def run(self, fn: Callable, jobs: list, *, shared: tuple = (), on_error: Callable | None = None
            ) -> Iterator[tuple[int, object]]:
        """Yield (job index, ``fn(job, *shared)``) in job order; a job that raises gives
        ``on_error(job, exception)``, or raises when ``on_error`` is ``None``."""
        for i, job in enumerate(jobs):
            try:
                value = fn(job, *shared)
            except Exception as exc:
                if on_error is None:
                    raise
                value = on_error(job, exc)
            yield i, value

    def warm_up(self, fn: Callable, jobs: list, *, shared: tuple = ()) -> None:
        """Nothing: the first job compiles the kernels in this process."""

    def close(self) -> None:
        pass


def map_jobs(engine, fn: Callable, jobs: list, *, shared: tuple = (), done: Callable | None = None) -> list:
    """``[fn(job, *shared) for job in jobs]`` through ``engine`` (:class:`LocalEngine` when ``None``), in job
    order whatever order they finish in; ``done(result)`` is called as each arrives. A job that raises
    raises here."""
    engine = engine or LocalEngine()
    results = [None] * len(jobs)
    for i, value in engine.run(fn, jobs, shared=shared):
        results[i] = value
        if done is not None:
            done(value)
    return results
