"""The stability map's report: Markdown tables, CSV files and plots of a measured :class:`StabilityMap`."""

from __future__ import annotations

import csv
import math
import os

import numpy as np
import warp as wp

from .. import checks
from ..plotting import pyplot
from .stability import stable_omega_h
from .stability_map import (
    Bracket,
    CLOTH_DAMPING_RATIO,
    CLOTH_PERTURBATION,
    ENERGY_CAP,
    GROWTH,
    OMEGA_H_RANGE,
    SEED_DAMPING,
    SEED_MASS,
    SEED_SIZE,
    SEED_SPACING,
    SEED_THRESHOLD,
    StabilityMap,
    UNITY_FIXED_STEP,
)



def _relative(bracket: Bracket | None, reference: float) -> str:
    """The bracket's ends divided by ``reference``: whether the reference lies inside it."""
    if bracket is None or not bracket.two_sided or not 0.0 < reference < math.inf:
        return "—"
    return f"{bracket.low / reference:.4f} … {bracket.high / reference:.4f}"


def _limit(value: float) -> str:
    if value == 0.0:
        return "0 (unstable at every step)"
    return "∞" if math.isinf(value) else f"{value:.4g}"


def to_markdown(result: StabilityMap) -> str:
    """The map as Markdown: one table per study, with the test's parameters and the assumptions."""
    plan = result.plan
    lines = [
        "# Stability map",
        "",
        f"Plan `{plan.name}` on {result.device}, Warp {wp.__version__}, {result.date}; wall time (kernel "
        f"compilation included): " + ", ".join(f"{k} {v:.1f} s" for k, v in result.timings.items()) + ".",
        f"Growth test: unstable when the mean of E over the last quarter of a run exceeds that over the second "
        f"quarter by more than (1 + {GROWTH:g})², E turns non-finite, or E exceeds {ENERGY_CAP:.0e}× its "
        f"start; undecided runs continue up to {2**plan.doublings}× their length. Measured values are "
        f"brackets: midpoint ± half-width.",
        "",
        "## 1. One damped spring: largest stable ωh",
        "",
        f"{plan.spring_points} oscillators per ζ and run, {plan.spring_steps} steps per run (up to "
        f"{plan.spring_steps * 2**plan.doublings}), h = 1 s, float64; first run ωh = {OMEGA_H_RANGE[0]:g} … "
        f"{OMEGA_H_RANGE[1]:g}.",
        "",
        "| integrator | ζ | theory ωh | measured ωh | bracket / theory | runs |",
        "|---|---|---|---|---|---|",
    ]
    for r in result.springs:
        measured = "adaptive: not measured" if r.measured is None else r.measured.text()
        relative = _relative(r.measured, r.theory)
        runs = r.measured.runs if r.measured else 0
        lines.append(f"| {r.integrator} | {r.zeta:g} | {_limit(r.theory)} | {measured} | {relative} | {runs} |")
    floors = [r for r in result.springs if r.theory == 0.0 and r.measured is not None and r.measured.low > 0.0]
    lines.append("")
    if floors:
        lines.append(
            "Theory 0 (growth at every step) with a finite measured value: the growth per step below that value "
            f"is too slow to exceed the test's threshold within {plan.spring_steps * 2**plan.doublings} steps "
            "(a detection floor, not a stable range)."
        )
    lines.append("dopri5's theory is the fixed-step limit of its 5th-order tableau: the cap on its internal step.")
    lines += [
        "",
        f"## 2. Cloth ({plan.cloth_size}×{plan.cloth_size}, ANCHORS layout, kd/ke = {CLOTH_DAMPING_RATIO:g} s): "
        "largest stable dt",
        "",
        f"Gravity off, flat, in-plane start of {CLOTH_PERTURBATION:g} × spacing (stiff-mode weighted); "
        f"{plan.cloth_steps} steps per run (up to {plan.cloth_steps * 2**plan.doublings}); bisection on dt to "
        f"{plan.cloth_resolution:.1%}. Advisor: power-iteration ω_max, Rayleigh damping kd/ke.",
        "",
        "| integrator | ke [N/m] | ω_max [rad/s] | ζ at ω_max | advisor dt [s] | measured dt [s] | bracket / advisor "
        "| runs |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in result.cloth:
        if r.measured is None:
            measured = "adaptive: chooses its step"
        elif math.isinf(r.measured.high):
            measured = f"stable at all {r.measured.runs} tested, up to {r.measured.low:.4g}"
        else:
            measured = r.measured.text()
        zeta = CLOTH_DAMPING_RATIO * r.omega_max / 2.0
        relative = _relative(r.measured, r.predicted)
        runs = r.measured.runs if r.measured else 0
        lines.append(f"| {r.integrator} | {r.stiffness:.0e} | {r.omega_max:.4g} | {zeta:.3g} | {_limit(r.predicted)} "
                     f"| {measured} | {relative} | {runs} |")
    lines += [
        "",
        "dopri5's advisor value is the stability cap on its internal step. Where ζ at ω_max is small, explicit "
        "Euler and midpoint grow only slowly just past their limit (explicit Euler by ~2ζ²ε per step at ε above "
        "it): a measured bracket above the advisor there is the run's detection floor, which shrinks with longer "
        "runs (plan `full`).",
    ]
    seed = result.seed
    if seed is not None:
        t = seed.threshold
        lines += [
            "",
            "## 3. The seed observation: RK4 unstable for k > 22",
            "",
            "Assumed layout (the seed's is not recorded): the public Unity project Darkgrouptw/Cloth-Simulation — "
            f"{SEED_SIZE}×{SEED_SIZE} particles {SEED_SPACING:g} m apart, {SEED_MASS:g} kg each, structural + shear + "
            f"bend + skip-one-diagonal springs with kd = {SEED_DAMPING:g} N·s/m, two corners pinned; warpspring's "
            "classic RK4; gravity off, flat start as in study 2.",
            "",
            "| quantity | value |",
            "|---|---|",
            f"| ω_max at k = {SEED_THRESHOLD:g} N/m (power iteration) | {seed.omega_max:.4g} rad/s |",
            f"| fixed step at which the advisor puts RK4's threshold at k = {SEED_THRESHOLD:g} N/m | {seed.dt:.4g} s |",
            f"| threshold k measured by simulation at that step ({t.runs} runs of {seed.steps} steps) | "
            f"{t.low:.4g} … {t.high:.4g} N/m (stable at {t.low:.4g}, unstable at {t.high:.4g}) |",
            f"| measured / {SEED_THRESHOLD:g} | {t.value / SEED_THRESHOLD:.4f} |",
            f"| the advisor's RK4 threshold at Unity's default step {UNITY_FIXED_STEP:g} s "
            f"| {seed.unity_threshold:.4g} N/m |",
            "",
            f"So the observation fits RK4 on this layout at a step of about {seed.dt:.3g} s, "
            f"{seed.dt / UNITY_FIXED_STEP:.1f}× Unity's default; at the default step the same cloth would stay "
            f"stable up to k ≈ {seed.unity_threshold:.3g} N/m.",
        ]
    return "\n".join(lines) + "\n"


def write_csv(result: StabilityMap, out_dir: str) -> list[str]:
    """spring.csv, cloth.csv and (with a seed result) seed.csv in ``out_dir``; returns their paths."""
    paths = []

    def write(name, header, rows):
        path = os.path.join(out_dir, name)
        with open(path, "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(header)
            writer.writerows(rows)
        paths.append(path)

    def ends(b: Bracket | None):
        return ("", "", 0) if b is None else (b.low, b.high, b.runs)

    write("spring.csv", ["integrator", "zeta", "theory_omega_h", "measured_low", "measured_high", "runs", "steps"],
          [(r.integrator, r.zeta, r.theory, *ends(r.measured), r.steps) for r in result.springs])
    write("cloth.csv", ["integrator", "stiffness", "omega_max", "predicted_dt", "measured_low", "measured_high",
                        "runs", "steps"],
          [(r.integrator, r.stiffness, r.omega_max, r.predicted, *ends(r.measured), r.steps) for r in result.cloth])
    if result.seed is not None:
        s = result.seed
        write("seed.csv", ["dt", "omega_max", "threshold_low", "threshold_high", "runs", "steps", "unity_threshold"],
              [(s.dt, s.omega_max, s.threshold.low, s.threshold.high, s.threshold.runs, s.steps, s.unity_threshold)])
    return paths


def plot_springs(result: StabilityMap, path: str) -> str:
    """ωh_max against ζ: theory lines, measured brackets as markers with error bars."""
    plt = pyplot("the stability plots")
    fig, ax = plt.subplots(figsize=(8, 5.5))
    # Dense, with the measured ζ and the cusp at critical damping (ζ = 1) on the grid.
    zetas = np.union1d(np.concatenate([np.linspace(0.0, 1e-3, 11), [1.0], np.geomspace(1e-3, 3.0, 120)]),
                       result.plan.zetas)
    names = list(dict.fromkeys(r.integrator for r in result.springs))
    for index, name in enumerate(names):
        rows = [r for r in result.springs if r.integrator == name]
        if math.isinf(rows[0].theory):
            continue  # unconditionally stable: nothing to draw
        color = f"C{index}"
        adaptive = rows[0].measured is None
        theory = [stable_omega_h(name, float(z)) for z in zetas]
        label = f"{name} (fixed-step tableau; adaptive)" if adaptive else name
        ax.plot(zetas, theory, color=color, linestyle="--" if adaptive else "-", label=label)
        for r in rows:
            if r.measured is None:
                continue
            b = r.measured
            ax.errorbar([r.zeta], [b.value], yerr=[[b.value - b.low], [b.high - b.value]], fmt="o", color=color,
                        markersize=5, capsize=2)
    stable_everywhere = [n for n in names if math.isinf(next(r for r in result.springs if r.integrator == n).theory)]
    ax.set_xscale("symlog", linthresh=1e-3, linscale=0.5)
    ax.set_xlim(0.0, 3.0)
    ax.set_ylim(0.0, 4.0)
    ax.set_xlabel("damping ratio ζ")
    ax.set_ylabel("largest stable ωh")
    title = "One damped spring: theory (lines) and simulation (markers)"
    if stable_everywhere:
        title += f"\n{', '.join(stable_everywhere)}: stable at every tested ωh (not drawn)"
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)
    return path


def plot_cloth(result: StabilityMap, path: str) -> str:
    """Largest stable dt against ke (log-log): the advisor's prediction (lines), simulation (markers)."""
    plt = pyplot("the stability plots")
    fig, ax = plt.subplots(figsize=(8, 5.5))
    names = list(dict.fromkeys(r.integrator for r in result.cloth))
    notes = []
    for index, name in enumerate(names):
        rows = [r for r in result.cloth if r.integrator == name]
        color = f"C{index}"
        if name in result.predictions:
            k, dt = result.predictions[name]
            adaptive = rows[0].measured is None
            ax.plot(k, dt, color=color, linestyle="--" if adaptive else "-",
                    label=f"{name} (internal-step cap; adaptive)" if adaptive else name)
        else:
            notes.append(name)
        for r in rows:
            if r.measured is None or not r.measured.two_sided:
                continue
            b = r.measured
            ax.errorbar([r.stiffness], [b.value], yerr=[[b.value - b.low], [b.high - b.value]], fmt="o",
                        color=color, markersize=5, capsize=2)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("spring stiffness ke [N/m]")
    ax.set_ylabel("largest stable dt [s]")
    title = (f"{result.plan.cloth_size}×{result.plan.cloth_size} cloth, kd/ke = {CLOTH_DAMPING_RATIO:g} s: "
             "advisor (lines) and simulation (markers)")
    if notes:
        title += f"\n{', '.join(notes)}: stable at every tested step (not drawn)"
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)
    return path


def write_report(result: StabilityMap, out_dir: str) -> list[str]:
    """stability.md, the CSV files and spring.png, cloth.png in ``out_dir`` (created); returns the paths."""
    os.makedirs(checks.output_dir(out_dir), exist_ok=True)
    md = os.path.join(out_dir, "stability.md")
    with open(md, "w") as f:
        f.write(to_markdown(result))
    return [md, *write_csv(result, out_dir), plot_springs(result, os.path.join(out_dir, "spring.png")),
            plot_cloth(result, os.path.join(out_dir, "cloth.png"))]
