"""The speed/accuracy study's files: its measurements as CSV (read back by ``warpspring choose``), a
Markdown report, and the Pareto, convergence and seed plots (:mod:`warpspring.analysis.trade` measures)."""

from __future__ import annotations

import csv
import dataclasses
import os

import numpy as np

from .. import checks
from ..errors import ConfigError
from ..core.integrators import INTEGRATORS
from ..plotting import pyplot
from . import trade_contact_report
from .trade import REFERENCE_REFINEMENT, STATUSES, Measurement, Study, _ms
from .trade_choice import ASYMPTOTIC_CEILING, ASYMPTOTIC_OMEGA_H, NOISE_MARGIN, convergence_orders, pareto_front
from .trade_problems import BLOWUP_FACTOR, ENERGY_BLOWUP, ClothProblem, SpringProblem


# -- files --------------------------------------------------------------------------------------------------

_FIELDS = [f.name for f in dataclasses.fields(Measurement)]
_INT_FIELDS = {"order", "crossings"}
_TEXT_FIELDS = {"problem", "integrator", "precision", "device", "status"}
#: Columns a study written before the contact scenes (and the device name in each row) lacks: read as not measured.
_CONTACT_FIELDS = ("option", "horizon", "error_horizon", "hausdorff", "quantity", "quantity_error", "crossings",
                   "device_name")


def write_csv(rows: list[Measurement], path: str) -> str:
    """Write ``rows`` to ``path`` (one column per :class:`Measurement` field, SI units, empty = not measured)."""
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(_FIELDS)
        for r in rows:
            values = dataclasses.astuple(r)
            writer.writerow(["" if v is None else repr(v) if isinstance(v, float) else v for v in values])
    return path


def read_csv(path: str) -> list[Measurement]:
    """The rows of a ``trade.csv`` written by :func:`write_csv`.

    Raises:
        ConfigError: a missing file, or one that is not a study.
    """
    if not os.path.isfile(path):
        raise ConfigError(f"study file not found: {path} (run 'warpspring trade' first, or pass --study)")
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        missing = [name for name in _FIELDS if name not in (reader.fieldnames or []) and name not in _CONTACT_FIELDS]
        if missing:
            raise ConfigError(f"{path} is not a warpspring trade study: it lacks the column {missing[0]!r}")
        rows = []
        for line, raw in enumerate(reader, start=2):
            try:
                rows.append(Measurement(**{name: _parse(name, raw.get(name) or "") for name in _FIELDS}))
            except ValueError:
                raise ConfigError(f"{path}:{line}: malformed row: {','.join(raw.get(n) or '' for n in _FIELDS)}") from None
    return rows


def _parse(name: str, text: str):
    if name in ("option", "device_name"):
        return text or None
    if name in _TEXT_FIELDS:
        if name == "status" and text not in STATUSES:
            raise ValueError(text)
        return text
    if text == "":
        return None
    return int(text) if name in _INT_FIELDS else float(text)


def _smooth_method(plan) -> str:
    """How the closed forms and the hanging cloth are measured: the report's paragraph."""
    return (
        f"Closed forms and the hanging cloth. Cost: wall time per simulated second, device synchronised, "
        f"compilation excluded: the median of {plan.repeats} batches of graph replays of at least "
        f"{plan.min_batch * 1e3:g} ms each (integrators that cannot be captured: their whole run). Runs projected "
        f"to take longer than {plan.run_limit:g} s are skipped. Unstable runs are reported as such: non-finite, or "
        f"blown up (an error over {BLOWUP_FACTOR:g}× the problem's length scale, or an energy drift over "
        f"{ENERGY_BLOWUP:g}: these damped systems cannot gain energy). Adaptive integrators are sampled at their "
        "outputs (their dt). Convergence orders are least-squares slopes of log error against log step over the "
        f"float64 runs in the asymptotic range (fixed steps: ω_max·h ≤ {ASYMPTOTIC_OMEGA_H:g}; error below "
        f"{ASYMPTOTIC_CEILING:g}× the length scale and above {NOISE_MARGIN:g}× the rounding and reference "
        "noise); adaptive integrators against their mean accepted step."
    )


