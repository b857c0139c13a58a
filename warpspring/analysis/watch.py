"""The stability advisor during a run: a cloth that sags, is pulled or is driven stiffens as its springs
stretch, and a step that was stable at the start may not be at the state the run reaches.

A :class:`StabilityWatch` is a frame hook (:class:`~warpspring.core.simulator.FrameHook`) that the runner,
or any caller, attaches to a simulator: ``StabilityWatch.attach(sim, every=N)``. Every ``every`` frames it
copies the state and runs a few warm-started power iterations on M⁻¹K about it (``kernels/stability.py``,
the advisor's own estimate of ω_max, all worlds in the same launches). On CUDA they run on a stream of their own, off the critical path: the frames go on
while they run, and their result is read at the next re-check, one period later, when it is long done.
On the CPU they run in line and are read at once. A world whose ω_max has reached ``margin`` of the
highest frequency its step keeps stable gets a :class:`~warpspring.errors.StabilityWarning` naming the
frame, the world and the substeps per frame that bring it back under the margin; a world is warned again
only when it needs more.

The highest stable frequency of each world comes from the advisor before the run (given, or run here):
ω_lim = ω_max · dt_stable / dt, exact for undamped modes (their stable step is c / ω) and close for the light damping of cloth (the
damping ratio of the start's top mode is kept). The Rayleigh quotient of a few iterations approaches
λ_max from below; iterations carried from one re-check to the next follow a slowly changing state.
"""

from __future__ import annotations

import contextlib
import math
import warnings

import numpy as np
import warp as wp

from .. import checks
from ..errors import ConfigError, SimulationError, StabilityWarning
from ..kernels.stability import PI_LAMBDA
from ..core.guard_records import GuardReport, stop_advice
from ..core.model import Model
from ..core.simulator import FrameHook, Simulator
from ..core.state import State
from .advisor import Advice, advise
from .omega import PowerIteration, _stiffness_values, free_particles

#: Default frames between re-checks.
WATCH_EVERY = 10
#: Power iterations per re-check (warm-started from the last).
WATCH_ITERATIONS = 20
#: Warn when ω_max reaches this fraction of the highest stable frequency (1: when the state reached is
#: beyond the step's limit; the advisor's own suggestions sit at the limit, so a lower margin would warn on
#: the runs they make).
WATCH_MARGIN = 1.0
#: Residual at which a world stops iterating within a re-check.
WATCH_TOLERANCE = 1.0e-4
#: The multiple of the highest frequency a step keeps stable that a world's ω_max may reach before a watch given
#: ``stop`` stops a guarded run: ``warpspring run``'s default. The guard's balance may not see the growth (off with
#: moving colliders, emitters, the force clamp; one-sided where losses go uncounted) and a position correction
#: (contacts, self-collision's cap, strain limiting, plasticity) may hold it below the tear and runaway limits. 5 % past
#: the limit the top mode grows by 1.9× a step under symplectic Euler and Verlet (ωh = 2.1) and 1.4× under RK4
#: (ωh = 2.97): an instability, not a matter of margin; the power iterations' estimate approaches ω_max from below.
#: In the guard's battery the advisor's steps kept at most 0.79 of the limit, and the injected instabilities reached
#: 1.06-1.15 (a spring 100× stiffer) and 2 (twice the limit) (bench/results/guard_battery_cpu.md).
WATCH_STOP = 1.05
#: The integrators whose stable step is their damping's (no undamped limit): a written model's limits are the advisor's
#: again at the state re-checked, not the start's scaled by ω (a spring made stiffer at the same kd has a smaller
#: damping ratio: thin_colliders' stiffest spring 100× stiffer under explicit Euler read 0.15 of the scaled limit while
#: the advisor found the step 3.2 times past it).
DAMPING_LIMITED = ("explicit_euler", "midpoint")


