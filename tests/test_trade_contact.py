"""The contact scenes of the speed/accuracy study (warpspring.analysis.trade_contact): their errors against the
float64 references follow the order of the scheme, the contact options' own difference shows, the files and
``warpspring choose --problem`` read them.

One quick study per device (symplectic Euler at 10 and 20 substeps per frame, references at 40 and 80) on the
drape, the stack, the tablecloth and both soft balls, shared by the tests.
"""

import dataclasses
import math
import pathlib

import pytest

from warpspring.analysis import trade_contact
from warpspring.analysis.trade import Measurement, run_study
from warpspring.analysis.trade_choice import choose
from warpspring.analysis.trade_scenes import STACK_BOX
from warpspring.analysis.trade_report import read_csv, write_csv, write_report
from warpspring.app.cli import EXIT_NO_CHOICE, main
from warpspring.errors import ConfigError

STACK_TOP = STACK_BOX[0][2] + STACK_BOX[1][2]  # [m]
PROBLEMS = ("drape", "stack", "tablecloth", "softball", "softball-neohookean")
_STUDIES = {}


@pytest.fixture
def study(device):
    """The quick contact study on ``device`` (computed once per device)."""
    if device not in _STUDIES:
        plan = trade_contact.study_plan(PROBLEMS, quick=True)
        _STUDIES[device] = run_study(device, plan=plan)
    return _STUDIES[device]


def _rows(study, problem, option=None):
    return [r for r in study.rows if r.problem == problem and (option is None or r.option == option)]


@pytest.mark.parametrize("problem", ["tablecloth", "softball", "softball-neohookean"])
def test_errors_are_first_order_in_the_step(study, problem):
    """Symplectic Euler with a contact projection after each step is first order: x_h ≈ x + C(t) h. Against the
    reference at h_N (N = 80 substeps), a run at h errs by |C| (h − h_N); the reference's runs at h_R and h_R / 2
    (R = 40) differ by |C| h_R / 2. So error(n) / that difference = (1/n − 1/N) / (1/R − 1/2R): 7 at n = 10 and 3 at
    n = 20, in float32 too (its rounding, ~1e-7 m a step, is far below errors of ~1e-4 m). The maxima over time
    and particles sit at the same place at every step in these smooth scenes: 20 % covers the O(h²) part."""
    spec = study.problem(problem)
    reference = study.references[problem]
    coarse, finest = reference.substeps[0], reference.substeps[-1]
    difference = reference.convergence[-1]["error_horizon"]
    rows = _rows(study, problem)
    assert len(rows) == 4 and {r.precision for r in rows} == {"float32", "float64"}
    for r in rows:
        assert r.status == "ok", r.label
        n = round(1.0 / (trade_contact.FPS * r.dt))
        predicted = (1.0 / n - 1.0 / finest) / (1.0 / coarse - 1.0 / (2 * coarse))
        assert r.error_horizon / difference == pytest.approx(predicted, rel=0.2), r.label
        assert r.error_max == max(r.error_horizon, r.hausdorff)
        assert r.horizon == spec.horizon and r.crossings is None
    # The quantity of interest at rest converges with it: the volume ratio and the sag within 2e-3 at 20 substeps.
    fine = [r for r in rows if r.steps_per_second == 20 * trade_contact.FPS]
    assert all(r.quantity_error < 2e-3 for r in fine)


