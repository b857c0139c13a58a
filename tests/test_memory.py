"""Memory estimates (``warpspring.core.memory``) against what is really allocated, and the refusal of models that
do not fit.

The model's arrays and the run's buffers are counted by walking the objects for every Warp array that owns
its memory; the host peak is the growth of the process's peak resident memory (``VmHWM``, reset after the
imports) while a cloth grid is built and finalized, in a fresh process. Run as a script, this file prints that comparison for larger grids,
and for a run's own peak after finalize (three frames to USD):

    python tests/test_memory.py 256 512 1024
    python tests/test_memory.py --run 512 symplectic_euler rk4 implicit_euler

(measured on the CPU: model arrays exact to the byte; the finalize peak within +2.6 % … +5.6 % at 256², 512²,
1024², springs gathered and laid out by group; a run's within -7 % … +11 %).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import warp as wp

import warpspring as ws
from warpspring.core import memory
from warpspring.core.constraints import StepFinisher
from warpspring.core.memory import MODEL_TOLERANCE, PEAK_TOLERANCE, AvailableMemory, format_bytes

from helpers import warp_allocations

HERE = Path(__file__).resolve()
#: The child processes import this checkout's warpspring (run as a script, tests/ would come first on their
#: path and an installed copy, not this one, would be measured).
CHILD_ENV = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(HERE.parent.parent),
                                                                      os.environ.get("PYTHONPATH")]))}


def owned_bytes(*roots, seen: dict | None = None) -> int:
    """Bytes of every Warp array that owns its memory reachable from ``roots`` through attributes, lists,
    dicts and Warp structs (views, which own nothing, and objects in ``seen`` are skipped; ``seen`` maps id to
    object, keeping them alive so that no id is reused, and is updated: a second call counts only what the
    first did not)."""
    seen = {} if seen is None else seen
    total = 0
    stack = list(roots)
    while stack:
        obj = stack.pop()
        if id(obj) in seen or obj is None or isinstance(obj, (str, bytes, int, float, np.ndarray, type, wp.Device)):
            continue
        if isinstance(obj, (types.ModuleType, types.FunctionType, types.MethodType, wp.Kernel)):
            continue  # code, not data: a kernel reaches its module and Python's (six's lazy modules import on access)
        seen[id(obj)] = obj
        if isinstance(obj, wp.array):
            total += obj.capacity if obj.deleter is not None else 0
        elif isinstance(obj, (list, tuple)):
            stack.extend(obj)
        elif isinstance(obj, dict):
            stack.extend(obj.values())
        elif hasattr(getattr(obj, "_cls", None), "vars"):  # a Warp struct instance
            stack.extend(getattr(obj, name) for name in obj._cls.vars)
        elif hasattr(obj, "__dict__"):
            stack.extend(vars(obj).values())
    return total


def grid_builder(n: int = 24, m: int = 16, **options) -> ws.ModelBuilder:
    builder = ws.ModelBuilder(stabilizers=options.pop("stabilizers", None))
    builder.add_cloth_grid(nx=n, ny=m, spacing=0.02, mass=0.5, pin=["top-left", "top-right"], **options)
    return builder


SCENES = {
    "grid": lambda: grid_builder(),
    "no shear, hinges, colliders": lambda: _with_colliders(grid_builder(shear=False, dihedral=ws.DihedralMaterial(
        ke=1e-3, kd=1e-5))),
    "pin group, moving collider": lambda: _moving(grid_builder()),
    "wind with noise, handles, emitters": lambda: _wind_and_handles(grid_builder()),
    "mesh colliders: cached, winding number, one-sided": lambda: _meshes(grid_builder()),
    "plastic springs": lambda: _plastic(grid_builder()),
    "square-law springs": lambda: _square(grid_builder()),
    "soft body (grid): spring groups wider than the per-spring head": lambda: _lattice(),
}


def _lattice():
    import trimesh

    builder = ws.ModelBuilder()
    builder.add_soft_body(trimesh.creation.icosphere(subdivisions=2, radius=0.1), method="grid", youngs_modulus=1e5,
                          density=1000.0, spacing=0.02)
    return builder


def _meshes(builder):
    import trimesh

    builder.add_collider_mesh(trimesh.creation.icosphere(subdivisions=1), center=(0.0, 0.0, -1.0))
    builder.add_collider_mesh(trimesh.creation.box(), center=(3.0, 0.0, -1.0), cache_candidates=8)
    builder.add_collider_mesh(trimesh.creation.box(), center=(6.0, 0.0, -1.0), winding_number=True)
    sheet = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    builder.add_collider_mesh(sheet, faces=[[0, 1, 2], [1, 3, 2]], center=(0.0, 5.0, -1.0), sides="one_sided")
    return builder


def _wind_and_handles(builder):
    builder.add_aerodynamics(wind=(1.0, 0.0, 0.0), noise=0.2)
    builder.add_handle([0, 1, 2], kp=10.0, kd=0.1, max_force=1.0,
                       translation=ws.Track([0.0, 1.0], [[0, 0, 0], [0.1, 0, 0]]))
    builder.add_handle([3, 4], kp=5.0, rotation=ws.Track.rotation([0.0, 1.0], axis=(0, 0, 1), degrees=[0, 45]))
    builder.add_emitter(center=(0.0, 0.0, 1.0), rate=50.0, bursts=[(0.5, 10)], life=0.4)
    builder.add_emitter(shape="mesh", mesh=(np.eye(3), [[0, 1, 2]]), rate=20.0, life=0.5, name="sheet")
    return builder


def _with_colliders(builder):
    builder.add_ground_plane()
    builder.add_collider_sphere(center=(0.0, 0.0, -0.5), radius=0.2)
    return builder


def _moving(builder):
    builder.add_pin_group([0, 1, 2], translation=ws.Track([0.0, 1.0], [[0, 0, 0], [0.1, 0, 0]]))
    builder.add_collider_box(center=(0, 0, -1), half_extents=(0.2, 0.2, 0.2),
                             rotation=ws.Track.rotation([0.0, 1.0], axis=(0, 0, 1), degrees=[0, 90]))
    return builder


# -- the estimate against what is allocated ------------------------------------------------------------------


@pytest.mark.parametrize("scene", list(SCENES))
@pytest.mark.parametrize("precision, worlds", [("float32", 1), ("float64", 3)])
def test_model_arrays_match_the_estimate(scene, precision, worlds):
    """Every array of the model is counted: the estimate equals their bytes but for the keyframe tracks' few
    bytes per key (a few hundred bytes here, far inside MODEL_TOLERANCE); and with the mesh colliders' native
    memory (boxes, BVHs, winding-number tables, measured by Warp's allocation tracker) it bounds all that finalize
    leaves allocated, within their descriptors (NATIVE_DESCRIPTOR_BYTES per mesh and BVH)."""
    builder = SCENES[scene]()
    estimate = builder.estimate_memory("cpu", precision=precision, worlds=worlds)
    native = sum(memory.mesh_native_bytes(len(s.mesh.faces), winding_number=s.mesh.winding_number, cuda=False)
                 for s in builder._shapes if getattr(s, "mesh", None) is not None)
    with warp_allocations("cpu") as allocated:
        model = builder.finalize("cpu", precision=precision, worlds=worlds)
    actual = owned_bytes(model)
    assert estimate.model - native == pytest.approx(actual, rel=MODEL_TOLERANCE)
    assert actual - 1024 <= estimate.model - native <= actual  # tracks: under 1 KiB, never over-counted
    meshes = len(builder._shapes) if native else 0
    assert allocated["live"] - 1024 <= estimate.model <= allocated["live"] + 2 * memory.NATIVE_DESCRIPTOR_BYTES * meshes


@pytest.mark.parametrize("integrator", sorted(ws.INTEGRATORS))
def test_run_buffers_match_the_estimate(integrator):
    """The states a Stepper holds, each integrator's scratch (INTEGRATOR_SCRATCH, read from its __init__),
    strain limiting's buffers and the contact stage's slots: byte for byte."""
    builder = _moving(grid_builder(stabilizers=ws.Stabilizers(max_strain=0.1)))
    estimate = builder.estimate_memory("cpu", precision="float64", worlds=2, integrator=integrator)
    model = builder.finalize("cpu", precision="float64", worlds=2, integrator=integrator)
    seen: dict = {}
    owned_bytes(model, seen=seen)
    assert owned_bytes(model.state(), model.state(), seen=seen) == estimate.states
    assert owned_bytes(ws.make_integrator(integrator, model), seen=seen) == estimate.integrator
    finish = StepFinisher(model)
    finish._strain_buffers()  # made at the first step that limits strain
    assert finish.contacts is not None  # the contact stage (a moving collider), made at its first use
    assert owned_bytes(finish, seen=seen) == estimate.post_step


def _dragged(builder):
    builder.drag = 0.1
    return builder


def _windy(builder):
    builder.drag = 0.1  # drag in wind: the power sums carry the wind's push as work
    builder.add_aerodynamics(wind=(1.0, 0.0, 0.0))
    return builder


def _handled(builder):
    builder.add_handle([0, 1, 2], kp=10.0, kd=0.1)
    return builder


def _plastic(builder):
    builder.add_springs([[0, 30], [1, 31]], stiffness=10.0, damping=0.01, family="plastic", plasticity=ws.SpringPlasticity(yield_strain=0.1))
    return builder


def _self_colliding(builder):
    builder.add_self_collision(thickness=0.004)
    return builder


def _square(builder):
    builder.add_springs([[0, 30], [1, 31]], stiffness=10.0, family="square", law="square")
    return builder


#: Scenes that take the guard down each of its paths (``memory.guard_path``): plain springs, drag, drag in wind,
#: handles' work, a collider (no dissipation counted), plastic springs, the force clamps (no dampers in the
#: scattered pass, no power sums in the force pass) and self-collision (the count of its pass's energy).
GUARD_SCENES = {
    "springs": lambda: grid_builder(8, 6),
    "drag": lambda: _dragged(grid_builder(8, 6)),
    "drag in wind": lambda: _windy(grid_builder(8, 6)),
    "handles": lambda: _handled(grid_builder(8, 6)),
    "collider": lambda: _with_colliders(_dragged(grid_builder(8, 6))),
    "plastic springs": lambda: _plastic(_dragged(grid_builder(8, 6))),
    "force clamps": lambda: _dragged(grid_builder(8, 6, stabilizers=ws.Stabilizers(max_spring_force=100.0,
                                                                                   max_particle_force=100.0))),
    "self-collision": lambda: _self_colliding(grid_builder(8, 6)),
}


@pytest.mark.parametrize("scene", list(GUARD_SCENES))
@pytest.mark.parametrize("evaluation", ["gather", "scatter"])
@pytest.mark.parametrize("integrator", sorted(ws.INTEGRATORS))
def test_guard_buffers_match_the_estimate(integrator, evaluation, scene):
    """What the guard and the integrator hold after a frame of the default simulator, byte for byte: the guard's
    fixed buffers and what it makes for the path the run takes (a substep's midpoint state, the scattered springs'
    damper sums, the power sums the integrator's force pass adds to, the force parts symplectic Euler's scattered
    update stores), with the integrator's scratch, for every integrator, both spring evaluations and each scene of
    GUARD_SCENES."""
    builder = GUARD_SCENES[scene]()
    estimate = builder.estimate_memory("cpu", worlds=2, spring_evaluation=evaluation, integrator=integrator)
    model = builder.finalize("cpu", worlds=2, spring_evaluation=evaluation, integrator=integrator)
    seen: dict = {}
    owned_bytes(model, seen=seen)
    sim = ws.Simulator(model, fps=60, substeps=20, integrator=ws.make_integrator(integrator, model))
    try:
        sim.step_frame()
    except ws.SimulationError:
        pass  # a stopped frame has made its buffers all the same
    stepper = sim.stepper  # the states and control the guard refers to are not its own
    owned_bytes(stepper.state, stepper._scratch, stepper.control, seen=seen)
    # The integrator holds the guard's damper and power sums while the guard hands them over: counted once, together.
    assert owned_bytes(stepper.integrator, sim.guard, seen=seen) == estimate.guard + estimate.integrator


def test_guard_rules_follow_the_guard():
    """memory.GUARD_RULES reads the guard's integrator lists and the integrators' own flags."""
    from warpspring.core.guard_records import DISSIPATION_UNCOUNTED, MIDPOINT_DISSIPATION, WORK_UNCOUNTED
    from warpspring.kernels.guards import DAMPERS_IN_FORCE_PASS

    assert set(memory.GUARD_RULES) == set(ws.INTEGRATORS)
    model = grid_builder(4, 4).finalize("cpu")
    for name, (dissipation, midpoint, work, dampers, power) in memory.GUARD_RULES.items():
        integrator = ws.make_integrator(name, model)
        off = getattr(integrator, "adaptive", False) or getattr(integrator, "unconditionally_stable", False)
        assert dissipation == (not off and name not in DISSIPATION_UNCOUNTED)
        assert midpoint == (dissipation and name in MIDPOINT_DISSIPATION)
        assert work == (not off and name not in WORK_UNCOUNTED)
        assert dampers == (dissipation and name in DAMPERS_IN_FORCE_PASS)
        assert power == {"symplectic_euler": "mean", "rk4": "start"}.get(name, "")


def test_the_substep_audit_is_estimated():
    """A run that audits every substep: the record of every substep's positions on the device, byte for byte, in the
    estimate's device bytes; its host part (the record read back as float64, the surface's pair lists) in the host
    peak."""
    from warpspring.analysis.audit import SubstepAudit

    builder = grid_builder()
    plain = builder.estimate_memory("cpu", worlds=2)
    estimate = builder.estimate_memory("cpu", worlds=2, audit_substeps=8)
    model = builder.finalize("cpu", worlds=2)
    sim = ws.Simulator(model, fps=60, substeps=8)
    seen: dict = {}
    owned_bytes(model, sim, seen=seen)
    audit = SubstepAudit().attach(sim)
    assert owned_bytes(audit, seen=seen) == estimate.audit == 9 * 2 * model.particle_count * 12
    assert estimate.device_bytes == plain.device_bytes + estimate.audit
    assert "substep audit" in estimate.parts()
    record, host = memory.audit_bytes(particles=model.particle_count, worlds=2, substeps=8,
                                      surface_vertices=model.particle_count, thickness=False)
    assert estimate.audit_host == host == 9 * 2 * model.particle_count * 24 + memory.AUDIT_MOTION_PER_VERTEX * 384
    thick = builder.estimate_memory("cpu", worlds=2, audit_substeps=8, audit_thickness=True)
    assert thick.audit_host == host + memory.AUDIT_NEAR_PER_VERTEX * 384
    assert estimate.host_bytes == max(estimate.finalize_host + estimate.model, estimate.audit_host
                                      + estimate.device_bytes)


def test_a_substep_audit_that_cannot_fit_is_refused_before_it_is_made(monkeypatch):
    """The audit's record and pair lists checked before anything is made: one line with the estimate and a remedy,
    the simulator left as it was."""
    from warpspring.analysis.audit import SubstepAudit

    model = grid_builder().finalize("cpu")
    sim = ws.Simulator(model, fps=60, substeps=1000)
    hooks = list(sim.stepper.hooks)
    record, host = memory.audit_bytes(particles=model.particle_count, worlds=1, substeps=1000,
                                      surface_vertices=model.particle_count, thickness=False)
    monkeypatch.setattr(memory, "available_memory", lambda device=None: AvailableMemory(host=host))
    with pytest.raises(ws.ConfigError) as refused:
        SubstepAudit().attach(sim)
    line = str(refused.value)
    assert "\n" not in line and "auditing every substep" in line and format_bytes(host + record) in line
    assert "fewer substeps" in line and sim.stepper.hooks == hooks
    monkeypatch.setattr(memory, "available_memory", lambda device=None: AvailableMemory(host=host + record))
    SubstepAudit().attach(sim)


def test_counts_alone_give_the_builders_estimate():
    """``ws.estimate_memory`` from counts equals the builder's exact one for a grid (a uniform degree: the mean
    degree rounded up is the incidence table's width), and every integrator has its scratch listed."""
    builder = grid_builder(40, 30)
    exact = builder.estimate_memory("cpu", integrator="rk4")
    counted = ws.estimate_memory(particles=1200, springs=builder.spring_count, triangles=2 * 39 * 29,
                                 integrator="rk4")
    assert counted == exact
    assert set(memory.INTEGRATOR_SCRATCH) == set(ws.INTEGRATORS)
    assert counted.device_bytes == (counted.model + counted.states + counted.integrator + counted.guard + counted.writer
                                    + max(counted.warmup, counted.setup))
    assert counted.setup == 8 * builder.spring_count  # the springs' energies in float64, the largest family's
    assert "model" in counted.describe() and "states" in counted.describe()
    with pytest.raises(ws.ConfigError, match="unknown integrator"):
        ws.estimate_memory(particles=10, integrator="leapfrog")