def to_markdown(study: Study) -> str:
    """The study as Markdown: provenance, method, and per problem its reference, fitted orders and a table."""
    plan = study.plan
    lines = [
        f"# Integrators: speed against accuracy ({plan.name} study)",
        "",
        *([f"Command: `{study.command}`", ""] if study.command else []),
        f"Device: {study.device} ({study.device_name}); Warp {study.warp_version}; {study.date}; the study took "
        f"{study.elapsed:.0f} s.",
    ]
    if trade_contact_report.contact_problems(study):
        lines += ["", trade_contact_report.METHOD]
    if _smooth_problems(study):
        lines += ["", _smooth_method(plan)]
    for problem in plan.problems:
        if getattr(problem, "contact", False):
            lines += trade_contact_report.section(study, problem)
            continue
        rows = [r for r in study.rows if r.problem == problem.name]
        lines += ["", f"## {problem.name}", "", problem.describe() + "."]
        if isinstance(problem, SpringProblem):
            lines += [
                "",
                "Reference: the closed form (warpspring.analysis.analytic.DampedOscillator). Errors are |x − x_exact| over "
                "every step (max, RMS) and at the end; energy drift is (E − E_exact) at the end over the "
                "oscillation energy E(0) − E(rest).",
            ]
        else:
            ref = study.references[problem.name]
            lines += [
                "",
                f"Reference: {ref.integrator}, float64, dt = {_ms(ref.dt)} ({REFERENCE_REFINEMENT}× finer than the "
                f"finest tested step); it differs from the same run at twice its step by {ref.self_difference:.2g} m "
                f"(max over particles), took {ref.wall:.1f} s for both runs, and ends with a max spring strain of "
                f"{ref.max_strain:.3f}. The cloth's fastest mode at rest: ω_max = {ref.fastest_frequency:.4g} rad/s "
                "(power iteration on M⁻¹K). Errors are |x − x_ref| over the particles at the end (max, RMS); energy "
                f"drift is (E − E_ref) at the end over the gravitational energy the reference released "
                f"({ref.released:.4g} J).",
            ]
        lines += ["", "| integrator | nominal order | fitted order | points | fitted steps |", "|---|---|---|---|---|"]
        for name, (order, fitted) in convergence_orders(study, problem.name).items():
            nominal = next(r.order for r in rows if r.integrator == name)
            steps = [r.mean_step for r in fitted]
            span = f"{_ms(min(steps))} – {_ms(max(steps))}" if fitted else "—"
            fit = "—" if order is None else f"{order:.2f}"
            lines.append(f"| {name} | {nominal} | {fit} | {len(fitted)} | {span} |")
        cloth = isinstance(problem, ClothProblem)
        head = "| integrator | precision | dt [ms] | tolerance | steps/s | wall [ms/s] | max error [m] |"
        head += " RMS error [m] |"
        head += " energy drift | max strain | status |" if cloth else " end error [m] | energy drift | status |"
        lines += ["", head, "|" + "---|" * 11]
        for r in rows:
            cells = [
                r.integrator,
                r.precision,
                f"{r.dt * 1e3:.4g}",
                "" if r.tolerance is None else f"{r.tolerance:g}",
                _num(r.steps_per_second, ".4g"),
                _num(None if r.wall_per_second is None else r.wall_per_second * 1e3, ".3g"),
                _num(r.error_max, ".2e"),
                _num(r.error_rms, ".2e"),
            ]
            cells += [_num(r.energy_drift, "+.2e"), _num(r.max_strain, ".3f")] if cloth else [
                _num(r.error_end, ".2e"),
                _num(r.energy_drift, "+.2e"),
            ]
            lines.append("| " + " | ".join(cells + [r.status]) + " |")
    return "\n".join(lines) + "\n"


