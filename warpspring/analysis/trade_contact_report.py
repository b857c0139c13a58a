"""The contact scenes' part of the speed/accuracy report (:mod:`warpspring.analysis.trade_contact` measures):
per problem its reference and the references' convergence, the table of runs, and the Pareto plot (cost
against error, one colour per integrator, one marker per contact option)."""

from __future__ import annotations

from ..core.integrators import INTEGRATORS
from ..plotting import pyplot
from .trade import Study
from .trade_choice import pareto_front
from .trade_contact import FPS, REFERENCE_INTEGRATOR, ContactProblem

_MARKERS = "osD^vP*Xph"
#: How the contact scenes are measured: the report's paragraph (docs/trade.md says why).
METHOD = (
    "Contact scenes (warpspring.analysis.trade_contact; docs/trade.md). Cost: wall time per simulated second of a "
    "Simulator run (its frame graphs, default guards on), the first frame (compilation, capture) excluded, the "
    "device synchronised at both ends; runs projected past the plan's limit are skipped with the finer ones of "
    "that integrator. Error [m]: the larger of the trajectory error over the horizon (the largest distance of a "
    "particle from its place in the reference, over the frames up to the horizon) and the symmetric Hausdorff "
    "distance of the particles at the end to the reference's. Δ quantity: |quantity of interest at the end − the "
    "reference's|. Crossings: frame ends at which triangles of the self-colliding surface intersect "
    "(IPC Toolkit; — where not audited). Status stopped: the run-time guard stopped the run."
)
_COLUMNS = ("integrator", "precision", "option", "substeps", "dt [ms]", "tolerance", "steps/s", "wall [ms/s]",
            "error [m]", "horizon error [m]", "Hausdorff [m]", "quantity", "Δ quantity", "max strain", "crossings",
            "status")


def contact_problems(study: Study) -> list[ContactProblem]:
    """The study's contact problems, in its order."""
    return [p for p in study.plan.problems if getattr(p, "contact", False)]


