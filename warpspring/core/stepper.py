"""The one stepper: warm-up, graph capture, replay and the swap of the two state buffers.

Everything that advances a model by a fixed number of steps at a time (the Simulator's frames, the
studies' measured runs, the examples) goes through :class:`Stepper`. A graph replays its launches with
the arguments they were captured with, so the stepper re-captures exactly when one of those could
differ, which it reads from explicit revision counters rather than guessing:

* ``model.revision``: a term switched on or off, a track added or removed, an array replaced;
* ``control.revision``: an input allocated for the first time (e.g. the external force);
* ``integrator.revision`` and each hook's ``revision``: their launches changed;
* the step ``dt``, the step count, and which integrator and control objects are used.

Values written into existing device arrays (gravity, drag, thresholds, stiffness, pin targets, solver
tolerances) are not in that list: the captured kernels read them from device memory at every replay.
"""

from __future__ import annotations

import warp as wp

from .. import checks
from ..errors import ConfigError
from .integrators import Integrator
from .model import Model
from .state import State, check_compatible
from .control import Control

#: Captured graphs a stepper keeps by their structure (``Stepper._key``), the least recently used dropped first: a
#: guard whose checks span frames alternates between a frame with its check and one without.
KEPT_GRAPHS = 4


class StepHook:
    """Device work a :class:`Stepper` runs around the integrator's steps (capturable: no host reads).

    Attributes:
        revision: bump it when the hook's launches change (the stepper then re-captures).
    """

    revision: int = 0

    def begin(self) -> None:
        """Called at the start of every :meth:`Stepper.advance`, before the first step."""

    def before_step(self, state: State, step: int, steps: int) -> None:
        """Called before step ``step`` (0-based) of ``steps``, with the state it starts from (optional: a hook
        without this method is not called)."""

    def after_step(self, state: State, step: int, steps: int) -> None:
        """Called after step ``step`` (0-based) of ``steps``, with the state that step produced."""

    def history(self) -> list:
        """Device arrays the hook carries from one advance to the next (restored after a capture's warm-up,
        like the integrator's history)."""
        return []

    def frame_check(self, steps: int, shape: tuple[int, int], *, integrator, control):
        """What the hook's work after the last step would be, as a check the one-launch frame of ``shape`` run by
        ``integrator`` with ``control`` can run at its end (``Integrator.advance_frame``'s ``check``), or ``None`` (the
        default): the hook's ``after_step`` then leaves that work out once told (:meth:`frame_checked`). Asked only
        of the stepper's first hook (no other hook's last ``after_step`` may come before the check), where every hook
        is quiet between steps."""
        return None

    def frame_checked(self) -> None:
        """The one-launch frame just launched ran :meth:`frame_check`'s check (this advance's last ``after_step``
        follows; the next :meth:`begin` forgets it)."""

    def quiet_between_steps(self, steps: int) -> bool:
        """Whether, in an advance of ``steps`` steps, the hook launches nothing around any step but the last
        (its ``before_step`` and ``after_step`` of the last step may still work). Only then may the integrator run
        the advance's steps in one launch (``Integrator.frame_shape``). Default: no."""
        return False


