"""What a speed/accuracy study's measurements say: convergence orders fitted in the asymptotic range, the
Pareto front of error against cost, and :func:`choose`, the cheapest measured configuration that meets an
error target (the tolerance knob of ``warpspring choose``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..checks import format_duration
from ..core.integrators import INTEGRATORS
from ..errors import ConfigError
from .trade import Measurement, Study

#: Fits of the convergence order keep steps with ω_max·h at most this (coarser ones are pre-asymptotic) ...
ASYMPTOTIC_OMEGA_H = 0.5
#: ... errors below this fraction of the problem's length scale (larger ones are saturated) ...
ASYMPTOTIC_CEILING = 0.1
#: ... and above this multiple of the noise floor (float64 rounding accumulated over the run, and the
#: cloth reference's own error, estimated by its difference from a run at twice its step).
NOISE_MARGIN = 10.0


# -- fits ---------------------------------------------------------------------------------------------------


def fit_order(step, error) -> float:
    """The convergence order p of error ≈ C · stepᵖ: the least-squares slope of log(error) against log(step).

    Args:
        step: step sizes [s], shape [n], n ≥ 2 distinct values.
        error: errors (any unit), shape [n], > 0.

    Raises:
        ConfigError: fewer than two distinct steps, mismatched shapes, or a non-positive value.
    """
    step, error = np.asarray(step, dtype=np.float64), np.asarray(error, dtype=np.float64)
    if step.shape != error.shape or step.ndim != 1:
        raise ConfigError(f"step and error must be 1-D arrays of one length, got shapes {step.shape} and {error.shape}")
    if len(np.unique(step)) < 2:
        raise ConfigError("fitting a convergence order needs at least two distinct steps")
    if not (np.all(step > 0) and np.all(error > 0)):
        raise ConfigError("fitting a convergence order needs positive steps and errors")
    return float(np.polyfit(np.log(step), np.log(error), 1)[0])


def asymptotic_range(
    rows: list[Measurement], *, frequency: float, length_scale: float, duration: float, noise: float = 0.0
) -> list[Measurement]:
    """The float64, stable rows in the asymptotic range: for fixed-step integrators a step h with
    ``frequency`` · h at most ``ASYMPTOTIC_OMEGA_H`` (``frequency``: the problem's fastest, ω_max [rad/s];
    adaptive integrators size their steps from their error estimate instead), an error below
    ``ASYMPTOTIC_CEILING`` × ``length_scale`` [m] and above ``NOISE_MARGIN`` × the noise floor: ``noise``
    [m] (e.g. the reference's own error) plus float64 rounding accumulated over the steps of a run of
    ``duration`` [s], ε · length_scale · steps."""
    chosen = []
    for r in rows:
        if r.status != "ok" or r.precision != "float64" or r.error_max is None or r.mean_step is None:
            continue
        if r.tolerance is None and frequency * r.dt > ASYMPTOTIC_OMEGA_H:
            continue
        steps = r.steps_per_second * duration
        floor = NOISE_MARGIN * (noise + np.finfo(np.float64).eps * length_scale * steps)
        if floor < r.error_max <= ASYMPTOTIC_CEILING * length_scale:
            chosen.append(r)
    return chosen


def convergence_orders(study: Study, problem: str) -> dict[str, tuple[float | None, list[Measurement]]]:
    """Fitted order per integrator on ``problem``: name → (order or ``None`` with fewer than 3 usable
    points, the rows fitted). Fixed-step integrators are fitted against dt, adaptive ones against their
    mean accepted step."""
    spec = study.problem(problem)
    reference = study.references.get(problem)
    noise = reference.self_difference if reference is not None else 0.0
    frequency = reference.fastest_frequency if reference is not None else spec.fastest_frequency
    orders = {}
    for name in dict.fromkeys(r.integrator for r in study.rows if r.problem == problem):
        rows = [r for r in study.rows if r.problem == problem and r.integrator == name]
        fitted = asymptotic_range(
            rows, frequency=frequency, length_scale=spec.length_scale, duration=spec.duration, noise=noise
        )
        distinct = len({r.mean_step for r in fitted})
        order = fit_order([r.mean_step for r in fitted], [r.error_max for r in fitted]) if distinct >= 3 else None
        orders[name] = (order, fitted)
    return orders


def pareto_front(rows: list[Measurement]) -> list[Measurement]:
    """The measured rows no other row beats in both wall time and error, by increasing wall time."""
    usable = sorted(
        (r for r in rows if r.status == "ok" and r.wall_per_second is not None and r.error_max is not None),
        key=lambda r: (r.wall_per_second, r.error_max),
    )
    front, best = [], math.inf
    for r in usable:
        if r.error_max < best:
            front.append(r)
            best = r.error_max
    return front


# -- the tolerance knob -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Choice:
    """What :func:`choose` recommends.

    Attributes:
        integrator: integrator name.
        options: its options, e.g. ``{"tolerance": 1e-5}`` for an adaptive integrator.
        dt: the step [s] (adaptive: the output interval measured), or ``None`` when unmeasured.
        precision: "float32" / "float64", or ``None`` when unmeasured.
        row: the measured configuration behind the choice, or ``None`` when the recommendation is untested.
        runner_up: the next-best measured configuration the explanation compares with, or ``None``.
        explanation: one paragraph: what was chosen and why, with the measured error and cost of the
            pick and of the runner-up.
    """

    integrator: str
    options: dict
    dt: float | None
    precision: str | None
    row: Measurement | None
    runner_up: Measurement | None
    explanation: str


def choose(study_rows, target_error: float, *, time_budget: float | None = None, problem: str | None = None) -> Choice:
    """The fastest measured fixed-step configuration whose max error meets ``target_error``, within
    ``time_budget`` if given; when none does, an adaptive integrator with a tolerance. Contact scenes' rows
    carry their contact options (the pick's label names them); a row with a crossing is never picked.

    Args:
        study_rows: :class:`~warpspring.analysis.trade.Measurement` rows (from
            :func:`~warpspring.analysis.trade.run_study` or :func:`warpspring.analysis.trade_report.read_csv`).
        target_error: the largest acceptable max position error [m].
        time_budget: the most wall time per simulated second [s/s], or ``None`` for no limit.
        problem: use only the rows of this problem; needed when the rows hold several.

    Raises:
        ConfigError: a non-positive target or budget, an unknown problem, or rows of several problems
            without ``problem``.
    """
    if not (isinstance(target_error, (int, float)) and math.isfinite(target_error) and target_error > 0):
        raise ConfigError(f"target error must be a finite number > 0 [m], got {target_error!r}")
    if time_budget is not None and not (
        isinstance(time_budget, (int, float)) and math.isfinite(time_budget) and time_budget > 0
    ):
        raise ConfigError(f"time budget must be a finite number > 0 [s per simulated s], got {time_budget!r}")
    rows = list(study_rows)
    problems = list(dict.fromkeys(r.problem for r in rows))
    if problem is not None:
        if problem not in problems:
            raise ConfigError(f"the study has no problem {problem!r}; it has: {', '.join(problems) or 'no rows'}")
        rows = [r for r in rows if r.problem == problem]
    elif len(problems) > 1:
        raise ConfigError(f"the study holds several problems ({', '.join(problems)}): say which one")
    if not rows:
        raise ConfigError("the study has no measurements")

    # A contact run whose surface crossed itself is wrong however small its distance to the reference.
    measured = [r for r in rows if r.status == "ok" and r.error_max is not None and r.wall_per_second is not None
                and not r.crossings]
    fixed = [r for r in measured if r.tolerance is None]
    adaptive = sorted((r for r in measured if r.tolerance is not None), key=lambda r: r.wall_per_second)
    accurate = sorted((r for r in fixed if r.error_max <= target_error), key=lambda r: r.wall_per_second)
    affordable = [r for r in accurate if time_budget is None or r.wall_per_second <= time_budget]
    adaptive_accurate = [r for r in adaptive if r.error_max <= target_error]
    target = f"a max error of at most {target_error:.3g} m"
    if affordable:
        pick = affordable[0]  # fixed steps first: their cost does not depend on how the motion goes
        adaptive_affordable = [r for r in adaptive_accurate if time_budget is None or r.wall_per_second <= time_budget]
        runner_up = _runner_up(sorted(affordable + adaptive_affordable, key=lambda r: r.wall_per_second), pick)
        within = f" within {_rate(time_budget)}" if time_budget is not None else ""
        text = (
            f"{pick.label} is the fastest measured configuration with {target}{within}: error "
            f"{pick.error_max:.3g} m at {_rate(pick.wall_per_second)} on {_device(pick)}. "
            + _compare(pick, runner_up, f"No other integrator meets the target{within}.")
            + _contact(pick)
        )
        return Choice(pick.integrator, {}, pick.dt, pick.precision, pick, runner_up, text)

    if accurate:  # only the budget fails: nothing measured meets both, so name the cheapest that meets the error
        candidates = sorted(accurate + adaptive_accurate, key=lambda r: r.wall_per_second)
        pick = candidates[0]
        runner_up = _runner_up(candidates, pick)
        text = (
            f"No measured configuration has {target} within {_rate(time_budget)}. The cheapest that meets the "
            f"error is {pick.label}: error {pick.error_max:.3g} m at {_rate(pick.wall_per_second)} "
            f"({pick.wall_per_second / time_budget:.3g}× the budget) on {_device(pick)}. "
            + _compare(pick, runner_up, "No other integrator meets the error.")
            + " Raise the budget or the error target."
        )
        options = {} if pick.tolerance is None else {"tolerance": pick.tolerance}
        return Choice(pick.integrator, options, pick.dt, pick.precision, pick, runner_up, text)

    if fixed and adaptive_accurate == [] and any(r.option is not None for r in fixed):
        return _contact_fallback(fixed, target_error, target)
    # No fixed-step configuration reaches the error: an adaptive integrator, measured if possible.
    if fixed:
        closest = min(fixed, key=lambda r: r.error_max)
        why = (
            f"No measured fixed-step configuration reaches {target}: the most accurate, {closest.label}, has "
            f"{closest.error_max:.3g} m at {_rate(closest.wall_per_second)}."
        )
    else:
        closest = None
        why = "The study holds no stable fixed-step measurement."
    if adaptive_accurate:
        pick = adaptive_accurate[0]
        over = time_budget is not None and pick.wall_per_second > time_budget
        text = (
            f"{why} Use {pick.label}: measured error {pick.error_max:.3g} m at {_rate(pick.wall_per_second)}"
            + (f", over the budget of {_rate(time_budget)}." if over else ".")
        )
        return Choice(pick.integrator, {"tolerance": pick.tolerance}, pick.dt, pick.precision, pick, closest, text)
    names = [r.integrator for r in adaptive] or [n for n, c in INTEGRATORS.items() if c.adaptive] or ["dopri5"]
    if adaptive:
        best = min(adaptive, key=lambda r: r.error_max)
        tolerance = _round_down(best.tolerance * target_error / best.error_max)
        text = (
            f"{why} Use {best.integrator} in {best.precision} with a tolerance of about {tolerance:g} (untested: "
            f"scaled from its most accurate measured run, {best.label}, error {best.error_max:.3g} m at "
            f"{_rate(best.wall_per_second)}, assuming error ∝ tolerance); check it with 'warpspring trade'."
        )
        return Choice(best.integrator, {"tolerance": tolerance}, None, best.precision, None, best, text)
    tolerance = _round_down(0.1 * target_error)
    text = (
        f"{why} Use {names[0]} with a tolerance of about {tolerance:g} (a tenth of the target; untested, as the "
        f"study measured no adaptive integrator); check it with 'warpspring trade'."
    )
    return Choice(names[0], {"tolerance": tolerance}, None, None, None, closest, text)


def _runner_up(candidates: list[Measurement], pick: Measurement) -> Measurement | None:
    """The cheapest of ``candidates`` (sorted by cost) with another integrator than ``pick``'s."""
    return next((r for r in candidates if r.integrator != pick.integrator), None)


def _compare(pick: Measurement, runner_up: Measurement | None, otherwise: str) -> str:
    """The sentence on the runner-up: its measured error and cost, relative to the pick's."""
    if runner_up is None:
        return otherwise
    return (
        f"Runner-up: {runner_up.label}, error {runner_up.error_max:.3g} m at {_rate(runner_up.wall_per_second)} "
        f"({runner_up.wall_per_second / pick.wall_per_second:.3g}× the cost)."
    )


def _contact_fallback(fixed: list[Measurement], target_error: float, target: str) -> Choice:
    """Contact scenes where nothing measured meets the target: the most accurate fixed-step configuration at a
    step scaled down by first-order convergence (what the references' convergence shows for contact runs; an
    adaptive integrator's tolerance does not bound the error its contact response makes)."""
    closest = min(fixed, key=lambda r: r.error_max)
    factor = closest.error_max / target_error
    dt = closest.dt / factor
    text = (
        f"No measured configuration reaches {target}: the most accurate, {closest.label}, has "
        f"{closest.error_max:.3g} m at {_rate(closest.wall_per_second)}. Contact runs converge at first order in "
        f"the step (docs/trade.md), so the same configuration at about {factor:.2g}× its steps (dt ≈ "
        f"{dt * 1e3:.3g} ms) should reach it, at about {factor:.2g}× its cost (untested: check it with "
        "'warpspring trade')."
    )
    return Choice(closest.integrator, {}, dt, closest.precision, None, closest, text)


def _contact(pick: Measurement) -> str:
    """For a contact scene's row: what its error is made of (:mod:`warpspring.analysis.trade_contact`)."""
    if pick.option is None or pick.error_horizon is None:
        return ""
    crossings = "" if pick.crossings is None else f"; {pick.crossings} crossings"
    return (
        f" Its error is the larger of the trajectory error over the first {pick.horizon:g} s "
        f"({pick.error_horizon:.3g} m) and the final shape's Hausdorff distance ({pick.hausdorff:.3g} m) to a "
        f"float64 fine-step reference; its quantity of interest ends {pick.quantity_error:.3g} from the "
        f"reference's{crossings}."
    )


def _device(row: Measurement) -> str:
    """The device a row was measured on: "cuda:0 (NVIDIA H100 80GB HBM3)", or its alias where the name is unknown."""
    return row.device if not row.device_name else f"{row.device} ({row.device_name})"


def _round_down(value: float) -> float:
    """``value`` rounded down to one significant digit (a tolerance setting)."""
    exponent = math.floor(math.log10(value))
    digit = max(1, math.floor(value / 10**exponent * (1.0 + 1e-12)))  # 0.99999… of a power of ten is that power
    return digit * 10.0**exponent


def _rate(wall_per_second: float) -> str:
    """A cost in wall time per simulated second, in readable units."""
    return f"{format_duration(wall_per_second)} per simulated second"