def section(study: Study, problem: ContactProblem) -> list[str]:
    """The Markdown lines of one contact problem: description, reference, its convergence, the runs."""
    ref = study.references[problem.name]
    option = problem.scene.options[0].label
    steps = ", ".join(str(n) for n in ref.substeps)
    lines = [
        "",
        f"## {problem.name}",
        "",
        problem.describe() + ".",
        "",
        f"Measured on {study.device} ({study.device_name}), Warp {study.warp_version}, {study.date}"
        + (f": `{study.command}`." if study.command else "."),
        "",
        f"Reference: {REFERENCE_INTEGRATOR}, float64, {option}, at {steps} substeps per frame (dt = "
        + ", ".join(f"{1e3 / (FPS * n):.4g}" for n in ref.substeps)
        + f" ms); the finest is the reference. Its quantity of interest at the end: {ref.quantity:.5g}"
        + ("" if ref.max_strain is None else f"; max spring strain {ref.max_strain:.3f}")
        + f". The reference runs took {ref.wall:.1f} s.",
        "",
        "Convergence of the reference: each run against the run at half its step (a first-order scheme: the "
        "finest run's own error is about the last row's).",
        "",
        "| run (substeps) | against | horizon error [m] | RMS over the horizon [m] | Hausdorff at the end [m] | "
        "quantity | Δ quantity | wall of the finer [s] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for c in ref.convergence:
        lines.append(
            f"| {c['substeps']} | {2 * c['substeps']} | {c['error_horizon']:.3g} | {c['error_rms']:.3g} | "
            f"{c['hausdorff']:.3g} | {c['quantity']:.5g} | {c['quantity_error']:.3g} | {c['wall']:.2f} |"
        )
    if ref.cross_check:
        lines += [
            "",
            f"Cross-check: {ref.cross_check[0]['integrator']} (float64, {option}) at the finest reference steps "
            "against the reference: whether a multi-stage integrator, whose stages do not see the contacts (the "
            "response runs after the step), approaches the same motion as its step shrinks.",
            "",
            "| integrator | substeps | horizon error [m] | Hausdorff at the end [m] | Δ quantity | wall [s] |",
            "|---|---|---|---|---|---|",
        ]
        for c in ref.cross_check:
            if "error" in c:
                lines.append(f"| {c['integrator']} | {c['substeps']} | failed: {c['error']} | | | |")
            else:
                lines.append(f"| {c['integrator']} | {c['substeps']} | {c['error_horizon']:.3g} | {c['hausdorff']:.3g} "
                             f"| {c['quantity_error']:.3g} | {c['wall']:.2f} |")
    lines += ["", "| " + " | ".join(_COLUMNS) + " |", "|" + "---|" * len(_COLUMNS)]
    for r in (r for r in study.rows if r.problem == problem.name):
        cells = [
            r.integrator, r.precision, r.option or "", "" if r.tolerance is not None else f"{round(1 / (FPS * r.dt))}",
            f"{r.dt * 1e3:.4g}", "" if r.tolerance is None else f"{r.tolerance:g}", _num(r.steps_per_second, ".4g"),
            _num(None if r.wall_per_second is None else r.wall_per_second * 1e3, ".3g"), _num(r.error_max, ".2e"),
            _num(r.error_horizon, ".2e"), _num(r.hausdorff, ".2e"), _num(r.quantity, ".4g"),
            _num(r.quantity_error, ".2e"), _num(r.max_strain, ".3f"), _num(r.crossings, "d"), r.status,
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _style(name: str) -> str:
    names = list(INTEGRATORS) + sorted({name} - set(INTEGRATORS))
    return f"C{names.index(name) % 10}"


def plot_pareto(study: Study, path: str) -> str:
    """Error [m] against wall time per simulated second (log-log), one panel per contact problem: one colour per
    integrator, one marker per contact option, float64 filled and float32 hollow, the Pareto front grey."""
    from matplotlib.lines import Line2D

    plt = pyplot("the trade plots")
    from matplotlib.ticker import NullFormatter

    problems = contact_problems(study)
    columns = min(len(problems), 3)
    lines = -(-len(problems) // columns)
    fig, axes = plt.subplots(lines, columns, figsize=(5.8 * columns, 4.6 * lines + 1.0), squeeze=False)
    for ax in axes.flat[len(problems):]:
        ax.set_visible(False)
    for ax, problem in zip(axes.flat, problems):
        rows = [r for r in study.rows if r.problem == problem.name and r.status == "ok" and r.wall_per_second]
        markers = {o.label: _MARKERS[k % len(_MARKERS)] for k, o in enumerate(problem.measured_options)}
        front = pareto_front(rows)
        if front:
            ax.step([r.wall_per_second for r in front], [r.error_max for r in front], where="post", color="0.6",
                    lw=1.5, zorder=1)
        for r in rows:
            colour = _style(r.integrator)
            ax.plot(r.wall_per_second, r.error_max, ls="none", ms=6, marker=markers[r.option], color=colour,
                    mfc=colour if r.precision == "float64" else "none", zorder=2)
        floor = study.references[problem.name].convergence[-1]
        ax.axhline(max(floor["error_horizon"], floor["hausdorff"]), color="k", ls=":", lw=1)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_minor_formatter(NullFormatter())  # minor labels collide over short ranges
        ax.yaxis.set_minor_formatter(NullFormatter())
        ax.set_title(problem.name)
        ax.set_xlabel("wall time per simulated second [s/s]")
        ax.set_ylabel("error: max(horizon error, Hausdorff at rest) [m]")
        ax.grid(True, which="both", alpha=0.25)
        handles = [Line2D([], [], color="0.3", marker=m, ls="none", label=label) for label, m in markers.items()]
        ax.legend(handles=handles, fontsize=7, loc="best", title="contact option", title_fontsize=7)
    names = dict.fromkeys(r.integrator for r in study.rows if any(r.problem == p.name for p in problems))
    handles = [Line2D([], [], color=_style(n), marker="o", ls="none", label=n) for n in names] + [
        Line2D([], [], color="0.3", marker="o", ls="none", label="float64 (filled)"),
        Line2D([], [], color="0.3", marker="o", mfc="none", ls="none", label="float32 (hollow)"),
        Line2D([], [], color="0.6", lw=1.5, label="Pareto front"),
        Line2D([], [], color="k", ls=":", lw=1, label="reference's own difference (h vs h/2)"),
    ]
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 5), frameon=False)
    fig.suptitle(f"Contact scenes: error against cost ({study.device}: {study.device_name}, Warp {study.warp_version})")
    fig.tight_layout(rect=(0, 0.9 / (4.6 * lines + 1.0) + 0.04, 1, 0.95))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _num(value, spec: str) -> str:
    return "—" if value is None else format(value, spec)
