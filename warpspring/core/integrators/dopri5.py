"""Adaptive Dormand-Prince 5(4): an embedded Runge-Kutta pair that chooses its own step, on the device.

``step(state_in, state_out, control, dt)`` advances by ``dt`` in as many internal steps as the error
tolerance needs. Each internal step computes the 5th-order solution and the embedded 4th-order one;
their difference estimates the local error, scaled per component by atol + rtol·|y| (both equal to
``tolerance``) and max-reduced over particles. A step with scaled error ≤ 1 is accepted; the next step
is h·min(5, max(0.2, 0.9·err^(-1/5))) (no growth right after a rejection), cut short to land on ``dt``.

The controller lives on the device (``kernels/integrators.step_control_kernels``), one per world: each
world chooses its own steps and rejections from its own error (a world that reached the end of the
interval waits, untouched, while the others finish). The internal steps run inside ``wp.capture_while``
until every world is done: no host synchronisation, so frames of adaptive steps capture into graphs like
every other integrator. The tolerance and the step budget live in the controller's
device array too: changing them between frames changes no captured launch.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ... import checks
from ...kernels.integrators import (
    STEP_ACCEPTED,
    STEP_CONTROL_SLOTS,
    STEP_COUNTERS,
    STEP_FAILED,
    STEP_MAX_ATTEMPTS,
    STEP_PROPOSED,
    STEP_REJECTED,
    STEP_TOLERANCE,
    rk_error_kernel,
    step_control_kernels,
)
from ...kernels.linalg import reduce_lanes, reduce_launch_dim
from ..forces import eval_forces
from ..model import Model
from ..state import State
from ..control import Control
from .runge_kutta import ExplicitRungeKutta


class DormandPrince(ExplicitRungeKutta):
    """Adaptive Dormand-Prince 5(4) with FSAL (first same as last: 6 force evaluations per accepted step).

    Args:
        model: the model.
        tolerance: local error tolerance per internal step, absolute and relative, on positions [m] and
            velocities [m/s]. In float32 a position of about 1 m resolves only ~6e-8 m, so tolerances
            much below 1e-6 chase round-off (steps shrink, cost grows): use ``precision="float64"``.
        max_steps: most internal steps (accepted or rejected) per call of ``step``; beyond it the step
            stops short and :meth:`failure` says so (the Simulator then raises a SimulationError).
    """

    name = "dopri5"
    order = 5
    adaptive = True
    a = (
        (),
        (1 / 5,),
        (3 / 40, 9 / 40),
        (44 / 45, -56 / 15, 32 / 9),
        (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
        (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656),
        (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84),
    )
    b = (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84, 0.0)
    b_embedded = (5179 / 57600, 0.0, 7571 / 16695, 393 / 640, -92097 / 339200, 187 / 2100, 1 / 40)

    def __init__(self, model: Model, *, tolerance: float = 1.0e-6, max_steps: int = 100_000):
        super().__init__(model)
        device = model.device
        self._y = model.state()  # the solution during a step, advanced in place by each accepted step
        worlds = model.world_count
        self._control = wp.zeros((worlds, STEP_CONTROL_SLOTS), dtype=wp.float64, device=device)
        self._counters = wp.zeros((worlds, STEP_COUNTERS), dtype=wp.int32, device=device)
        self._keep_going = wp.zeros(1, dtype=wp.int32, device=device)
        self._tiled = device.is_cuda
        self._lanes = reduce_lanes(model.particle_count, model.block_dim, self._tiled)
        self._error_partials = wp.zeros(reduce_launch_dim(worlds, model.particle_count, self._lanes)[:2],
                                        dtype=wp.float64, device=device)
        self._error_weights = wp.types.vector(length=7, dtype=model.scalar)(*np.subtract(self.b, self.b_embedded))
        self._step_size = wp.zeros(worlds, dtype=wp.float64, device=device)  # each world's step in use [s]
        self.tolerance = tolerance
        self.max_steps = max_steps

    @property
    def tolerance(self) -> float:
        """Local error tolerance per internal step (absolute and relative); settable between frames."""
        return self._tolerance

    @tolerance.setter
    def tolerance(self, value: float) -> None:
        self._tolerance = checks.positive("tolerance", value)
        self._write_setting(STEP_TOLERANCE, self._tolerance)

    @property
    def max_steps(self) -> int:
        """Most internal steps (accepted or rejected) per call of ``step``; settable between frames."""
        return self._max_steps

    @max_steps.setter
    def max_steps(self, value: int) -> None:
        self._max_steps = checks.count("max_steps", value, minimum=1)
        self._write_setting(STEP_MAX_ATTEMPTS, float(self._max_steps))

    def _write_setting(self, slot: int, value: float) -> None:
        """Write a setting into every world's control row (one host copy of the table)."""
        control = self._control.numpy()
        control[:, slot] = value
        self._control.assign(control)


    @property
    def accepted_steps(self) -> int:
        """Internal steps accepted since construction, in world 0 (reads the device; every world's:
        :meth:`world_steps`)."""
        return int(self._counters.numpy()[0, STEP_ACCEPTED])

    @property
    def rejected_steps(self) -> int:
        """Internal steps rejected since construction, in world 0 (reads the device)."""
        return int(self._counters.numpy()[0, STEP_REJECTED])

    @property
    def step_size(self) -> float:
        """The internal step [s] the controller of world 0 will try next (reads the device)."""
        return float(self._control.numpy()[0, STEP_PROPOSED])

    def world_steps(self) -> dict:
        """Each world's controller since construction (reads the device): "accepted" and "rejected" internal
        steps (int arrays, shape [world_count]), the "step_size" it will try next [s] and whether its last
        interval "failed" (ran out of steps)."""
        counters, control = self._counters.numpy(), self._control.numpy()
        return {"accepted": counters[:, STEP_ACCEPTED].copy(), "rejected": counters[:, STEP_REJECTED].copy(),
                "step_size": control[:, STEP_PROPOSED].copy(), "failed": counters[:, STEP_FAILED] != 0}

    def reset(self) -> None:
        """Forget the step-size history and zero the step counters (the settings stay)."""
        self._control.zero_()
        self._counters.zero_()
        self.tolerance, self.max_steps = self._tolerance, self._max_steps

    def persistent_arrays(self) -> dict[str, wp.array]:
        """Each world's step-size controller: "step_control" (float64, shape [world_count, STEP_CONTROL_SLOTS]:
        the proposed next step [s], the growth cap, the last error and the settings), "step_counters" (int32,
        shape [world_count, STEP_COUNTERS]: accepted, rejected and attempted steps, failure) and "step_size"
        (the step in use [s], float64, shape [world_count])."""
        return {"step_control": self._control, "step_counters": self._counters, "step_size": self._step_size}

    def failure(self) -> str | None:
        """Why the last steps stopped short, or ``None`` (reads the device)."""
        steps = self.world_steps()
        failed = np.flatnonzero(steps["failed"])
        if len(failed) == 0:
            return None
        where = f"in world {failed[0]} " if self.model.world_count > 1 else ""
        if len(failed) > 1:
            where = f"in {len(failed)} worlds (first: world {failed[0]}) "
        return (
            f"dopri5 needed more than {self.max_steps} internal steps for one step {where}(step size now "
            f"{steps['step_size'][failed[0]]:.3g} s): the state is diverging or the tolerance ({self.tolerance:g}) is "
            "too tight; use an implicit integrator or loosen the tolerance"
        )

    def step(self, state_in: State, state_out: State, control: Control | None, dt: float) -> None:
        model = self.model
        begin, decide, commit = step_control_kernels(model.scalar, self._tiled)
        y = self._y
        y.assign(state_in)
        worlds = model.world_count
        self._keep_going.zero_()
        wp.launch(begin, dim=worlds, inputs=[wp.float64(dt), model.world_enabled],
                  outputs=[self._control, self._counters, self._step_size, self._keep_going], device=model.device)
        eval_forces(model, y, control, particle_f=self._stage_f[0])

        def attempt():
            self.eval_stages(y, control, self._step_size, first=False)
            self._measure_error(y)
            wp.launch(decide, dim=(worlds, self._lanes), block_dim=self._lanes, inputs=[self._error_partials],
                      outputs=[self._control, self._counters, self._step_size, self._keep_going], device=model.device)
            # The 5th-order solution is stage 6's state (a₆ = b), its force f(y_new) stage 0's next (FSAL).
            wp.launch(commit, dim=model.particle_dim, block_dim=model.block_dim,
                      inputs=[model.particle_count, self._counters, self._stage_q, self._stage_qd[6], self._stage_time,
                              self._stage_f[6]],
                      outputs=[y.particle_q, y.particle_qd, y.time, self._stage_f[0]], device=model.device)

        wp.capture_while(self._keep_going, attempt)
        state_out.assign(y)
        self.finish_step(state_out, dt, state_in)
        self.hold_worlds(state_in, state_out)


    def _measure_error(self, y: State) -> None:
        model = self.model
        wp.launch(
            rk_error_kernel(model.scalar, 7, self._tiled),
            dim=reduce_launch_dim(model.world_count, model.particle_count, self._lanes),
            block_dim=self._lanes,
            inputs=[
                model.particle_count,
                model.particle_flags,
                model.particle_inv_mass,
                y.particle_qd,
                self._stage_qd,
                self._stage_f,
                self._error_weights,
                self._stage_q,
                self._stage_qd[6],
                self._control,
                self._counters,
            ],
            outputs=[self._error_partials],
            device=model.device,
        )
