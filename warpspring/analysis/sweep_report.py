"""A sweep's files: its table (CSV, and Parquet when pyarrow is installed), one row per variant with its
parameters and metrics, and a summary plot (:mod:`warpspring.analysis.sweep` runs it)."""

from __future__ import annotations

import csv
import dataclasses
import math
import os

import numpy as np

from ..plotting import pyplot
from .sweep import SweepResult, atomic_write
from .sweep_batch import VariantResult

#: The metric columns, after ``variant``, ``hash`` and the parameters.
METRICS = [f.name for f in dataclasses.fields(VariantResult) if f.name not in ("index", "key")]


def table(result: SweepResult) -> tuple[list[str], list[list]]:
    """The table's header and rows: ``variant``, ``hash``, one column per axis key, then :data:`METRICS`."""
    keys = result.plan.keys
    header = ["variant", "hash", *keys, *METRICS]
    rows = []
    for v, row in zip(result.plan.variants, result.rows):
        values = [_cell(v.params[k]) for k in keys]
        rows.append([v.index, v.key, *values, *(getattr(row, m) for m in METRICS)])
    return header, rows


def _cell(value):
    """A parameter as one cell: numbers and strings as they are, a list (a vector) as its TOML text."""
    if isinstance(value, list):
        return "[" + ", ".join(str(x) for x in value) + "]"
    return value


def write_csv(result: SweepResult, path: str) -> str:
    """Write the table as CSV (empty cells for missing values), atomically."""
    import io

    header, rows = table(result)
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(header)
    for row in rows:
        writer.writerow(["" if x is None else repr(x) if isinstance(x, float) else x for x in row])
    atomic_write(path, buffer.getvalue().encode())
    return path


def write_parquet(result: SweepResult, path: str) -> str | None:
    """Write the table as Parquet when pyarrow is installed (else nothing: ``None``), atomically."""
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        return None
    header, rows = table(result)
    columns = {name: [row[i] for row in rows] for i, name in enumerate(header)}
    tmp = f"{path}.tmp{os.getpid()}"
    pq.write_table(pa.table(columns), tmp)
    os.replace(tmp, path)
    return path


def summary(result: SweepResult) -> list[str]:
    """A few lines: counts by status, the stopped and failed variants' messages (the first few), the
    spread of each metric, and the throughput."""
    rows = result.rows
    counts = {s: sum(r.status == s for r in rows) for s in ("ok", "stopped", "error")}
    lines = [f"{len(rows)} variants ({counts['ok']} ok, {counts['stopped']} stopped by the guard, {counts['error']} "
             f"errors); {result.ran} run now on {result.engine} in {result.elapsed:.1f} s"
             f"{f' ({60.0 * result.ran / result.elapsed:.0f} variants/min)' if result.ran and result.elapsed else ''}"]
    for r in [r for r in rows if r.status != "ok"][:5]:
        lines.append(f"  variant {r.index} {r.status}: {r.message}")
    for name, unit in (("max_strain", ""), ("error_max", " m"), ("min_contact_distance", " m")):
        values = [getattr(r, name) for r in rows if getattr(r, name) is not None]
        if values:
            lines.append(f"  {name}: {min(values):.4g} … {max(values):.4g}{unit}")
    return lines


def plot_summary(result: SweepResult, path: str) -> str:
    """The metrics against the first numeric axis (coloured by the second, if any): the largest strain, the
    error against the reference (or the final energy without one) and frames per wall second; stopped and
    failed variants as red crosses on the axis. Needs matplotlib."""
    plt = pyplot("the sweep's plot")
    plan, rows = result.plan, result.rows
    numeric = [k for k in plan.keys if all(_number(v.params[k]) for v in plan.variants)]
    x_key = numeric[0] if numeric else None
    colour_key = next((k for k in plan.keys if k != x_key), None)
    xs = np.array([v.params[x_key] if x_key else v.index for v in plan.variants], dtype=np.float64)
    panels = [("max_strain", "largest strain [-]"),
              ("error_max" if plan.reference is not None else "energy_end",
               "error vs reference [m]" if plan.reference is not None else "final energy [J]"),
              ("frames_per_second", "frames per wall second")]
    fig, axes = plt.subplots(1, len(panels), figsize=(5.0 * len(panels), 4.0), constrained_layout=True)
    groups = {}
    for v, row in zip(plan.variants, rows):
        groups.setdefault(_cell(v.params[colour_key]) if colour_key else "", []).append((v, row))
    log_x = x_key is not None and xs.min() > 0 and xs.max() / xs.min() >= 100
    for ax, (metric, label) in zip(axes, panels):
        for (name, members), colour in zip(groups.items(), _colours(len(groups))):
            good = [(v.params[x_key] if x_key else v.index, getattr(r, metric)) for v, r in members
                    if r.status == "ok" and getattr(r, metric) is not None]
            if good:
                gx, gy = zip(*sorted(good))
                ax.plot(gx, gy, "o-", color=colour, label=f"{colour_key} = {name}" if colour_key else None)
        bad = [v.params[x_key] if x_key else v.index for v, r in zip(plan.variants, rows) if r.status != "ok"]
        if bad:
            ax.plot(bad, np.zeros(len(bad)), "x", color="tab:red", markersize=9, transform=ax.get_xaxis_transform(),
                    clip_on=False, label="stopped / error")
        values = [getattr(r, metric) for r in rows if getattr(r, metric) is not None]
        if values and min(values) > 0 and max(values) / min(values) >= 100:
            ax.set_yscale("log")
        if log_x:
            ax.set_xscale("log")
        ax.set_xlabel(x_key or "variant")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    if axes[0].get_legend_handles_labels()[0]:
        axes[0].legend(fontsize="small")
    fig.suptitle(f"{os.path.basename(plan.path)}: {len(rows)} variants on {result.engine}")
    tmp = f"{path}.tmp{os.getpid()}.png"
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)
    return path


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _colours(n: int) -> list:
    import matplotlib

    cmap = matplotlib.colormaps["viridis"]
    return [cmap(0.5)] if n == 1 else [cmap(i / (n - 1) * 0.9) for i in range(n)]


def write_report(result: SweepResult, out_dir: str, *, plot: bool = True) -> list[str]:
    """Write ``sweep.csv`` (and ``sweep.parquet`` with pyarrow) and ``sweep.png`` into ``out_dir``; the paths."""
    paths = [write_csv(result, os.path.join(out_dir, "sweep.csv"))]
    parquet = write_parquet(result, os.path.join(out_dir, "sweep.parquet"))
    if parquet:
        paths.append(parquet)
    if plot:
        paths.append(plot_summary(result, os.path.join(out_dir, "sweep.png")))
    return paths