class Stepper:
    """Advances :attr:`state` by ``steps`` integrator steps of ``dt`` per :meth:`advance`, replaying one
    captured graph (a CUDA graph on GPUs, Warp's CPU graph on the CPU).

    Two state buffers alternate within an advance; an odd step count ends with a copy back, so the result
    is always :attr:`state`. Before a capture, one uncaptured step on the scratch buffer compiles and loads
    every module the advance launches (a capture must not load modules), and the integrator's history
    (warm starts, step-size control) is restored afterwards, so a captured run equals an uncaptured one
    bit for bit. A graph is kept for each structure met lately (``KEPT_GRAPHS``) and replayed when it comes back.

    Args:
        model: the model.
        integrator: the integrator (built for ``model``).
        dt: the step [s].
        steps: integrator steps per :meth:`advance`.
        control: time-varying inputs, or ``None``.
        hooks: :class:`StepHook` objects run around the steps, in order.
        use_graph: capture and replay; off runs the same launches from Python every time (debugging).
        state: the state to advance (default: ``model.state()``).
    """

    def __init__(
        self,
        model: Model,
        integrator: Integrator,
        *,
        dt: float,
        steps: int,
        control: Control | None = None,
        hooks=(),
        use_graph: bool = True,
        state: State | None = None,
    ):
        if integrator.model is not model:
            raise ConfigError("the integrator was built for another model: build it with this model")
        if control is not None and control.model is not model:
            raise ConfigError("the control was made by another model: use model.control() of this model")
        self.model = model
        self.integrator = integrator
        self.control = control
        self.dt = checks.positive("dt", dt)
        self.steps = checks.count("steps", steps, minimum=1)
        self.hooks = list(hooks)
        self.use_graph = bool(use_graph)
        self._scratch = model.state()
        if state is not None:
            check_compatible(self._scratch, state)
        self.state = state if state is not None else model.state()
        self._graph = None
        self._graph_key = None
        self._graphs = {}  # key → graph: the structures captured lately (a guard's checked and unchecked frames)
        #: Captures made so far (a structural change makes one more at the next advance).
        self.captures = 0

    def _key(self) -> tuple:
        """(what the graph's launches depend on but the hooks, the hooks' revisions)."""
        control = self.control
        return (
            (self.model.revision, id(control), control.revision if control is not None else None,
             id(self.integrator), self.integrator.revision, self.dt, self.steps),
            tuple((id(h), h.revision) for h in self.hooks),
        )

    def advance(self) -> None:
        """Run ``steps`` steps (capturing them first when nothing is captured yet or the structure changed)."""
        if not self.use_graph:
            self._run()
            return
        self_contact = self.model.self_contact
        if self_contact is not None and not self_contact.capturable:
            self._run()  # a CPU BVH refit is host work, which Warp's CPU graphs do not record
            return
        key = self._key()
        if self._graph is None or key != self._graph_key:
            graph = self._graphs.pop(key, None)  # (a graph of this structure captured before: used again)
            if graph is None:
                self._capture()
            else:
                self._graph = graph
            # Kept: the graphs that differ from this one in their hooks' revisions alone (a model, control or
            # integrator changed since makes the others stale), the least recently used dropped first.
            self._graphs = {k: g for k, g in self._graphs.items() if k[0] == key[0]}
            self._graphs[key] = self._graph
            while len(self._graphs) > KEPT_GRAPHS:
                self._graphs.pop(next(iter(self._graphs)))
            self._graph_key = key
        wp.capture_launch(self._graph)

    def reset(self, state: State | None = None) -> None:
        """Continue from ``state`` (default: the model's initial state) and forget the integrator's history
        (step-size control, warm starts) and the plastic springs' (rest lengths and plastic strains as
        built), so that the run repeats exactly."""
        self.state.assign(state if state is not None else self.model.state())
        self.integrator.reset()
        self.model.reset_plasticity()

    def _run(self) -> None:
        for hook in self.hooks:
            hook.begin()
        a, b = self.state, self._scratch
        before = [hook for hook in self.hooks if _wants_before_step(hook)]
        shape = self.integrator.frame_shape(self.control, self.steps)
        if shape is not None and all(hook.quiet_between_steps(self.steps) for hook in self.hooks):
            # The advance's steps in one launch (the same arithmetic, the same bits); the hooks see the last step.
            last = self.steps - 1
            for hook in before:
                hook.before_step(a if last % 2 == 0 else b, last, self.steps)
            # The first hook's check may run at the launch's end: no other hook's last step comes before it.
            first = self.hooks[0] if self.hooks else None
            check = (None if first is None else
                     first.frame_check(self.steps, shape, integrator=self.integrator, control=self.control))
            if check is None:
                self.integrator.advance_frame(a, b, self.control, self.dt, self.steps, shape)
            elif self.integrator.advance_frame(a, b, self.control, self.dt, self.steps, shape, check=check):
                first.frame_checked()
            result = a if self.steps % 2 == 0 else b
            for hook in self.hooks:
                hook.after_step(result, last, self.steps)
            if result is not self.state:
                self.state.assign(result)
            return
        for k in range(self.steps):
            for hook in before:
                hook.before_step(a, k, self.steps)
            self.integrator.step(a, b, self.control, self.dt)
            a, b = b, a
            for hook in self.hooks:
                hook.after_step(a, k, self.steps)
        if a is not self.state:
            self.state.assign(a)

    def _capture(self) -> None:
        # Warm-up: one uncaptured step (and every hook) on the scratch buffer loads every module; the
        # integrator's history is put back, so the warm-up leaves no trace in the run.
        carried = [*self.integrator.history(), *self.integrator.finish_step.history(),
                   *(a for hook in self.hooks for a in hook.history())]
        history = [wp.clone(a) for a in carried]
        for hook in self.hooks:
            hook.begin()
        for hook in self.hooks:
            if _wants_before_step(hook):
                hook.before_step(self.state, self.steps - 1, self.steps)
        self.integrator.step(self.state, self._scratch, self.control, self.dt)
        for hook in self.hooks:
            hook.after_step(self._scratch, self.steps - 1, self.steps)
        for saved, live in zip(history, carried):
            wp.copy(live, saved)
        with wp.ScopedCapture(device=self.model.device, force_module_load=False) as capture:
            self._run()
        self._graph = capture.graph
        self.captures += 1


def _wants_before_step(hook) -> bool:
    """Whether ``hook`` does something before a step (its class overrides :meth:`StepHook.before_step`)."""
    method = getattr(type(hook), "before_step", None)
    return method is not None and method is not StepHook.before_step