def write_report(study: Study, out_dir: str) -> list[str]:
    """Write ``trade.csv``, ``trade.md``, ``pareto.png`` and ``convergence.png`` (when the plan has closed forms or
    the hanging cloth), ``pareto_contact.png`` (when it has contact scenes) and ``seed.png`` (when it has a seed
    plot) to ``out_dir`` (created if missing); returns their paths."""
    os.makedirs(checks.output_dir(out_dir), exist_ok=True)
    paths = [write_csv(study.rows, os.path.join(out_dir, "trade.csv"))]
    with open(os.path.join(out_dir, "trade.md"), "w") as f:
        f.write(to_markdown(study))
    paths.append(f.name)
    if _smooth_problems(study):
        paths.append(plot_pareto(study, os.path.join(out_dir, "pareto.png")))
        paths.append(plot_convergence(study, os.path.join(out_dir, "convergence.png")))
    if trade_contact_report.contact_problems(study):
        paths.append(trade_contact_report.plot_pareto(study, os.path.join(out_dir, "pareto_contact.png")))
    if study.trajectories:
        paths.append(plot_seed(study, os.path.join(out_dir, "seed.png")))
    return paths


# -- plots --------------------------------------------------------------------------------------------------


def _smooth_problems(study: Study) -> list:
    """The study's closed forms and hanging cloth (the contact scenes have their own plot)."""
    return [p for p in study.plan.problems if not getattr(p, "contact", False)]

_MARKERS = "osD^vP*Xph"


def _style(name: str) -> dict:
    """Colour and marker of an integrator, fixed by its place in the registry (the same in every plot)."""
    names = list(INTEGRATORS) + sorted(set([name]) - set(INTEGRATORS))
    k = names.index(name)
    return {"color": f"C{k % 10}", "marker": _MARKERS[k % len(_MARKERS)]}


def _log_axes(ax) -> None:
    """Log-log axes labelled at the decades only (minor labels collide over short ranges)."""
    from matplotlib.ticker import NullFormatter

    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.yaxis.set_minor_formatter(NullFormatter())


def _legend_handles(names) -> list:
    """Legend entries: one per integrator in ``names``, then how precision is drawn."""
    from matplotlib.lines import Line2D

    return [Line2D([], [], ls="none", label=name, **_style(name)) for name in names] + [
        Line2D([], [], color="0.3", marker="o", ls="none", label="float64 (filled)"),
        Line2D([], [], color="0.3", marker="o", mfc="none", ls="none", label="float32 (hollow)"),
    ]


