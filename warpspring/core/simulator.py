"""Frame loop: a fixed number of integrator substeps per output frame, captured once as a graph."""

from __future__ import annotations


import warp as wp

from .. import checks
from ..errors import ConfigError, SimulationError
from .guards import Guard, GuardLimits
from .integrators import Integrator, SymplecticEuler
from .model import Control, Model, State


class Simulator:
    """Advances a model by frames of 1/fps seconds, each made of ``substeps`` integrator steps.

    The substeps of a frame are captured once into a graph (a CUDA graph on GPUs, Warp's CPU graph on
    the CPU) and replayed with a single launch per frame, with no host synchronisation between substeps. The current state is always
    :attr:`state` (two buffers alternate inside a frame; an odd substep count ends with a copy back).

    Args:
        model: the model to simulate.
        integrator: the integrator; default :class:`SymplecticEuler`.
        fps: output frames per second [1/s].
        substeps: integrator steps per frame; the step is dt = 1 / (fps · substeps) [s].
        control: time-varying inputs; default ``model.control()``.
        use_graph: capture each frame as a graph (a CUDA graph, or Warp's CPU graph); off runs the same
            launches from Python every frame (for debugging).
        guard: run-time checks (non-finite state, torn springs, runaway energy) made on the device
            every ``guard.every`` substeps; a failure raises :class:`SimulationError` at the end of
            the frame. ``None`` disables them (and the per-frame read of their record).
    """

    def __init__(
        self,
        model: Model,
        *,
        integrator: Integrator | None = None,
        fps: float = 60.0,
        substeps: int = 16,
        control: Control | None = None,
        use_graph: bool = True,
        guard: GuardLimits | None = GuardLimits(),
    ):
        self.model = model
        self.integrator = integrator if integrator is not None else SymplecticEuler(model)
        if self.integrator.model is not model:
            raise ConfigError("the integrator was built for another model: build it with this Simulator's model")
        if control is not None and control.model is not model:
            raise ConfigError("the control was made by another model: use model.control() of this Simulator's model")
        self.fps = checks.positive("fps", fps)
        self.substeps = checks.count("substeps", substeps, minimum=1)
        self.frame_dt = 1.0 / self.fps
        self.dt = self.frame_dt / substeps
        self.control = control if control is not None else model.control()
        self.use_graph = bool(use_graph)
        self.state = model.state()
        self._scratch = model.state()
        self.guard = Guard(model, guard, substeps) if guard is not None else None
        self.frame = 0
        self._graph = None
        self._graph_key = None

    @property
    def time(self) -> float:
        """Simulated time [s] of :attr:`state`."""
        return self.frame * self.frame_dt

    def _simulate(self) -> None:
        """Run one frame's substeps (and guard checks), leaving the result in ``self.state``."""
        guard = self.guard
        if guard is not None:
            guard.reset()
        a, b = self.state, self._scratch
        for substep in range(self.substeps):
            self.integrator.step(a, b, self.control, self.dt)
            a, b = b, a
            if guard is not None and ((substep + 1) % guard.every == 0 or substep + 1 == self.substeps):
                guard.check(a, substep)
        if a is not self.state:
            self.state.assign(a)

    def step_frame(self) -> None:
        """Advance :attr:`state` by one frame.

        Raises:
            SimulationError: a guard check failed during the frame; :attr:`state` is then unusable and
                :attr:`frame` still counts the frames completed before it.
        """
        if self.use_graph:
            key = self.model.force_features(self.control)
            if self._graph is None or key != self._graph_key:
                self._capture()
                self._graph_key = key
            wp.capture_launch(self._graph)
        else:
            self._simulate()
        if self.integrator.adaptive:
            failure = self.integrator.failure()
            if failure is not None:
                raise SimulationError(f"frame {self.frame + 1}: {failure}", frame=self.frame + 1)
        if self.guard is not None:
            report = self.guard.report()
            if report is not None:
                raise SimulationError(
                    f"frame {self.frame + 1}, substep {report.substep + 1} of {self.substeps} "
                    f"(t ≤ {self.time + (report.substep + 1) * self.dt:.4g} s): {report.describe(self.model)}",
                    frame=self.frame + 1,
                    substep=report.substep + 1,
                )
        self.frame += 1

    def _capture(self) -> None:
        # One uncaptured step and guard check on the scratch state compile and load every kernel the
        # frame launches (a capture must not load modules); they leave self.state untouched, and the
        # resets drop what they taught the integrator (e.g. an adaptive step size) and the guard, so
        # replays match the plain loop.
        self.integrator.step(self.state, self._scratch, self.control, self.dt)
        self.integrator.reset()
        if self.guard is not None:
            self.guard.check(self._scratch, 0)
            self.guard.reset()
        with wp.ScopedCapture(device=self.model.device, force_module_load=False) as capture:
            self._simulate()
        self._graph = capture.graph

    def reset(self, state: State | None = None) -> None:
        """Restart at frame 0 from ``state`` (default: the model's initial state), forgetting the
        integrator's history (step-size control, warm starts), so the run repeats exactly."""
        self.state.assign(state if state is not None else self.model.state())
        self.integrator.reset()
        self.frame = 0
