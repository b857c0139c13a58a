"""The check's fold (``kernels/guards.py``: ``guard_fold_kernel``): each chunk of a world's per-block partial sums added
(strains by their largest), the substeps' running sums folded and cleared with the sampled power kept, against numpy in
float64."""

import numpy as np
import pytest
import warp as wp

import warpspring as ws
from warpspring.kernels.guards import (
    FOLD_CHUNK,
    FOLD_COLUMNS,
    GUARD_MAX_STRAIN,
    PARTIAL_SLOTS,
    RUNNING_DISSIPATION,
    RUNNING_POWER,
    RUNNING_SLOTS,
    RUNNING_STEP_DISSIPATION,
    RUNNING_WORK,
    guard_fold_kernel,
)
from warpspring.kernels.linalg import reduction_funcs


def test_the_fold_adds_each_chunk_of_partials(device):
    rng = np.random.default_rng(7)
    worlds = 2
    partials = rng.normal(size=(worlds, 2 * FOLD_CHUNK + 5, PARTIAL_SLOTS))
    energy = rng.normal(size=(worlds, 3 * FOLD_CHUNK + 3))
    strain = rng.uniform(-1.0, 2.0, size=energy.shape)
    power = rng.normal(size=energy.shape)
    running = rng.normal(size=(worlds, FOLD_CHUNK + 2, RUNNING_SLOTS))
    chunks = -(-max(partials.shape[1], energy.shape[1], running.shape[1]) // FOLD_CHUNK)
    arrays = [wp.array(a, dtype=wp.float64, device=device) for a in (partials, energy, strain, power, running)]
    folded = [wp.zeros((worlds, chunks, PARTIAL_SLOTS), dtype=wp.float64, device=device)]
    folded += [wp.zeros((worlds, chunks), dtype=wp.float64, device=device) for _ in range(3)]
    folded += [wp.zeros((worlds, chunks, RUNNING_SLOTS), dtype=wp.float64, device=device)]
    wp.launch(guard_fold_kernel(), dim=(worlds, chunks, FOLD_COLUMNS), inputs=arrays[:4], outputs=[arrays[4], *folded],
              device=device)
    got = [f.numpy() for f in folded]

    def each_chunk(a, reduce, empty):
        return np.stack([np.array([reduce(a[w, c * FOLD_CHUNK:(c + 1) * FOLD_CHUNK]) if c * FOLD_CHUNK < a.shape[1]
                                   else empty for c in range(chunks)]) for w in range(worlds)])

    # each chunk's values added in order, as numpy's sum of ≤ 32 values does (pairwise from 8 on): a few ulps apart
    tol = dict(rtol=0.0, atol=1e-13)
    expected = each_chunk(partials, lambda block: block.sum(axis=0), np.zeros(PARTIAL_SLOTS))
    expected[..., GUARD_MAX_STRAIN] = each_chunk(partials[..., GUARD_MAX_STRAIN], np.max, -1.0)
    np.testing.assert_allclose(got[0], expected, **tol)
    np.testing.assert_allclose(got[1], each_chunk(energy, np.sum, 0.0), **tol)
    np.testing.assert_array_equal(got[2], each_chunk(strain, np.max, -1.0))
    np.testing.assert_allclose(got[3], each_chunk(power, np.sum, 0.0), **tol)
    for slot in (RUNNING_DISSIPATION, RUNNING_WORK, RUNNING_STEP_DISSIPATION):
        np.testing.assert_allclose(got[4][..., slot], each_chunk(running[..., slot], np.sum, 0.0), **tol)
    left = arrays[4].numpy()
    np.testing.assert_array_equal(left[..., RUNNING_POWER], running[..., RUNNING_POWER])  # the sampled power kept
    for slot in (RUNNING_DISSIPATION, RUNNING_WORK, RUNNING_STEP_DISSIPATION):
        assert not left[..., slot].any()  # folded and cleared


@pytest.mark.parametrize("integrator", ["symplectic_euler", "rk4", "implicit_euler"])
def test_a_folded_check_is_the_unfolded_one(device, integrator, monkeypatch):
    """A damped cloth with drag, its check's partial sums folded before the gather (forced on this small model) and not:
    the same energy balance and work to float64 rounding of sums taken in another order, frame after frame (on CUDA,
    where a check leaves a partial sum per block; on the CPU a world's one partial sum passes through)."""
    from warpspring.core import guards

    def run(fold: bool):
        monkeypatch.setattr(guards, "FOLD_MIN_BLOCKS", 0 if fold else None)
        builder = ws.ModelBuilder(drag=0.05)
        spring = ws.SpringMaterial(ke=1.0e3, kd=0.1)
        builder.add_cloth_grid(nx=24, ny=24, spacing=0.05, particle_mass=0.02, structural=spring, shear=spring,
                               bend=spring, pin=["top-left", "top-right"])
        model = builder.finalize(device)
        sim = ws.Simulator(model, integrator=ws.make_integrator(integrator, model), fps=60, substeps=24)
        assert (sim.guard._folding() is not None) == fold
        balances = []
        for _ in range(6):
            sim.step_frame()
            b = sim.guard.energy_balance()
            balances.append([b.energy[0], b.reference[0], b.work[0], b.peak[0], b.dissipated[0], sim.guard.work()[0]])
        return np.array(balances), sim.state.particle_q.numpy()

    (folded, x_folded), (gathered, x_gathered) = run(True), run(False)
    assert np.array_equal(x_folded, x_gathered)  # the check changes no state
    if integrator != "implicit_euler":  # (an unconditionally stable step's balance leaves D out)
        assert folded[-1, 4] > 0.0  # the dampers and drag took energy out
    np.testing.assert_allclose(folded, gathered, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("lanes", [1, 32, 96, 256])
def test_block_reductions_give_every_lane_the_blocks_sum_and_largest(device, lanes):
    """``linalg.reduction_funcs``: every lane of a block gets the block's sum and largest value, for blocks of one
    warp, of a number of warps that is no power of two and of eight (exact: integers in float64), twice in a row
    (a call's shared slots reused by the next)."""
    if (lanes > 1) != device.startswith("cuda"):
        pytest.skip("a block is one thread on the CPU, and a whole number of warps on CUDA")
    block_sum, block_max = reduction_funcs(device.startswith("cuda"))

    @wp.kernel(module="unique", enable_backward=False)
    def reduce(values: wp.array2d[wp.float64], sums_out: wp.array2d[wp.float64], maxima_out: wp.array2d[wp.float64]):
        block, lane = wp.tid()
        value = values[block, lane]
        sums_out[block, lane] = block_sum(value)
        maxima_out[block, lane] = block_max(value)
        sums_out[block, lane] += block_sum(wp.float64(2.0) * value)  # again: 3 × the sum

    values = np.random.default_rng(3).integers(-1000, 1000, size=(5, lanes)).astype(np.float64)
    sums = wp.zeros(values.shape, dtype=wp.float64, device=device)
    maxima = wp.zeros(values.shape, dtype=wp.float64, device=device)
    wp.launch(reduce, dim=values.shape, block_dim=lanes, inputs=[wp.array(values, dtype=wp.float64, device=device)],
              outputs=[sums, maxima], device=device)
    np.testing.assert_array_equal(sums.numpy(), np.repeat(3.0 * values.sum(axis=1, keepdims=True), lanes, axis=1))
    np.testing.assert_array_equal(maxima.numpy(), np.repeat(values.max(axis=1, keepdims=True), lanes, axis=1))
