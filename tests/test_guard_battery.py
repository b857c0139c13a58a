"""A subset of the guard's battery (``warpspring/analysis/guard_battery.py``; the whole of it is
``bench/guard_battery.py``): ``examples/flag_in_wind.toml`` under symplectic Euler: not stopped at the step the advisor passes (10 frames);
stopped within 60 frames, before any non-finite value and by a message naming what the scene holds, at twice the
advisor's limit and after its stiffest spring is made 100 times stiffer mid-run. About one minute on an idle 2-core
CPU, most of it the advisor's dry run, whose wall budget on a loaded machine makes its choice conservative
(Gershgorin). The loaded variants (a handle and a moving collider added to the wind, the balance then off) take a
minute each and are in the benchmark only."""

import pathlib

import pytest

from warpspring.analysis.guard_battery import STIFF_AT, STOP_FRAMES, run_case

pytestmark = pytest.mark.slow

FLAG = pathlib.Path(__file__).resolve().parents[1] / "examples" / "flag_in_wind.toml"


@pytest.mark.parametrize("variant, case", [("as is", "advisor"), ("as is", "twice"), ("as is", "stiff")])
def test_the_flag_in_the_battery(variant, case):
    outcome = run_case(FLAG, variant, "symplectic_euler", case, device="cpu", frames=10)
    assert outcome.passed, outcome.row() + "\n" + outcome.message
    if case == "advisor":
        assert not outcome.stopped and outcome.frames == 10
    else:
        first = STIFF_AT if case == "stiff" else 0
        assert outcome.stopped and first < outcome.frames <= first + STOP_FRAMES
        assert outcome.reason != "non-finite state"
        assert "wind triangles" in outcome.message
        assert ("handle grabs" in outcome.message) == (variant == "loaded")
