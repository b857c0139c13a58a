"""Frame loop: a fixed number of integrator substeps per output frame, replayed as one graph by the Stepper,
with run-time guards, clear errors and host-side hooks after each frame."""

from __future__ import annotations

import os
import warnings
import weakref
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .. import checks
from ..errors import ConfigError, ContactOverflowWarning, SimulationError, SolverWarning
from .checkpoint import Checkpoint
from .contacts import Contacts
from .emitters import EmitterHook
from .mesh_colliders import advance_mesh_colliders
from .guard_records import GuardLimits, GuardReport
from .guards import Guard
from .integrators import Integrator, SymplecticEuler
from .model import Model
from .state import State
from .control import Control
from .stepper import Stepper


class FrameHook:
    """Host work a :class:`Simulator` runs after every frame it completes, in the order the hooks were added
    (:meth:`Simulator.add_frame_hook`); not captured, so it may read the device. The analyses attach theirs
    (the run-time stability watch: :class:`~warpspring.analysis.watch.StabilityWatch`); device work inside
    the substeps is a :class:`~warpspring.core.stepper.StepHook` instead."""

    def after_frame(self, sim: Simulator, frame: int) -> None:
        """Called at the end of :meth:`Simulator.step_frame`, once ``sim`` has completed frame ``frame``
        (1-based: ``sim.frame``) and :attr:`Simulator.state` holds its end state."""


