"""A check's particle passes in one launch (``kernels/guards.py``: ``guard_check_kernel``, CUDA's default) and the
springs' energy walked by particles (``guard_energy_kernel``'s ``walk``, the springs' gathered ``particle_energy`` hook)
against the passes apart and the springs' energy walked by springs (the CPU's default): each spring at the lower of
its two ends, so the energy, the drives' work, the dampers' power at the check and the energy balance agree to float64
rounding of sums taken in another order, and the largest strain to the bit, frame after frame."""

import numpy as np
import pytest

import warpspring as ws
from helpers import driven_cloth


def grid_cloth(device, worlds: int = 2, clamp: float | None = None):
    """A damped 12 × 12 grid cloth in drag (the grouped grid layout: each group's values read once); with two worlds the
    second world's springs stiffer (the groups then read per spring); with ``clamp`` its springs' force clamped there
    [N] (the clamp law: no damper counted)."""
    stabilizers = ws.Stabilizers(max_spring_force=clamp) if clamp is not None else None
    builder = ws.ModelBuilder(drag=0.05, stabilizers=stabilizers)
    spring = ws.SpringMaterial(ke=1.0e3, kd=0.1)
    builder.add_cloth_grid(nx=12, ny=12, spacing=0.05, particle_mass=0.02, structural=spring, shear=spring,
                           bend=spring, pin=["top-left", "top-right"])
    model = builder.finalize(device, worlds=worlds)
    if worlds == 2:
        ke = model.world_values("spring_stiffness")[0]
        model.set_world_values("spring_stiffness", np.stack([ke, 1.5 * ke]))
    return model


def mesh_cloth(device, plastic: bool = False):
    """A jittered triangle mesh (no grid: gathered by its incidence table) with a hub joined to 12 particles (more than
    the head's slots: a tail), its springs plastic where asked."""
    rng = np.random.default_rng(5)
    n = 9
    u, v = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float))
    vertices = np.stack([u.ravel() * 0.05, np.zeros(n * n), -v.ravel() * 0.05], axis=1)
    vertices[:, [0, 2]] += rng.uniform(-0.01, 0.01, size=(n * n, 2))
    faces = []
    for r in range(n - 1):
        for c in range(n - 1):
            a, b, d, e = r * n + c, r * n + c + 1, (r + 1) * n + c, (r + 1) * n + c + 1
            faces += [[a, b, d], [b, e, d]]
    builder = ws.ModelBuilder(drag=0.02)
    builder.add_cloth_mesh(vertices, np.array(faces), mass=0.3, pin=[0, n - 1],
                           structural=ws.SpringMaterial(ke=800.0, kd=0.2), bend=ws.SpringMaterial(ke=20.0, kd=0.01))
    hub = 4 * n + 4
    others = [k for k in rng.choice(n * n, size=13, replace=False) if k != hub][:12]
    plasticity = ws.SpringPlasticity(yield_strain=0.002, hardening=0.5) if plastic else None
    builder.add_springs([[hub, k] for k in others], stiffness=300.0, damping=0.05, plasticity=plasticity)
    return builder.finalize(device)


SCENES = {"grid": lambda device: grid_cloth(device, worlds=1), "grid, two worlds": grid_cloth,
          "mesh with a tail": mesh_cloth, "mesh, plastic": lambda device: mesh_cloth(device, plastic=True),
          "driven pins": lambda device: driven_cloth(device, n=10),
          "grid, force clamp": lambda device: grid_cloth(device, worlds=1, clamp=0.05)}
#: (the particle passes in one launch, the springs' energy walked by particles)
MODES = [(True, True), (True, False), (False, True)]


@pytest.mark.parametrize("integrator", ["symplectic_euler", "rk4"])
@pytest.mark.parametrize("scene", list(SCENES))
def test_the_fused_and_walked_check_is_the_check_apart(device, scene, integrator, monkeypatch):
    from warpspring.kernels import guards

    cuda = device.startswith("cuda")

    def run(fused: bool, walk: bool):
        monkeypatch.setitem(guards.CHECK_FUSED, cuda, fused)
        monkeypatch.setitem(guards.ENERGY_BY_PARTICLES, cuda, walk)
        model = SCENES[scene](device)
        sim = ws.Simulator(model, integrator=ws.make_integrator(integrator, model), fps=60, substeps=20)
        assert sim.guard._walks(model.families[0]) == walk
        assert (sim.guard._fused_walk() is not False) == fused
        rows, values = [], []
        for _ in range(8):
            sim.step_frame()
            sim.settle()
            b = sim.guard.energy_balance()
            rows.append(np.stack([b.energy, b.reference, b.work, b.peak, b.dissipated, sim.guard.work()]))
            values.append(sim.guard._values.numpy().copy())
        return np.array(rows), np.array(values), sim.state.particle_q.numpy()

    reference, reference_values, x = run(False, False)
    assert reference[-1, 0].min() > 0.0 and reference[-1, 4].min() > 0.0  # energy held, the dampers took some out
    if scene == "driven pins":
        assert np.abs(reference[-1, 2]).min() > 0.0  # the drives did work
    for fused, walk in MODES:
        rows, values, x_mode = run(fused, walk)
        assert np.array_equal(x_mode, x)  # the check changes no state
        np.testing.assert_allclose(rows, reference, rtol=1e-12, atol=1e-15, err_msg=f"fused {fused}, walk {walk}")
        np.testing.assert_array_equal(values, reference_values)  # the largest strain and the rest of the record