class StabilityWatch(FrameHook):
    """Re-checks the stability of a running simulation's step at the state it reached (module docstring):
    a frame hook that re-checks after every ``every``-th frame. :meth:`attach` makes one for a simulator
    and adds it to the simulator's frame hooks.

    Args:
        model: the model.
        integrator: the integrator's registry name.
        dt: the step [s].
        fps: frame rate [1/s]; substeps: steps per frame (for the advice).
        state: the state at the start (the advisor's first linearisation).
        control: the run's Control.
        advice: the advisor's verdict on this model, integrator and step, if the caller has one (the CLI's
            pre-run check): its per-world ω_max and stable step give the limits; default: the advisor is
            run here, linearised about ``state``.
        iterations: power iterations per re-check, ≥ 1.
        margin: fraction of the stable limit at which to warn, in (0, 1].
        every: frames between re-checks (≥ 1): it re-checks after the first frame and after the frames that are
            multiples of it.
        stop: a multiple of the stable limit (≥ 1; ``None``, the default: warn only) at which a world's ω_max stops
            a guarded run with a :class:`~warpspring.errors.SimulationError` (``WATCH_STOP``), or with the guard's
            ``stop="world"`` holds the world; read at the frame after the re-check (on the CPU, at once).

    Attributes:
        omega_limit: each world's highest stable angular frequency at ``dt`` [rad/s], float64,
            shape [world_count]; ∞ where the step is stable at any frequency (implicit, adaptive).
        omega: each world's ω_max at the last re-check read [rad/s], float64, shape [world_count] (NaN
            before the first).
        frame: the frame of that re-check (-1 before the first).
        warned: each world's substeps per frame recommended so far (0: none).
        notify: where a warning goes: a callable taking its one-line message, or ``None`` (default) for a
            :class:`~warpspring.errors.StabilityWarning` through :mod:`warnings`.
    """

    def __init__(self, model: Model, integrator: str, dt: float, *, fps: float, substeps: int, state: State,
                 control=None, advice: Advice | None = None, iterations: int = WATCH_ITERATIONS,
                 margin: float = WATCH_MARGIN, every: int = WATCH_EVERY, stop: float | None = None):
        self.every = checks.count("watch", every, minimum=1)
        if stop is not None and not (math.isfinite(stop) and stop >= 1.0):
            raise ConfigError(f"watch stop must be a multiple of the stable limit of at least 1, got {stop!r}")
        self.stop = stop
        self.model = model
        self.integrator = integrator
        self.dt = checks.positive("dt", dt)
        self.fps, self.substeps = fps, substeps
        self.iterations = checks.count("watch iterations", iterations, minimum=1)
        margin = checks.positive("watch margin", margin)
        if margin > 1.0:
            raise ConfigError(f"watch margin must be in (0, 1], got {margin!r}")
        self.margin = margin
        worlds = model.world_count
        self.omega = np.full(worlds, math.nan)
        self.frame = -1
        self.warned = np.zeros(worlds, dtype=np.int64)
        self.notify = None
        self._pending = None  # the frame of the re-check started and not read yet
        self._sim = None  # the simulator whose frames it watches (``after_frame``): its guard decides a stop
        self._control = control
        if advice is None:
            advice = advise(model, integrator, dt, fps=fps, state=state, control=control)
        self._limit(advice)
        # Worlds whose step some frequency can break, and that have free particles to move.
        free = free_particles(model)
        watched = np.isfinite(self.omega_limit) & free.any(axis=1)
        self.active = bool(watched.any())
        if not self.active:
            return
        device = model.device
        self._start = np.random.default_rng(0).normal(size=(model.particle_count, 3))[None] * free[..., None]
        self._watched = wp.array(watched.astype(np.int32), dtype=wp.int32, device=device)
        self._snapshot = wp.empty_like(state.particle_q)
        self._stream = wp.Stream(device) if device.is_cuda else None
        self._done = None
        self._build()

    @classmethod
    def attach(cls, sim: Simulator, *, every: int = WATCH_EVERY, advice: Advice | None = None,
               **options) -> StabilityWatch:
        """A watch of ``sim``'s run from its current state, re-checking after its next frame and every ``every``
        frames from now on, added to its frame hooks (:meth:`~warpspring.core.simulator.Simulator.add_frame_hook`); returns it.
        ``advice``: the advisor's verdict on this run, if the caller already has one (else the watch runs the
        advisor about the current state); ``options``: ``iterations``, ``margin``, ``stop``."""
        return sim.add_frame_hook(cls(sim.model, sim.integrator.name, sim.dt, fps=sim.fps, substeps=sim.substeps,
                                      state=sim.state, control=sim.control, advice=advice, every=every, **options))

    def after_frame(self, sim: Simulator, frame: int) -> None:
        """Read a re-check still pending at the frame after it (on CUDA: its stream has long finished), then
        re-check after the first frame and after the frames that are multiples of :attr:`every` (:meth:`check`): a
        step past its limit from the start is seen at once; with :attr:`stop`, a world past it stops ``sim``'s run
        where it has a guard (:meth:`collect`)."""
        self._sim = sim
        if self._pending is not None:
            if frame == self._pending + 1:
                self.collect()
            else:  # (a reset or a checkpoint's load since: that re-check judged a state of another run)
                self._pending = None
        if frame % self.every == 0 or (self.frame < 0 and self._pending is None):
            self.check(sim.state, frame)

    def _limit(self, advice: Advice) -> None:
        """Each world's highest stable frequency at the step from the advisor's verdict (:attr:`omega_limit`): its linear
        limit, or the larger step its trial runs held at over the run's horizon where the verdict passed the step on
        trial (:attr:`~.advisor.Advice.trial`: an RK4 step past the linear limit at a transient peak)."""
        limits = advice.world_dt_stable
        if advice.trial is not None and advice.trial.passed:  # the run's own states held on trial to its larger step
            limits = np.maximum(limits, max(r.dt for r in advice.trial.runs))
        finite = np.isfinite(limits) & (limits > 0.0) & (not advice.adaptive)
        self.omega_limit = np.where(finite, advice.world_omega_max * np.where(finite, limits, 0.0) / self.dt, math.inf)

    def _build(self) -> None:
        """The iteration's buffers for the model's current values (the last iterate carried over), and no
        graph yet: the next re-check captures one."""
        previous = getattr(self, "_iteration", None)
        start = previous.x.numpy() if previous is not None else self._start
        self._iteration = PowerIteration(self.model, _stiffness_values(self.model, None), start)
        self._graph = None
        self._version = self.model.input_version

    def check(self, state: State, frame: int) -> None:
        """Read the last re-check (warning where due) and start one about ``state`` after ``frame`` (on the
        CPU: run and read it). The re-check's launches are captured once into a graph (a CUDA graph on the
        watch's stream, Warp's CPU graph on the CPU) and replayed; new model values rebuild it."""
        if not self.active:
            return
        self.collect()
        device = self.model.device
        if self._version != self.model.input_version:
            self._build()
            if self.integrator in DAMPING_LIMITED:  # (the limit scales with ω alone only at a kept damping ratio)
                self._limit(advise(self.model, self.integrator, self.dt, fps=self.fps, state=state,
                                   control=self._control))
        wp.copy(self._snapshot, state.particle_q)  # on the frames' stream, after the frame
        if self._stream is not None:
            self._stream.wait_event(wp.get_stream(device).record_event())
        with wp.ScopedStream(self._stream) if self._stream is not None else contextlib.nullcontext():
            if self._graph is None:
                self._launch()  # uncaptured: loads the modules (a capture must not), and is this re-check
                with wp.ScopedCapture(device=device, stream=self._stream, force_module_load=False) as capture:
                    self._launch()
                self._graph = capture.graph
            else:
                wp.capture_launch(self._graph, stream=self._stream)
            if self._stream is not None:
                self._done = self._stream.record_event()
        self._pending = frame
        if self._stream is None:  # in line: the result is there at once
            self.collect()

    def _launch(self) -> None:
        iteration = self._iteration
        iteration.iteration.zero_()
        wp.copy(iteration.active, self._watched)
        iteration.tolerance, iteration.max_iterations = WATCH_TOLERANCE, self.iterations
        for _ in range(self.iterations):
            iteration.iterate(self._snapshot)

    def collect(self) -> None:
        """Read the re-check started last (waiting for it where it still runs) and warn where due; with
        :attr:`stop`, stop or hold the worlds past it (:meth:`_stop`) instead."""
        frame = self._pending
        if frame is None:
            return
        if self._done is not None:
            wp.synchronize_event(self._done)
        self._pending = None
        self.omega = np.sqrt(np.maximum(self._iteration.scalars.numpy()[:, PI_LAMBDA], 0.0))
        self.frame = frame
        ratio = self.omega / self.omega_limit
        sim = self._sim
        stopping = self.stop is not None and sim is not None and sim.guard is not None
        held = set(sim.world_failures) if stopping else set()  # (read once: the property settles the frame)
        over = [int(w) for w in np.flatnonzero(ratio >= self.stop) if int(w) not in held] if stopping else []
        for w in np.flatnonzero(ratio >= self.margin):
            if w in over or int(w) in held:
                continue  # (stopped or held, now or before, with the substeps it needs)
            needed = math.ceil(self.substeps * ratio[w] / self.margin - 1.0e-9)
            if needed <= max(self.warned[w], self.substeps):
                continue
            self.warned[w] = needed
            where = f"world {w}'s" if self.model.world_count > 1 else "the"
            message = (f"frame {frame}: {where} state has stiffened toward the stability limit of {self.integrator}: "
                       f"ω_max ≈ {self.omega[w]:.4g} rad/s is {ratio[w]:.0%} of the {self.omega_limit[w]:.4g} rad/s "
                       f"that dt = {self.dt:.3g} s keeps stable; the run may blow up: use at least {needed} substeps "
                       f"per 1/{self.fps:g} s frame (--substeps {needed}) or implicit_euler")
            if self.notify is not None:
                self.notify(message)
            else:
                warnings.warn(StabilityWarning(message), stacklevel=3)
        if over:
            self._stop(sim, frame, over, ratio)

    def _stop(self, sim: Simulator, frame: int, worlds: list, ratio: np.ndarray) -> None:
        """``worlds``' states at ``frame`` are past ``stop`` times their step's stable limit (``ratio``: each world's
        ω_max over it): with the guard's ``stop="world"`` hold
        them (:meth:`~warpspring.core.simulator.Simulator.hold_world`) and go on while a world runs, else stop the
        run (the message names the scene's suspects and a remedy)."""
        reports = [GuardReport(world=w, reason="stability limit", substep=self.substeps - 1, particle=None,
                               spring=None, strain=math.nan, kinetic_energy=math.nan, stability_ratio=float(ratio[w]))
                   for w in worlds]
        if sim.guard.limits.stop == "world":
            for report in reports:
                sim.hold_world(report, frame)
            if len(sim.world_failures) < self.model.world_count:
                return
        world = max(worlds, key=lambda w: ratio[w])
        report = next(r for r in reports if r.world == world)
        needed = math.ceil(self.substeps * ratio[world] - 1.0e-9)
        where = f"world {world}'s" if self.model.world_count > 1 else "the"
        advice = stop_advice(report, self.model, integrator=self.integrator, substeps=self.substeps, dt=self.dt,
                             control=sim.control)
        terms = sim.guard.balance_terms()
        if not terms.on:
            balance = f"with the guard's energy balance off in this scene ({'; '.join(terms.off)}) no growth is seen"
        elif terms.losses:
            balance = (f"the guard's energy balance, which does not count {', '.join(terms.losses)} here, may see the "
                       "growth late, or never where a position correction holds it")
        else:
            balance = "its growth has not yet shown in the guard's energy balance"
        error = SimulationError(
            f"frame {frame}: {where} state is past the stability limit of {self.integrator}: ω_max ≈ "
            f"{self.omega[world]:.4g} rad/s is {ratio[world]:.2f}× the {self.omega_limit[world]:.4g} rad/s that dt = "
            f"{self.dt:.3g} s keeps stable (the stability watch); {balance}; the advisor's estimate asks for at "
            f"least {needed} substeps per 1/{self.fps:g} s frame; {advice}",
            frame=sim.frame)
        error.reason = "stability limit"
        raise error
