"""The one contract every integrator implements."""

from __future__ import annotations

import abc

import numpy as np
import warp as wp

from ...kernels.worlds import hold_worlds_kernel
from ..constraints import StepFinisher
from ..model import Model
from ..state import State
from ..control import Control


def step_arguments(scalar: type, dt: float) -> tuple:
    """The step ``dt`` [s] as the kernels that advance a state's clock take it: rounded to ``scalar`` (the
    step the physics uses) and what that rounding dropped, so that their float64 sum is ``dt`` to ~1e-16
    relative (0 for float64 models)."""
    rounded = float(np.float32(dt)) if scalar is wp.float32 else float(dt)  # (a wp.float32 keeps the float)
    return scalar(rounded), scalar(dt - rounded)


def write_setting(settings: wp.array, slot: int, value: float) -> None:
    """Write one float64 setting (a tolerance, an iteration cap) into an integrator's device array: the
    captured kernels read it there, so a new value takes effect at the next replay, with no re-capture."""
    wp.copy(settings, wp.array([value], dtype=wp.float64, device="cpu"), dest_offset=slot, count=1)


class Integrator(abc.ABC):
    """Advances a :class:`State` of a :class:`Model` by one step.

    Subclasses set :attr:`name` (the scene-file / CLI name) and :attr:`order` (the method's
    convergence order), allocate any scratch states once in ``__init__``, and implement :meth:`step`.
    Options of a subclass are keyword-only arguments of its ``__init__``.
    """

    name: str = ""
    order: int = 0
    #: Whether the integrator chooses its own internal steps (it then takes a ``tolerance`` option).
    adaptive: bool = False
    #: Whether its step is stable at any size (its energy error at large steps is not an instability: the
    #: guard's energy balance does not apply).
    unconditionally_stable: bool = False
    #: Counts structural changes of the integrator's launches (a Stepper re-captures when it changes).
    #: Its settings (tolerances, iteration caps) are device values: changing them changes no launch.
    revision: int = 0
    #: The guard's sums counted in this integrator's force passes (``core/forces.py``), set by the guard that reads
    #: them: the scattered springs' dampers (``DamperSums``) and the power of dampers, drag and loads from outside
    #: (``PowerSums``); ``None``: not counted. Each simulator's integrator carries its own guard's.
    dampers = None
    power = None
    #: Where symplectic Euler's fused step sums the guard's power per block instead of per particle (``PowerSums``'s
    #: ``sums``): (the guard's running sums [world, block, slot], float64; the launch grid; the slots of the energy
    #: taken out and of the work put in), set by the guard (``Guard._attach_power``); ``None``: per particle.
    power_blocks = None

    def __init__(self, model: Model):
        self.model = model
        self.finish_step = StepFinisher(model)  # strain limiting, speed clamp, contacts: call on the result

    def frame_shape(self, control: Control | None, steps: int) -> tuple[int, int] | None:
        """(threads per block, blocks per world) with which :meth:`advance_frame` runs ``steps`` steps in one launch,
        or ``None`` where this integrator, the scene or the device does not allow it (the default: steps one launch
        at a time)."""
        return None

    def advance_frame(self, state_a: State, state_b: State, control: Control | None, dt: float, steps: int,
                      shape: tuple[int, int], check=None) -> bool:
        """``steps`` steps of ``dt`` [s] from ``state_a`` in one launch of ``shape`` (:meth:`frame_shape`),
        alternating between the two states as the stepper does (an odd count leaves the result in ``state_b``);
        ``check``: a step hook's check of the last state, to run at the launch's end (``StepHook.frame_check``).
        Returns whether it ran ``check``."""
        raise NotImplementedError(f"{type(self).__name__} has no one-launch frame")

    def hold_worlds(self, state_in: State, state_out: State) -> None:
        """Keep the held worlds (``model.world_enabled`` 0) of ``state_in`` unchanged in ``state_out``: the last
        launch of every step, and only in models that may hold worlds (``Model.holds_worlds``)."""
        model = self.model
        if not model.holds_worlds:
            return
        wp.launch(hold_worlds_kernel(model.scalar), dim=model.particle_dim, block_dim=model.block_dim,
                  inputs=[model.particle_count, model.world_enabled, state_in.particle_q, state_in.particle_qd,
                          state_in.time],
                  outputs=[state_out.particle_q, state_out.particle_qd, state_out.time], device=model.device)

    def reset(self) -> None:
        """Forget what earlier steps left behind (step-size control, solver warm starts), so the next step
        behaves as the first. Stateless integrators have nothing to forget."""

    def persistent_arrays(self) -> dict[str, wp.array]:
        """The device arrays that carry what one step leaves to the next (what :meth:`reset` forgets), by
        name: a Stepper saves and restores them around its warm-up step, and a checkpoint
        (``Simulator.save_checkpoint``) saves them. Override it to list an integrator's own; stateless
        integrators (every array of theirs rewritten by each step before it is read) have none."""
        return {}

    def history(self) -> list:
        """The arrays of :meth:`persistent_arrays`, in their order (what a Stepper restores after its warm-up)."""
        return list(self.persistent_arrays().values())

    def failure(self) -> str | None:
        """Why the last steps could not complete, for integrators that can stop short (adaptive ones
        with a step budget), else ``None``. May read the device."""
        return None

    #: Whether a shortfall of the inner solves (:meth:`solve_shortfall`) stops the run instead of warning.
    strict_solves: bool = False

    def solve_shortfall(self) -> str | None:
        """A line on inner iterative solves of the last steps that stopped short of their tolerance (the residual
        reached, the remedy), for the Simulator to warn with (or raise, with :attr:`strict_solves`), else ``None``.
        Integrators without inner solves have none. May read the device."""
        return None

    @abc.abstractmethod
    def step(self, state_in: State, state_out: State, control: Control | None, dt: float) -> None:
        """Advance ``state_in`` by ``dt`` [s] under ``control`` and write the result to ``state_out``.

        Every world of the model is stepped (held worlds are left as they are: :meth:`hold_worlds`).
        ``state_out.time`` becomes ``state_in.time`` + dt; kinematic particles follow their prescribed
        motion; animated inputs are evaluated at the time of every state whose forces are evaluated.
        ``state_in`` is not modified (but for its forces, ``particle_f``); the caller swaps the two states
        afterwards. No host synchronisation happens inside, so steps can be captured in a CUDA graph.
        """