def plot_pareto(study: Study, path: str) -> str:
    """Max error against wall time per simulated second (log-log), one panel per problem, one marker series
    per integrator, float64 filled and float32 hollow, the Pareto front as a grey staircase."""
    plt = pyplot("the trade plots")
    problems = _smooth_problems(study)
    fig, axes = plt.subplots(1, len(problems), figsize=(5.5 * len(problems), 4.8), squeeze=False)
    for ax, problem in zip(axes[0], problems):
        rows = [r for r in study.rows if r.problem == problem.name]
        front = pareto_front(rows)
        if front:
            ax.step([r.wall_per_second for r in front], [r.error_max for r in front], where="post", color="0.6",
                    lw=1.5, zorder=1, label="Pareto front")
        for name in dict.fromkeys(r.integrator for r in rows):
            style = _style(name)
            for precision in study.plan.precisions:
                pts = [r for r in rows if r.integrator == name and r.precision == precision and r.status == "ok"
                       and r.wall_per_second is not None]
                if not pts:
                    continue
                ax.plot([r.wall_per_second for r in pts], [r.error_max for r in pts], ls="none", ms=6,
                        marker=style["marker"], color=style["color"], zorder=2,
                        mfc=style["color"] if precision == "float64" else "none")
        _log_axes(ax)
        ax.set_title(problem.name)
        ax.set_xlabel("wall time per simulated second [s/s]")
        ax.set_ylabel("max position error [m]")
        ax.grid(True, which="both", alpha=0.25)
    from matplotlib.lines import Line2D

    labels = _legend_handles(dict.fromkeys(r.integrator for r in study.rows))
    labels.append(Line2D([], [], color="0.6", lw=1.5, label="Pareto front"))
    fig.legend(handles=labels, loc="lower center", ncol=min(len(labels), 6), frameon=False)
    fig.suptitle(f"Error against cost ({study.device}: {study.device_name}, Warp {study.warp_version})")
    fig.tight_layout(rect=(0, 0.1, 1, 0.95))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_convergence(study: Study, path: str) -> str:
    """Max error against step (log-log), one panel per problem; float64 filled and joined, float32 hollow;
    the fitted order of each integrator in the legend and its fit as a dashed line."""
    plt = pyplot("the trade plots")
    problems = _smooth_problems(study)
    fig, axes = plt.subplots(1, len(problems), figsize=(5.5 * len(problems), 5.2), squeeze=False)
    for ax, problem in zip(axes[0], problems):
        rows = [r for r in study.rows if r.problem == problem.name]
        orders = convergence_orders(study, problem.name)
        for name, (order, fitted) in orders.items():
            style = _style(name)
            nominal = next(r.order for r in rows if r.integrator == name)
            label = f"{name}: p = {'n/a' if order is None else f'{order:.2f}'} (nominal {nominal})"
            for precision in study.plan.precisions:
                pts = [r for r in rows if r.integrator == name and r.precision == precision and r.status == "ok"]
                pts.sort(key=lambda r: r.mean_step)
                if not pts:
                    continue
                double = precision == "float64"
                ax.plot([r.mean_step for r in pts], [r.error_max for r in pts], marker=style["marker"],
                        color=style["color"], mfc=style["color"] if double else "none", ls="-" if double else "none",
                        lw=1, ms=5, label=label if double else None)
            if order is not None:
                steps = np.array([r.mean_step for r in fitted])
                errors = np.array([r.error_max for r in fitted])
                intercept = np.mean(np.log(errors) - order * np.log(steps))
                span = np.array([steps.min(), steps.max()])
                ax.plot(span, np.exp(intercept) * span**order, ls="--", color=style["color"], lw=2, alpha=0.5)
        _log_axes(ax)
        ax.set_title(problem.name)
        ax.set_xlabel("step [s] (adaptive: mean accepted step)")
        ax.set_ylabel("max position error [m]")
        ax.grid(True, which="both", alpha=0.25)
        ax.legend(handles=ax.get_legend_handles_labels()[0] + _legend_handles(()), fontsize=7, loc="lower right")
    fig.suptitle("Convergence: fitted order p = least-squares slope over the float64 asymptotic range (dashed)")
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_seed(study: Study, path: str) -> str:
    """x(t) and v(t) of the seed spring under each integrator (float64, one moderate step) over the exact solution."""
    plt = pyplot("the trade plots")
    problem = next(p for p in study.plan.problems if isinstance(p, SpringProblem) and p.plot_steps)
    osc = problem.oscillator
    t = np.linspace(0.0, problem.duration, 2001)
    x, v = osc.state(t)
    fig, (ax_x, ax_v) = plt.subplots(2, 1, figsize=(10, 7.5), sharex=True)
    ax_x.plot(t, x, color="k", lw=1.2, ls="--", zorder=5, label="exact")
    ax_v.plot(t, v, color="k", lw=1.2, ls="--", zorder=5)
    for label, (ts, xs, vs) in study.trajectories.items():
        style = _style(label.split(",")[0])
        ax_x.plot(ts, xs, marker=style["marker"], color=style["color"], ms=3, lw=1, label=label)
        ax_v.plot(ts, vs, marker=style["marker"], color=style["color"], ms=3, lw=1)
    lo, hi = np.min(x), np.max(x)
    pad = 0.6 * (hi - lo)
    ax_x.set_ylim(lo - pad, hi + pad)  # an unstable method may leave the frame: the exact motion sets the scale
    vlo, vhi = np.min(v), np.max(v)
    ax_v.set_ylim(vlo - 0.6 * (vhi - vlo), vhi + 0.6 * (vhi - vlo))
    ax_x.set_ylabel("x [m]")
    ax_v.set_ylabel("v [m/s]")
    ax_v.set_xlabel("t [s]")
    for ax in (ax_x, ax_v):
        ax.grid(True, alpha=0.25)
    ax_x.legend(fontsize=8, ncol=2)
    ax_x.set_title(
        f"{problem.name}: {osc.mass:g} kg, k = {osc.stiffness:g} N/m, c = {osc.damping:g} N·s/m, "
        f"F = {osc.force:g} N; dt = {_ms(problem.duration / problem.plot_steps)} (ω₀·dt = "
        f"{osc.natural_frequency * problem.duration / problem.plot_steps:.3g}), float64"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _num(value, spec: str) -> str:
    return "—" if value is None else format(value, spec)