def test_stack_lands_without_crossings_at_first_order(study):
    """The quick stack covers the landing of both layers (0.15 s: the bottom cloth falls 4 cm onto the box, the top
    one 7 cm onto it). Every frame end of every run is audited (IPC Toolkit's exact triangle test): no crossing. The
    errors against the reference at h_N (N = 80) are first order, |C| (h − h_N): error(10) / error(20) = (1/10 − 1/80)
    / (1/20 − 1/80) = 7/3, within 20 % (self-contact events move with the step: the maxima need not sit at one
    place), in both precisions; so is the quantity (the top cloth's sag below the box's top at the end). The
    reference's own difference (40 against 80 substeps) is below what it judges at 10 substeps."""
    pytest.importorskip("ipctk", reason="the crossing audit (IPC Toolkit, the audit extra)")
    reference = study.references["stack"]
    own = reference.convergence[-1]
    predicted = (1.0 / 10 - 1.0 / 80) / (1.0 / 20 - 1.0 / 80)
    for precision in ("float32", "float64"):
        rows = sorted((r for r in _rows(study, "stack") if r.precision == precision), key=lambda r: r.dt)
        assert [r.status for r in rows] == ["ok", "ok"] and [r.crossings for r in rows] == [0, 0]
        fine, coarse = rows
        assert coarse.error_horizon / fine.error_horizon == pytest.approx(predicted, rel=0.2), precision
        assert coarse.quantity_error / fine.quantity_error == pytest.approx(predicted, rel=0.2), precision
        assert own["error_horizon"] < coarse.error_horizon < 0.01  # millimetres: the layers land where they should
        assert 0.0 < fine.quantity < STACK_TOP  # the top cloth hangs below the box's top, above the ground


def test_drape_measures_and_the_contact_options(study):
    """Particle contacts (the reference option): the errors shrink with the step and stay above the reference's
    own difference, and the drape coefficient comes within 0.01 of the reference's. Triangle contacts are another
    model of the same cloth at this coarse spacing (the builder's rule asks them here): their difference from the
    reference is the option's, not the step's, so halving the step leaves it, ten times the particle contacts' error."""
    reference = study.references["drape"]
    own = reference.convergence[-1]
    assert own["quantity_error"] < 0.01 and 0.0 < own["error_horizon"] < 0.01
    for precision in ("float32", "float64"):
        particle = sorted((r for r in _rows(study, "drape", "particle contacts") if r.precision == precision),
                          key=lambda r: r.dt)
        assert [r.status for r in particle] == ["ok", "ok"]
        fine, coarse = particle
        assert own["error_horizon"] < fine.error_horizon < coarse.error_horizon
        assert fine.quantity_error < 0.01
        assert 0.3 < fine.quantity < 0.8  # a drape: the shadow is between the sphere's disc and the flat cloth
        triangle = [r for r in _rows(study, "drape", "triangle contacts") if r.precision == precision]
        for r in triangle:
            assert r.error_horizon > 10.0 * coarse.error_horizon
        assert triangle[0].error_horizon == pytest.approx(triangle[1].error_horizon, rel=0.1)


