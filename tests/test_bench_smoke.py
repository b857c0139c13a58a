"""The benchmarks still build and run: ``bench/smoke.py``, run as a script in a process of its own, checks that
every ``bench/*.py`` imports and that each benchmark scene, built by its own script's builder at a tiny size, steps
a frame or two to a state that obeys something checkable in closed form (each check's docstring says what). Each
test here reports one of its checks (same name, without ``test_``); the tests import nothing from ``bench/``.
Speed is not tested here: it lives in ``bench/RESULTS.md``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from helpers import CUDA

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "bench"


@pytest.fixture(scope="module")
def smoke(tmp_path_factory) -> dict:
    """Every check's result from one run of ``bench/smoke.py`` on the CPU (and ``cuda:0`` where present), by
    (check, param, device), with this checkout's warpspring first on the child's path."""
    report = tmp_path_factory.mktemp("smoke") / "report.json"
    devices = ["cpu", "cuda:0"] if CUDA else ["cpu"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    command = [sys.executable, str(BENCH / "smoke.py"), "--report", str(report)]
    for device in devices:
        command += ["--device", device]
    done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=600)
    if not report.exists():
        pytest.fail(f"bench/smoke.py wrote no report (exit {done.returncode}):\n{done.stdout}\n{done.stderr}",
                    pytrace=False)
    return {(r["check"], r["param"], r["device"]): r for r in json.loads(report.read_text())}


@pytest.fixture
def check(request, smoke):
    """A function that reports this test's check: passed, skipped (with its reason) or failed (with its
    traceback). The check has the test's name without ``test_``, its parameter and its device."""

    def report():
        params = dict(request.node.callspec.params) if hasattr(request.node, "callspec") else {}
        device = params.pop("device", None)
        param = next(iter(params.values()), None)
        name = request.node.originalname.removeprefix("test_")
        result = smoke.get((name, param, device))
        if result is None:
            pytest.fail(f"bench/smoke.py has no check {name}[{param}] on {device}", pytrace=False)
        if result["status"] == "skipped":
            pytest.skip(result["detail"])
        if result["status"] != "passed":
            pytest.fail(f"bench/smoke.py: {name}[{param}] on {device}:\n{result['detail']}", pytrace=False)

    return report


@pytest.mark.parametrize("script", sorted(path.stem for path in BENCH.glob("*.py")))
def test_every_bench_script_imports(script, check):
    check()


def test_the_hanging_cloth_holds_its_pins_and_its_bottom_row_falls_freely(device, check):
    check()


def test_newton_runs_the_same_cloth_to_the_same_positions(device, check):
    check()


def test_worlds_fall_under_their_own_gravity(device, check):
    check()


@pytest.mark.parametrize("variant", ["fused", "stage"])
def test_the_contact_scene_falls_as_one_body_before_it_touches(device, variant, check):
    check()


@pytest.mark.parametrize("scene", ["wind", "handle", "emitter", "strain limit"])
def test_scene_force_benches_run_and_hold_their_pins(device, scene, check):
    check()


def test_the_soak_scene_follows_its_pin_track(device, check):
    check()


def test_the_delaunay_network_holds_its_pinned_base(device, check):
    check()


def test_the_usd_stream_bench_writes_its_frames(device, check):
    check()


def test_the_build_bench_counts_the_anchors_springs(check):
    check()


def test_the_traffic_model_counts_the_gathers_arrays(check):
    check()


def test_the_traffic_model_counts_spring_data_per_group(check):
    check()


def test_the_traffic_model_counts_the_grid_layout(check):
    check()


def test_ncu_output_is_read_in_base_units(check):
    check()


def test_the_scaling_plot_draws_a_csv(check):
    check()


def test_the_integrator_bench_tells_a_stable_run_from_a_blow_up(device, check):
    check()


def test_the_floor_bench_counts_graph_nodes_and_its_update_only_cloth_falls_freely(device, check):
    check()


def test_the_vbd_bench_colours_the_spring_graph(check):
    check()


def test_newtons_vbd_and_implicit_euler_take_the_same_backward_euler_step(device, check):
    check()


def test_the_vbd_bench_reads_cost_at_equal_error_off_the_pareto_front(check):
    check()


def test_the_battery_plot_reads_every_case_of_a_battery_table(check):
    check()


def test_the_cpu_bench_times_two_trees_and_counts_a_plain_cloths_launches(check):
    check()


def test_the_cloth_bench_times_the_default_guard_off_and_newton_on_the_cpu(check):
    check()


def test_every_check_of_the_smoke_script_is_a_test_here(smoke):
    """No check of ``bench/smoke.py`` goes unreported: each is a test of this module."""
    tests = {name.removeprefix("test_") for name in globals() if name.startswith("test_")}
    assert {name for name, _, _ in smoke} <= tests