def _measure(n: int) -> dict:
    """In this (fresh) process: build and finalize an n × n grid on the CPU; its model's bytes, the estimate and
    the growth of the peak resident memory."""
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    # The peak from here on: the high-water mark is reset (Linux), and the growth counted from the resident
    # memory now (the imports' own transient peak must not hide part of the build's).
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    base = _status_bytes("VmRSS")
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=n, ny=n, spacing=1.0 / n, mass=1.0, pin=["top-left"])
    estimate = builder.estimate_memory("cpu")
    model = builder.finalize("cpu")
    peak = _status_bytes("VmHWM") - base
    return dict(n=n, particles=model.particle_count, springs=model.spring_count, model=owned_bytes(model),
                model_estimate=estimate.model, peak=peak, peak_estimate=estimate.finalize_peak)


def _status_bytes(key: str) -> int:
    """A memory figure of this process from /proc/self/status [B] (VmRSS: resident now; VmHWM: its peak)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    raise KeyError(key)


def measure(n: int) -> dict:
    """:func:`_measure` in a fresh Python process (a peak is per process)."""
    done = subprocess.run([sys.executable, str(HERE), "--measure", str(n)], capture_output=True, text=True, env=CHILD_ENV,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.splitlines()[-1])


@pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(), reason="needs Linux's /proc peak-memory reset")
def test_peak_memory_of_finalize_is_within_tolerance():
    """The peak resident memory of building and finalizing a 256² cloth on the CPU (~100 MiB above the
    interpreter's) is the estimate's within PEAK_TOLERANCE; the model's arrays are exact."""
    result = measure(256)
    assert result["model_estimate"] == result["model"]
    assert result["peak_estimate"] == pytest.approx(result["peak"], rel=PEAK_TOLERANCE)


# -- refusing what does not fit ---------------------------------------------------------------------------


def test_finalize_refuses_a_model_that_does_not_fit(monkeypatch):
    """With half the host memory the estimate needs, finalize refuses before allocating: one message with the
    estimate, what is available and a remedy; ``check_memory=False`` goes ahead."""
    builder = grid_builder()
    estimate = builder.estimate_memory("cpu", precision="float64", worlds=4)
    available = AvailableMemory(host=estimate.host_bytes // 2)
    monkeypatch.setattr(memory, "available_memory", lambda device: available)
    with pytest.raises(ws.ConfigError) as caught:
        builder.finalize("cpu", precision="float64", worlds=4)
    message = str(caught.value)
    assert "does not fit in memory" in message and "\n" not in message
    assert format_bytes(estimate.host_bytes) in message and format_bytes(available.host) in message
    assert "smaller cloth" in message and "float32" in message and "fewer worlds" in message
    assert builder.finalize("cpu", precision="float64", worlds=4, check_memory=False).world_count == 4


def test_a_gpu_model_is_checked_against_the_devices_free_memory():
    """On a CUDA device the arrays are compared with the device's free memory, the host's peak with the host."""
    estimate = ws.estimate_memory(particles=4_000_000, springs=24_000_000, triangles=8_000_000, device="cuda:0")
    plenty = 64 * 2**30
    memory.check_fits(estimate, AvailableMemory(host=plenty, device=plenty, device_total=plenty))
    with pytest.raises(ws.ConfigError, match=r"on cuda:0 .* but 1 GiB of 80 GiB is free.*a 1\d\d\d × 1\d\d\d grid"):
        memory.check_fits(estimate, AvailableMemory(host=plenty, device=2**30, device_total=80 * 2**30))
    with pytest.raises(ws.ConfigError, match="of host memory at its peak"):
        memory.check_fits(estimate, AvailableMemory(host=2**30, device=plenty))
    memory.check_fits(estimate, AvailableMemory(host=None, device=None))  # unknown: not checked


def test_a_failed_allocation_becomes_a_config_error(monkeypatch):
    """Warp's "Failed to allocate" RuntimeError during finalize becomes a ConfigError with the estimate; any
    other RuntimeError passes through."""
    builder = grid_builder()

    def failing(*args, **kwargs):
        raise RuntimeError("Failed to allocate 123456 bytes on device 'cuda:0'")

    monkeypatch.setattr(ws.ModelBuilder, "_finalize", failing)
    with pytest.raises(ws.ConfigError, match=r"out of memory while finalizing .*Failed to allocate.* smaller cloth"):
        builder.finalize("cpu")

    def broken(*args, **kwargs):
        raise RuntimeError("something else")

    monkeypatch.setattr(ws.ModelBuilder, "_finalize", broken)
    with pytest.raises(RuntimeError, match="something else"):
        builder.finalize("cpu")


def test_a_grid_too_large_to_build_is_refused_before_its_arrays(monkeypatch):
    """A 5000 × 5000 grid on a machine with 1 GiB free: refused at once, naming a grid that fits; nothing added."""
    monkeypatch.setattr(memory, "available_memory", lambda device: AvailableMemory(host=2**30))
    builder = ws.ModelBuilder()
    with pytest.raises(ws.ConfigError, match=r"a 5000 × 5000 cloth grid needs an estimated .* GiB .*about \d+ × \d+ "
                                             r"fits"):
        builder.add_cloth_grid(nx=5000, ny=5000, spacing=0.01, mass=1.0)
    assert builder.particle_count == 0


def test_the_cli_refuses_a_scene_that_does_not_fit(tmp_path, capsys, monkeypatch):
    """`warpspring run` on a machine with too little memory: exit 2, one line with the estimate, no file."""
    from helpers import write_scene

    from warpspring.app.cli import EXIT_CONFIG, main

    from warpspring.io.scene import load_scene

    scene = write_scene(tmp_path)
    estimate = load_scene(str(scene)).builder().estimate_memory("cpu")
    monkeypatch.setattr(memory, "available_memory", lambda device: AvailableMemory(host=1000))
    out = tmp_path / "out.usdc"
    assert main(["run", str(scene), "-o", str(out), "--device", "cpu"]) == EXIT_CONFIG
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("warpspring: error: scene.toml: in [cloth]: a 5 × 5 cloth grid ")
    assert "needs an estimated" in lines[0] and "but 1000 B is available" in lines[0]
    assert not out.exists()

    # With room to build the cloth but not to finalize it, finalize refuses.
    # (the builder's checks ask for the host's memory alone, device None; finalize asks with its device)
    room = AvailableMemory(host=estimate.host_bytes - 1)
    monkeypatch.setattr(memory, "available_memory",
                        lambda device: AvailableMemory(host=2**40) if device is None else room)
    assert main(["run", str(scene), "-o", str(out), "--device", "cpu"]) == EXIT_CONFIG
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and "does not fit in memory" in lines[0] and format_bytes(room.host) in lines[0]
    assert not out.exists()


def test_host_memory_is_known_here():
    """The available host memory is a positive number of bytes (Linux: MemAvailable, within any cgroup limit)."""
    available = memory.host_available_memory()
    assert available is None or available > 0
    if sys.platform.startswith("linux"):
        assert available is not None
    assert memory.available_memory(wp.get_device("cpu")).device is None


def _measure_run(n: int, integrator: str, folder: str) -> dict:
    """In this (fresh) process: the growth of the peak resident memory of a run of an n × n hanging cloth (three
    frames written to USD, the advisor's check before) after its model is finalized, against the estimate's run
    part (the run's buffers and the larger of a frame's and the setup's host memory). The kernels, USD and the
    advisor are loaded on a small cloth first: their code is not the run's data."""
    import ctypes
    import gc

    from warpspring.app.runner import preflight
    from warpspring.io.usd import UsdWriter

    wp.config.log_level = wp.LOG_WARNING

    def scene(size):
        builder = ws.ModelBuilder(drag=0.002)
        builder.add_cloth_grid(nx=size, ny=size, spacing=1.0 / size, origin=(0, 0, 1), particle_mass=0.01,
                               pin=["top-left", "top-right"], structural=ws.SpringMaterial(40.0, 0.01),
                               shear=ws.SpringMaterial(10.0, 0.01), bend=ws.SpringMaterial(1.0, 0.001))
        builder.add_ground_plane()
        return builder

    def run(model, path):
        sim = ws.Simulator(model, integrator=ws.make_integrator(integrator, model), fps=60, substeps=4)
        preflight(model, integrator, sim.dt, fps=60)
        with UsdWriter(path, model, fps=60) as usd:
            usd.write_frame(sim.state)
            for _ in range(3):
                sim.step_frame()
                usd.write_frame(sim.state)

    run(scene(16).finalize("cpu"), f"{folder}/warm.usdc")
    builder = scene(n)
    estimate = builder.estimate_memory("cpu", integrator=integrator)
    model = builder.finalize("cpu", integrator=integrator)
    del builder
    gc.collect()
    ctypes.CDLL("libc.so.6").malloc_trim(0)
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    base = _status_bytes("VmRSS")
    run(model, f"{folder}/run.usdc")
    return dict(n=n, integrator=integrator, peak=_status_bytes("VmHWM") - base,
                peak_estimate=estimate.device_bytes - estimate.model + max(estimate.frame_host, estimate.run_host))


if __name__ == "__main__":
    if sys.argv[1:2] == ["--measure"]:
        print(json.dumps(_measure(int(sys.argv[2]))))
        sys.exit(0)
    if sys.argv[1:2] == ["--run"]:  # python tests/test_memory.py --run 512 [integrator ...]
        import tempfile

        print("| grid | integrator | run's peak RSS growth | estimate | error |")
        print("|---|---|---|---|---|")
        for name in sys.argv[3:] or ["symplectic_euler"]:
            with tempfile.TemporaryDirectory() as folder:
                done = subprocess.run([sys.executable, str(HERE), "--run-one", sys.argv[2], name, folder],
                                      capture_output=True, text=True, timeout=600, env=CHILD_ENV)
            assert done.returncode == 0, done.stderr
            r = json.loads(done.stdout.splitlines()[-1])
            print(f"| {r['n']}² | {name} | {format_bytes(r['peak'])} | {format_bytes(r['peak_estimate'])} | "
                  f"{r['peak_estimate'] / r['peak'] - 1:+.1%} |")
        sys.exit(0)
    if sys.argv[1:2] == ["--run-one"]:
        print(json.dumps(_measure_run(int(sys.argv[2]), sys.argv[3], sys.argv[4])))
        sys.exit(0)
    print("| grid | particles | springs | model arrays | estimate | peak RSS growth | estimate | error |")
    print("|---|---|---|---|---|---|---|---|")
    for size in map(int, sys.argv[1:] or ["256", "512", "1024"]):
        r = measure(size)
        print(f"| {size}² | {r['particles']:,} | {r['springs']:,} | {format_bytes(r['model'])} | "
              f"{format_bytes(r['model_estimate'])} | {format_bytes(r['peak'])} | {format_bytes(r['peak_estimate'])} | "
              f"{r['peak_estimate'] / r['peak'] - 1:+.1%} |")


def test_inside_tests_ask_trimesh_a_chunk_at_a_time(monkeypatch):
    """The soft-body methods' inside tests (``soft_topologies.inside_mesh``) ask trimesh at most INSIDE_CHUNK points a
    call, whose ray tests hold every ray's candidate triangles at once (without embreex a 5 mm voxel sphere's 64k
    centres took 3.5 GB in one call), and answer as the sphere does away from its faceted surface."""
    import trimesh

    from warpspring.core import soft_topologies

    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    rng = np.random.default_rng(3)
    points = rng.uniform(-0.12, 0.12, (3000, 3))
    radius = np.linalg.norm(points, axis=1)
    points = points[(radius < 0.098) | (radius > 0.101)]  # the icosphere lies between 0.0988 and 0.1
    asked = []
    contains = type(mesh).contains
    monkeypatch.setattr(type(mesh), "contains", lambda self, p: asked.append(len(p)) or contains(self, p))
    inside = soft_topologies.inside_mesh(mesh, points)
    assert max(asked) <= soft_topologies.INSIDE_CHUNK and sum(asked) == len(points) and len(asked) > 1
    np.testing.assert_array_equal(inside, np.linalg.norm(points, axis=1) < 0.098)