def test_report_and_choose(study, tmp_path, capsys):
    paths = write_report(study, str(tmp_path))
    names = {pathlib.Path(p).name for p in paths}
    assert names == {"trade.csv", "trade.md", "pareto_contact.png"}  # no closed forms: no convergence plot
    assert (tmp_path / "pareto_contact.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    markdown = (tmp_path / "trade.md").read_text()
    for problem in PROBLEMS:
        assert f"## {problem}\n" in markdown
    assert "| run (substeps) | against | horizon error [m] |" in markdown
    rows = read_csv(str(tmp_path / "trade.csv"))
    assert rows == study.rows
    assert {(r.device, r.device_name) for r in rows} == {(study.device, study.device_name)}  # the rows name it
    assert f"Measured on {study.device} ({study.device_name})" in markdown

    # The cheapest measured tablecloth configuration within 1 mm, and what it says.
    target = 1e-3
    qualifying = [r for r in rows if r.problem == "tablecloth" and r.status == "ok" and r.error_max <= target]
    best = min(qualifying, key=lambda r: r.wall_per_second)
    assert main(["choose", "--error", str(target), "--study", str(tmp_path / "trade.csv"), "--problem",
                 "tablecloth"]) == 0
    out = capsys.readouterr().out
    assert best.label in out and "2 slots" in out and f"on {study.device} ({study.device_name})" in out
    assert f"trajectory error over the first {best.horizon:g} s ({best.error_horizon:.3g} m)" in out
    floor = min(r.error_max for r in rows if r.problem == "drape" and r.status == "ok")
    assert main(["choose", "--error", str(floor / 2), "--study", str(tmp_path / "trade.csv"), "--problem",
                 "drape"]) == EXIT_NO_CHOICE


def _contact_row(wall, error, crossings=None, option="τ = 4 mm") -> Measurement:
    return Measurement(problem="stack", integrator="symplectic_euler", order=1, precision="float32", device="cpu",
                       dt=1e-3, tolerance=None, steps_per_second=1e3, mean_step=1e-3, wall_per_second=wall,
                       status="ok", error_max=error, option=option, crossings=crossings)


def test_choose_never_picks_a_crossing(tmp_path):
    crossed = _contact_row(0.1, 1e-4, crossings=2)  # the cheapest and the most accurate, but the cloth crossed
    clean = _contact_row(0.3, 5e-4, crossings=0, option="τ = 10 mm")
    choice = choose([crossed, clean], 1e-3)
    assert choice.row is clean and "τ = 10 mm" in choice.explanation
    path = write_csv([crossed, clean], str(tmp_path / "t.csv"))
    assert read_csv(path) == [crossed, clean]


def test_choose_scales_the_step_where_nothing_meets_a_contact_target():
    """Contact runs converge at first order (the references show it): 8 mm at dt = 1 ms asks 8× the steps for 1 mm."""
    rows = [_contact_row(0.3, 8e-3), dataclasses.replace(_contact_row(0.1, 2e-2), dt=2e-3)]
    choice = choose(rows, 1e-3)
    assert choice.row is None and choice.runner_up is rows[0]
    assert choice.dt == pytest.approx(1e-3 / 8) and choice.integrator == "symplectic_euler"
    assert "first order" in choice.explanation and "about 8× its steps" in choice.explanation


def test_an_older_study_still_reads():
    """A study written before the contact scenes (no contact columns) reads, its rows without contact fields."""
    rows = read_csv(str(pathlib.Path(__file__).parents[1] / "bench" / "results" / "trade_cpu.csv"))
    assert rows and all(r.option is None and r.crossings is None for r in rows)
    assert choose(rows, 1e-3, problem="cloth").row is not None


def test_plans():
    full = trade_contact.study_plan(["cloth", "drape"])
    assert [p.name for p in full.problems] == ["cloth", "drape"]
    assert full.problems[1] is trade_contact.FULL_PROBLEMS["drape"]
    assert trade_contact.study_plan(None, quick=True).problems == trade_contact.QUICK.problems
    with pytest.raises(ConfigError, match="unknown problem 'drapes'"):
        trade_contact.study_plan(["drapes"])
    # Every quick problem is a smaller copy of its full one: same scene, horizon within the run.
    for name, quick in trade_contact.QUICK_PROBLEMS.items():
        full = trade_contact.FULL_PROBLEMS[name]
        assert quick.horizon <= quick.duration and full.horizon <= full.duration
        assert quick.size <= full.size and quick.refinements == 1
        assert all(label in {o.label for o in quick.scene.options} for label in quick.options)
    # The reduced plan (the GPU rows): the full scenes, the reference option, two steps, one reference refinement.
    for name, reduced in trade_contact.REDUCED_PROBLEMS.items():
        full = trade_contact.FULL_PROBLEMS[name]
        assert (reduced.size, reduced.duration, reduced.horizon) == (full.size, full.duration, full.horizon)
        assert reduced.measured_options == full.scene.options[:1] and reduced.substeps == (20, 40)
        assert reduced.refinements == 1 and reduced.integrators == full.integrators
    plan = trade_contact.study_plan(["drape"], reduced=True)
    assert plan.name == "reduced" and plan.problems == (trade_contact.REDUCED_PROBLEMS["drape"],)
    with pytest.raises(ConfigError, match="one of quick and reduced"):
        trade_contact.study_plan(["drape"], quick=True, reduced=True)
    with pytest.raises(ConfigError, match="no contact option"):
        dataclasses.replace(trade_contact.QUICK_PROBLEMS["drape"], options=("edge contacts",)).measured_options
    assert math.isclose(trade_contact.FPS, 60.0)