class Simulator:
    """Advances a model by frames of 1/fps seconds, each made of ``substeps`` integrator steps.

    A :class:`~warpspring.core.stepper.Stepper` captures the substeps of a frame once into a graph (a CUDA
    graph on GPUs, Warp's CPU graph on the CPU) and replays it with a single launch per frame, with no host
    synchronisation between substeps. Live inputs (``model.gravity``, ``model.drag``, stabiliser values,
    keyframe tracks, ``control`` values, pin targets) can change between frames; the replay sees them.
    The current state is always :attr:`state`.

    Args:
        model: the model to simulate.
        integrator: the integrator; default :class:`SymplecticEuler`.
        fps: output frames per second [1/s].
        substeps: integrator steps per frame; the step is dt = 1 / (fps · substeps) [s]. Or a step chooser,
            ``chooser(model, integrator, fps=..., control=...) -> int``, called once before capture:
            :func:`~warpspring.analysis.step_choice.auto_substeps` picks the fewest substeps the stability advisor
            passes with a margin (what scene files and ``warpspring run`` do by default).
        control: time-varying inputs; default ``model.control()``.
        use_graph: capture each frame as a graph (a CUDA graph, or Warp's CPU graph); off runs the same
            launches from Python every frame (for debugging). Both give the same result bit for bit.
        guard: run-time checks (non-finite state, torn springs, runaway energy) made on the device, per
            world, every ``guard.every`` substeps; a failure raises :class:`SimulationError` at the end of
            the frame (with ``defer_verdict``, at the next frame or :meth:`settle`), or with
            ``GuardLimits(stop="world")`` holds the failed world, records it in :attr:`world_failures` and goes on
            with the others. ``None`` disables them (and the per-frame
            read of their record).
        defer_verdict: read each frame's guard record a frame later (``None``, the default, is on; on both devices,
            so that a CPU run stops where the same run on a GPU stops): :meth:`step_frame` queues the next frame
            before it waits for the previous one's record, so the device does not idle while the host reads. A
            failure then raises at the next :meth:`step_frame` or at :meth:`settle` (or on reading :attr:`state`),
            naming its own frame; see :meth:`step_frame`. On an H200 (Warp 1.16.0, bench/results/guard_cost.md) the
            default run went from 0.65 to 0.79 of the guard-off rate at 32² and from 0.59 to 0.74 at 64² with it; on
            the CPU, whose launches return when done, it is what lets a check span frames (``GuardLimits.check_frames``).
            ``False``: every frame is judged before :meth:`step_frame` returns, and checked.

    Attributes:
        world_failures: the worlds stopped by the guard (``stop="world"``) so far: world → (frame, report),
            the frame being the one during which it failed (its last valid frame is the one before).
        frame_hooks: the :class:`FrameHook` objects run after every frame (:meth:`add_frame_hook`), in order.
            The run-time stability check is one: ``StabilityWatch.attach(sim, every=N)``
            (:class:`~warpspring.analysis.watch.StabilityWatch`) re-checks the step at the state reached every
            N frames and warns with a :class:`~warpspring.errors.StabilityWarning` naming the substeps.

    With the contact stage (``Model.contact_stage``), the guard also reads the contact buffer's overflow
    after every frame and warns (:class:`~warpspring.errors.ContactOverflowWarning`) in a frame that dropped
    contacts; :meth:`contact_overflow` counts them per world.

    A run can be saved at any frame and continued later bit for bit: :meth:`save_checkpoint`,
    :meth:`load_checkpoint`.
    """

    def __init__(
        self,
        model: Model,
        *,
        integrator: Integrator | None = None,
        fps: float = 60.0,
        substeps: int | Callable[..., int] = 16,
        control: Control | None = None,
        use_graph: bool = True,
        guard: GuardLimits | None = GuardLimits(),
        defer_verdict: bool | None = None,
    ):
        self.model = model
        self.frame = 0
        self._unsettled = False  # the last frame's record is posted and not yet read (``defer_verdict``)
        self._read = False  # the last frame was settled (read) before the next began
        self._span_from = None  # the first frame the posted check covers (``GuardLimits.check_frames``)
        self._unchecked_from = None  # the first of the frames in a row left to a later check, if the last was one
        self.fps = checks.positive("fps", fps)
        control = control if control is not None else model.control()
        integrator = integrator if integrator is not None else SymplecticEuler(model)
        if callable(substeps):  # a step chooser (analysis.step_choice.auto_substeps): once, before capture
            substeps = substeps(model, integrator, fps=self.fps, control=control)
        elif substeps == "auto":  # the advisor lives above the core: the chooser is passed in
            raise ConfigError('Simulator(substeps="auto"): pass the chooser, substeps=warpspring.auto_substeps')
        self.substeps = checks.count("substeps", substeps, minimum=1)
        self.frame_dt = 1.0 / self.fps
        self.dt = self.frame_dt / self.substeps
        # The guard counts the work of the control's external force (its kinetic-energy limit grows by it).
        self.guard = (Guard(model, guard, self.substeps, control=control, integrator=integrator, dt=self.dt)
                      if guard is not None else None)
        self.stepper = Stepper(
            model,
            integrator,
            dt=self.dt,
            steps=self.substeps,
            control=control,
            # Births and deaths first, so that the guard checks the state the step leaves.
            hooks=([EmitterHook(model, self.dt)] if model.emitters else []) + ([self.guard] if self.guard is not None
                                                                              else []),
            use_graph=use_graph,
        )
        if self.guard is not None:
            self.guard.restart(self.state)  # Δx of the first check from the start state (pins at t = 0)
            # A read of its sums checks a frame left to a later check first (weakly: the guard keeps no simulator alive).
            def before_read(settle=weakref.WeakMethod(self.settle)) -> None:
                method = settle()
                if method is not None:
                    method()

            self.guard.before_read = before_read
        self.frame_hooks: list[FrameHook] = []
        self.defer_verdict = (True if defer_verdict is None else bool(defer_verdict)) and \
            self.guard is not None
        self.frame = 0
        self._world_failures: dict = {}
        self._overflow_seen = np.zeros(model.world_count, dtype=np.int64)

    @property
    def world_failures(self) -> dict:
        """The worlds the guard stopped (``stop="world"``) so far, world → (frame, report); reading it settles the
        last frame (:meth:`settle`)."""
        self.settle()
        return self._world_failures

    @world_failures.setter
    def world_failures(self, failures: dict) -> None:
        self._world_failures = failures

    @property
    def integrator(self) -> Integrator:
        return self.stepper.integrator

    @property
    def control(self) -> Control:
        return self.stepper.control

    @property
    def state(self) -> State:
        """The current state (at :attr:`time`), once the guard passed it: reading it settles the last frame
        (:meth:`settle`; raises :class:`SimulationError` where the guard stopped it)."""
        self.settle()
        return self.stepper.state

    @property
    def contacts(self) -> Contacts | None:
        """The contact buffer the steps fill (the contact stage), or ``None``."""
        return self.integrator.finish_step.contacts

    def contact_overflow(self) -> np.ndarray:
        """Contacts dropped so far because a particle touched more colliders than it has slots, per world,
        int64, shape [world_count] (reads the device; zeros without the contact stage)."""
        contacts = self.contacts
        return contacts.overflow() if contacts is not None else np.zeros(self.model.world_count, dtype=np.int64)

    @property
    def use_graph(self) -> bool:
        return self.stepper.use_graph

    @property
    def time(self) -> float:
        """Simulated time [s] of :attr:`state`."""
        return self.frame * self.frame_dt

    def add_frame_hook(self, hook: FrameHook) -> FrameHook:
        """Run ``hook.after_frame(self, frame)`` after every frame from now on, after the hooks added before
        it; returns ``hook``."""
        self.frame_hooks.append(hook)
        return hook

    def step_frame(self) -> None:
        """Advance :attr:`state` by one frame.

        With :attr:`defer_verdict` (the default) the guard's verdict on a frame is read when the next frame
        is queued: ``step_frame`` raises for a failure of the frame before its own, and :meth:`settle` for the
        last frame's. The promise: whatever was read from a frame whose verdict is known stayed valid; a frame hook
        sees only a state whose verdict is known (the frame is settled before the hooks run), and ``warpspring run``
        writes a frame only once it is settled. Without it every frame is settled before
        ``step_frame`` returns. With it, and frames not read one by one, a check may span frames where the scene allows
        it (``GuardLimits.check_frames``): a frame that leaves its end to a later check is judged with that check, and
        :meth:`settle` checks the last frame first where its end went unchecked. With self-collision, a frame's
        review (``SelfContact.collect_review``: its pair buffers grown where they filled; a stop where pins pressed
        the cloth beyond the cap) is read likewise at the next frame or :meth:`settle` (at once without
        :attr:`defer_verdict` and a guard), so the device does not idle while the host reads it.

        Raises:
            SimulationError: a guard check failed during this frame, or with :attr:`defer_verdict` the one before;
                the message names the frame and substep. :attr:`state` is then unusable and :attr:`frame` counts the
                frames completed before the failed one.
        """
        if self.guard is not None:
            # A check may span frames only where they are not read one by one (a read checks its frame first).
            self.guard.deferred = self.defer_verdict and not self._read
            self.guard.refresh()
        self._read = False
        if self.model.shape_deforming:
            advance_mesh_colliders(self.model, self.time, self.time + self.frame_dt)
        self.stepper.advance()
        if self.guard is not None and self.defer_verdict:
            # The frame before is judged first: its failure, if any, is the earlier one (before this frame's own
            # integrator stops below).
            # This frame's record, read at the next frame (the device keeps busy); none where its end is left to a
            # later check (``GuardLimits.check_frames``: :meth:`settle` checks it first):
            checked = not self.guard.frame_unchecked
            if checked:
                self.guard.post(until=self.time + self.frame_dt)
            if self._unsettled:
                self._judge(self.guard.collect(), self.frame, self._span_from)  # the frame before: raises for it
            self._unsettled = checked
            # The first frame this frame's check (or the later one it is left to) covers.
            first = self._unchecked_from if self._unchecked_from is not None else self.frame + 1
            if checked:
                self._span_from, self._unchecked_from = first, None
            else:
                self._unchecked_from = first
        revision = self.model.revision  # the buffers this frame ran on (the review before may grow them)
        if self.model.self_contact is not None:
            # The frame before's self-collision review (pairs dropped or lists filling: room in the next frames; pins
            # beyond the cap: a stop naming that frame), read while the device runs this one.
            self._collect_review(self.frame)
        if self.integrator.adaptive:
            failure = self.integrator.failure()
            if failure is not None:
                self._forget_verdict()
                raise SimulationError(f"frame {self.frame + 1}: {failure}", frame=self.frame + 1)
        shortfall = self.integrator.solve_shortfall()  # an implicit step's CG stopped at its cap: once, or raise
        if shortfall is not None:
            if self.integrator.strict_solves:
                self._forget_verdict()
                raise SimulationError(f"frame {self.frame + 1}: {shortfall}", frame=self.frame + 1)
            warnings.warn(SolverWarning(f"frame {self.frame + 1}: {shortfall}"), stacklevel=2)
        if self.guard is not None:
            if not self.defer_verdict:
                self._judge(self.guard.reports(), self.frame + 1)
            if self.contacts is not None:
                self._report_overflow()
        if self.model.self_contact is not None:
            self.model.self_contact.post_review(revision)  # this frame's, queued behind it
            if self.guard is not None and not self.defer_verdict:
                self._collect_review(self.frame + 1)  # this frame's at once, as the guard's verdict
        self.frame += 1
        if self.frame_hooks:
            self.settle()
        for hook in self.frame_hooks:
            hook.after_frame(self, self.frame)

    def settle(self) -> None:
        """Wait for the guard's verdict on the last frame (:attr:`defer_verdict`; otherwise nothing to wait for), checking
        it first where a check spanning frames left its end unchecked (``GuardLimits.check_frames``): a state read
        after ``settle`` returns has passed the guard, and the next frames are checked one by one until frames go
        unread again.

        Raises:
            SimulationError: the guard stopped the last frame (see :meth:`step_frame`).
        """
        if self._unsettled:
            self._unsettled = False
            self._judge(self.guard.collect(), self.frame, self._span_from)
        if self.guard is not None and self.guard.catch_up(self.stepper.state):  # its end left to a later check: now
            self.guard.post(until=self.time)
            first, self._unchecked_from = self._unchecked_from, None
            self._judge(self.guard.collect(), self.frame, first)
        if self.model.self_contact is not None:
            self._collect_review(self.frame)  # the last frame's self-collision review (pins beyond the cap stop it)
        self._read = True

    def _judge(self, reports: list, frame: int, first: int | None = None) -> None:
        """Act on the guard's ``reports`` of ``frame`` (1-based): record the held worlds (``stop="world"``; a world
        already held is in the record a frame later again: skipped), or raise for the earliest failure (``first``:
        the first frame the check covered, where it spanned frames: ``GuardLimits.check_frames``; the message says
        so)."""
        if reports and self.guard.limits.stop == "world":
            reports = [report for report in reports if report.world not in self._world_failures]
            for report in reports:
                self._world_failures[report.world] = (frame, report)
            if len(self._world_failures) < self.model.world_count:
                reports = []
        if reports:
            report = min(reports, key=lambda r: (r.substep, r.world))
            self.frame = frame - 1
            self._unsettled = False
            self.guard.discard()
            spanned = (f" (its check spanned frames {first}-{frame}: the failure may have begun in any of them)"
                       if first is not None and first < frame else "")
            error = SimulationError(
                f"frame {frame}{spanned}, substep {report.substep + 1} of {self.substeps} "
                f"(t ≤ {self.time + (report.substep + 1) * self.dt:.4g} s): {self.guard.explain(report)}",
                frame=frame,
                substep=report.substep + 1,
            )
            error.reason = report.reason  # what tripped: the runner's diagnosis tells its kind apart
            raise error

    def _forget_verdict(self) -> None:
        """Drop a posted verdict not yet read, and a posted self-collision review: the state they judged is about to
        be replaced."""
        self._unsettled = False
        self._span_from = self._unchecked_from = None
        if self.guard is not None:
            self.guard.discard()
        if self.model.self_contact is not None:
            self.model.self_contact.forget_review()

    def _collect_review(self, frame: int) -> None:
        """Read the self-collision review posted after ``frame`` (1-based; ``SelfContact.collect_review``: nothing
        where none is posted) and, with a guard, stop on its pins beyond the cap (:meth:`_stop_on_outrun`)."""
        outran = self.model.self_contact.collect_review()
        if outran is not None and self.guard is not None and outran.any():
            self._stop_on_outrun(outran, frame)

    def _stop_on_outrun(self, new: np.ndarray, frame: int) -> None:
        """Stop the run after ``frame`` (1-based), in which a pin closed in on free cloth that had no room to give way
        (``new``: each world's pair-steps beyond the self-collision cap in it, ``SelfContact.review``), where the
        surface may have crossed itself. The frames before it passed the cap's guarantee; this one is not handed on
        (the run stands at the frame before it, as after a guard's stop)."""
        contact = self.model.self_contact
        self._forget_verdict()
        self.frame = frame - 1
        worlds = ", ".join(f"world {w}: {n}" for w, n in enumerate(new) if n) if len(new) > 1 else f"{new[0]}"
        raise SimulationError(
            f"frame {frame}: a pinned part of the surface closed in on free cloth that had no room to give "
            f"way ({worlds} pair-step(s) beyond the self-collision cap), so the surface may have crossed itself. "
            f"The pins' tracks press the cloth tighter than its thickness τ = {contact.thickness * 1e3:.3g} mm "
            "allows: slow the tracks, lower the self-collision thickness, or pin fewer particles where the cloth "
            "folds onto the pins",
            frame=frame)

    def _report_overflow(self) -> None:
        overflow = self.contact_overflow()
        new = overflow - self._overflow_seen
        if new.any():
            worlds = ", ".join(f"world {w}: {n}" for w, n in enumerate(new) if n) if len(new) > 1 else f"{new[0]}"
            slots = self.contacts.slots
            warnings.warn(ContactOverflowWarning(
                f"frame {self.frame + 1}: particles touched more colliders than their {slots} contact slot(s); "
                f"contacts dropped ({worlds}), so those particles were not kept out of every collider: "
                f"finalize with contact_slots={min(2 * slots, 64)}"), stacklevel=3)
        self._overflow_seen = overflow

    def hold_world(self, report: GuardReport, frame: int | None = None) -> None:
        """Hold ``report.world`` from now on and record its failure in :attr:`world_failures` at ``frame`` (default:
        the last frame completed), as the guard's ``stop="world"`` does for its own checks: a frame hook's finding
        (the stability watch's, ``StabilityWatch`` given ``stop``)."""
        self._world_failures.setdefault(report.world, (self.frame if frame is None else frame, report))
        self.model.set_world_enabled(report.world, False)

    def describe_failure(self, world: int) -> str:
        """One line on why the guard stopped ``world`` (a key of :attr:`world_failures`)."""
        frame, report = self.world_failures[world]
        return (f"world {world} stopped at frame {frame}, substep {report.substep + 1} of {self.substeps}: "
                f"{report.describe(self.model, name_world=False)}")

    def set_pin_targets(self, group, positions) -> None:
        """Send a control-driven pin group to ``positions`` [m] by the end of the next frame (see
        ``Control.set_pin_targets``): its particles move there in a straight line, exactly on it at every
        substep."""
        self.control.set_pin_targets(group, positions, time=self.time + self.frame_dt)

    def reset(self, state: State | None = None) -> None:
        """Restart at frame 0 (time 0) from ``state`` (default: the model's initial state), forgetting the
        integrator's history (step-size control, warm starts) and the pin targets set so far, so the run
        repeats exactly."""
        self._forget_verdict()  # a failure of the run left behind is not this run's
        self.stepper.reset(state)
        self.state.time.zero_()
        if self.guard is not None:
            self.guard.restart(self.state)
        if self.contacts is not None:
            self.contacts.reset()
            self._overflow_seen[:] = 0
        self.control.clear_pin_targets()  # they were set for times of the run before
        self.frame = 0
        if self.world_failures:
            self.model.set_world_enabled(list(self.world_failures), True)
            self.world_failures = {}

    def save_checkpoint(self, path: str | os.PathLike) -> Path:
        """Save everything this run needs to go on from the current frame to ``path`` (one ``.npz``, used as
        given), at full precision, so that :meth:`load_checkpoint` continues it bit for bit on the same device.

        Saved: the state (positions [m], velocities [m/s], forces [N], each world's time [s] in float64), the
        frame counter, the integrator's persistent arrays and settings (dopri5's step-size control, implicit
        Euler's warm start, tolerances), the model's live values (the input table of gravity, drag and
        stabiliser thresholds, ``world_enabled``, particle flags, masses, radii, rest lengths, stiffness and
        damping) and switches, the control's external force and pin targets, the contact overflow counters,
        the guard's record and :attr:`world_failures`; see :mod:`warpspring.core.checkpoint`. Not saved: the
        scene (topology, colliders, keyframe tracks), the guard's limits and ``use_graph``. The write is
        atomic: an interrupted save leaves a checkpoint already at ``path`` intact. Reads the device.

        Returns:
            The path written.

        Raises:
            ConfigError: the directory does not exist or cannot be written.
        """
        self.settle()  # the frame saved has passed the guard
        return Checkpoint.capture(self).save(path)

    def load_checkpoint(self, path: str | os.PathLike) -> None:
        """Continue from the checkpoint at ``path`` (written by :meth:`save_checkpoint` of a simulator of the
        same scene, integrator, fps and substeps): afterwards :attr:`frame`, :attr:`state` and everything
        :meth:`save_checkpoint` lists are as they were when it was saved, and the next frames repeat the saved
        run's bit for bit on the same device.

        The values are written into this simulator's existing device arrays, so a captured frame graph stays
        valid; a switch the saved run had turned on (gravity, drag, a stabiliser, held worlds, an external
        force) is turned on here too, and the next frame re-captures.

        Raises:
            ConfigError: the file is missing, damaged or not a checkpoint, or it was saved from another scene,
                integrator, fps or substeps (the one-line message names what differs and how to fix it).
        """
        self._forget_verdict()
        Checkpoint.load(path).restore(self)
        # What this simulator derives from the restored values: the overflow already reported, and a default
        # kinetic-energy limit (it follows the live inputs).
        self._overflow_seen = self.contact_overflow()
        if self.guard is not None:
            self.guard.limits = self.guard.limits
