"""Sweeps: many variants of one scene, each run and measured, on one machine or a Ray cluster.

A sweep file is planned into variants (:mod:`warpspring.analysis.sweep_plan`: the file's schema, its axes,
each variant's key), the variants are batched as worlds and measured
(:mod:`warpspring.analysis.sweep_batch`), and the batches run through an engine
(:mod:`warpspring.analysis.engines`: in this process, or on Ray). This module runs a plan and keeps its
results: each variant's result is written, atomically (temporary file, then rename), to
``OUT/results/<hash>.json`` as soon as it arrives, so an interrupted sweep resumes by skipping the variants
whose result exists (:func:`run_sweep` ``resume=True``).
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from .engines import LocalEngine
from .sweep_batch import STATUSES, Batch, BatchOutput, RunSettings, VariantResult, make_batches, run_batch, topology
from .sweep_plan import SweepPlan, Variant, apply_override, one_line


#: Batches of variants a sweep holds at once (a window of the plan's stream; see :func:`run_sweep`).
WINDOW_BATCHES = 64


@dataclass
class SweepResult:
    """A finished sweep: its plan and one row per variant, in plan order.

    Attributes:
        plan: the plan.
        rows: the variants' results.
        ran: variants run by this call (the others' results were found: resumed).
        elapsed: wall time of this call [s].
        engine: where it ran.
        reference: the reference run's result, or ``None``.
    """

    plan: SweepPlan
    rows: list
    ran: int
    elapsed: float
    engine: str
    reference: VariantResult | None = None


def results_dir(out_dir: str) -> str:
    """Where a sweep keeps one result file per variant."""
    return os.path.join(out_dir, "results")


def run_sweep(plan: SweepPlan, out_dir: str, *, engine=None, resume: bool = False, device: str | None = None,
              progress: bool = False, task_hook: Callable | None = None, log: Callable | None = None) -> SweepResult:
    """Run every variant of ``plan`` (the reference first) and write their results to ``out_dir``.

    Args:
        plan: from :func:`~warpspring.analysis.sweep_plan.load_sweep` or
            :func:`~warpspring.analysis.sweep_plan.plan_sweep`.
        out_dir: the output folder: ``results/<hash>.json`` per variant, ``usd/<hash>.usdc`` with ``usd``.
        engine: :class:`~warpspring.analysis.engines.LocalEngine` (default) or a
            :class:`~warpspring.analysis.sweep_ray.RayEngine`.
        resume: skip the variants whose result is in ``out_dir`` already. Without it, a folder holding
            results of a sweep is refused (nothing is overwritten by accident).
        device: Warp device of every task; default: Warp's default where each task runs.
        progress: a progress bar (tqdm) over the variants, on stderr.
        task_hook: see :class:`~warpspring.analysis.sweep_batch.RunSettings`.
        log: called with a line when the reference or a batch ends, or ``None``.

    Raises:
        ConfigError: ``out_dir`` holds results and ``resume`` is off; the reference run stopped.
    """
    from tqdm import tqdm

    engine = engine or LocalEngine()
    log = log or (lambda line: None)
    start = time.perf_counter()
    folder = results_dir(out_dir)
    if not resume and os.path.isdir(folder) and any(name.endswith(".json") for name in os.listdir(folder)):
        raise ConfigError(f"{out_dir} holds results of a sweep already: pass --resume to continue it (variants done "
                          "are skipped), or choose another --out")
    os.makedirs(folder, exist_ok=True)
    usd_dir = os.path.join(out_dir, "usd") if plan.usd else None
    settings = RunSettings(device=device, usd_dir=usd_dir, task_hook=task_hook, metrics_every=plan.metrics_every)

    reference = None
    if plan.reference is not None:
        ref = Variant(index=-1, params={}, scene=plan.reference, key=plan.reference_key)
        reference, reference_q = _load(folder, ref.key, positions=True)
        if reference is None:
            job = Batch((ref,), plan.scene_path)
            engine.warm_up(run_batch, _warm_up_jobs([job]), shared=(RunSettings(device=device),))
            [(_, output)] = list(engine.run(run_batch, [job], shared=(settings,), on_error=_failed_batch))
            reference = output.results[0]
            reference_q = output.final_q.get(ref.key)
            _save(folder, reference, reference_q)
        if reference.status != "ok":
            raise ConfigError(f"the reference run {reference.status}: {reference.message}; choose a reference that "
                              "runs to the end ([sweep] reference)")
        log(f"reference: {reference.frames} frames in {reference.wall_time or 0.0:.2f} s")
        settings = dataclasses.replace(settings, reference_q=reference_q)

    # The variants stream through in windows of WINDOW_BATCHES batches: only a window's scenes are held at once
    # (the plan makes each variant when it is read); the rows kept are the results, one small record each.
    found, ran, warmed = {}, 0, set()
    window = WINDOW_BATCHES * plan.batch
    with tqdm(total=len(plan.variants), unit="variant", disable=not progress,
              dynamic_ncols=True, desc=f"sweep on {engine.describe()}") as bar:
        for chunk in _windows(plan.variants, window):
            todo = []
            for v in chunk:
                row = _load(folder, v.key)[0] if resume and v.key not in found else found.get(v.key)
                if row is not None:
                    row.index = v.index
                    found[v.key] = row
                    bar.update(1)
                else:
                    todo.append(v)
            batches = make_batches(todo, plan.scene_path, plan.batch)
            warm = [job for job in _warm_up_jobs(batches) if topology(job.variants[0].scene) not in warmed]
            if warm:
                engine.warm_up(run_batch, warm, shared=(RunSettings(device=device),))
                warmed.update(topology(job.variants[0].scene) for job in warm)
            ran += len(todo)
            for i, output in engine.run(run_batch, batches, shared=(settings,), on_error=_failed_batch):
                for row in output.results:
                    _save(folder, row, None)
                    found[row.key] = row
                bar.update(len(output.results))
                statuses = [r.status for r in output.results]
                log(f"batch of {len(statuses)}: " + ", ".join(f"{statuses.count(s)} {s}" for s in STATUSES
                                                              if s in statuses))
    rows = [found[v.key] for v in plan.variants]
    for v, row in zip(plan.variants, rows):
        row.index = v.index
    return SweepResult(plan=plan, rows=rows, ran=ran, elapsed=time.perf_counter() - start,
                       engine=engine.describe(), reference=reference)


def _windows(variants, size: int):
    """``variants`` in consecutive lists of at most ``size``, read lazily."""
    chunk = []
    for v in variants:
        chunk.append(v)
        if len(chunk) == size:
            yield chunk
            chunk = []
    if chunk:
        yield chunk


def _failed_batch(batch: Batch, exc: BaseException) -> BatchOutput:
    """The rows of a batch whose task failed for good (its worker died at every retry): each its error."""
    message = f"the task failed: {type(exc).__name__}: {one_line(exc)}"[:2000]
    return BatchOutput([VariantResult(index=v.index, key=v.key, status="error", message=message)
                        for v in batch.variants])


def _warm_up_jobs(batches: list) -> list:
    """One batch per topology of its first variant for one frame (the frame count compiles nothing): what a
    node compiles and loads before the sweep's tasks reach it."""
    seen, jobs = set(), []
    for b in batches:
        v = b.variants[0]
        shape = topology(v.scene)
        if shape not in seen:
            seen.add(shape)
            scene = apply_override(v.scene, "simulation.frames", 1, where="warm-up")
            jobs.append(Batch((dataclasses.replace(v, scene=scene),), b.scene_path))
    return jobs


def _save(folder: str, row: VariantResult, final_q) -> None:
    """Write a variant's result (and the reference's positions) atomically: a temporary file, then rename."""
    path = os.path.join(folder, f"{row.key}.json")
    atomic_write(path, json.dumps(dataclasses.asdict(row), indent=1).encode())
    if final_q is not None:
        buffer = io.BytesIO()
        np.save(buffer, final_q)
        atomic_write(os.path.join(folder, f"{row.key}.npy"), buffer.getvalue())


def atomic_write(path: str, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically: a temporary file, flushed to disk, then renamed over ``path``."""
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _load(folder: str, key: str, *, positions: bool = False):
    """A stored result and (``positions``) final positions, or (None, None)."""
    path = os.path.join(folder, f"{key}.json")
    if not os.path.isfile(path):
        return None, None
    try:
        with open(path) as f:
            row = VariantResult(**json.load(f))
    except (OSError, ValueError, TypeError):  # unreadable: run it again
        return None, None
    q = None
    if positions:
        npy = os.path.join(folder, f"{key}.npy")
        if not os.path.isfile(npy):
            return None, None
        q = np.load(npy)
    return row, q
