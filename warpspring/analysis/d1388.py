"""ASTM D1388 (option A, the cantilever) by simulation: the overhang at which a strip of a :class:`ClothMaterial`,
slid slowly off a horizontal platform under a ruler, touches the plane inclined at 41.5° below the platform's
edge, against the heavy elastica's float64 answer (:mod:`warpspring.analysis.elastica`).

The strip is a material grid (``add_cloth_grid(material=...)``) along x, ``width_cells`` cells wide: two
columns of pinned particles are the part under the ruler, the second of them on the platform's edge, and
``cells`` cells overhang it. The slide is slow enough to be a sequence of static equilibria, so each overhang
L is solved statically: implicit Euler steps of 1 s (ω h ≫ 1 for every mode: each step is a Gauss-Newton
iteration of the static problem) until no particle moves by more than 1e-9 L, in float64. The chord from
the edge to the tip (the mean of the last column) falls by an angle that grows with L; the overhang at
41.5° is found by the secant method on L (the spacing is L / cells, so every overhang is resolved alike),
to 1e-6 of L. The printed bending length is then c = L / 2.0003 (:func:`elastica.overhang_ratio`; the
standard's c = L / 2).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .. import checks
from ..core.builder import ModelBuilder
from ..core.integrators import ImplicitEuler
from ..core.material import ClothMaterial
from ..errors import ConfigError
from . import elastica

GRAVITY = 9.81  # [m/s²]
_STEP = 1.0  # [s], a static step (module docstring)
_MOVE = 1.0e-9  # the largest particle move of a converged solve, per metre of overhang
_MAX_STEPS = 200


class Cantilever(NamedTuple):
    """A static strip over the platform's edge."""

    overhang: float  # [m]
    chord_angle: float  # [rad], below the horizontal, of the line from the edge to the tip
    positions: np.ndarray  # [m], shape [width_cells + 1, cells + 2, 3] (row, column)
    steps: int  # static (implicit Euler) steps taken


class D1388(NamedTuple):
    """The simulated and the exact overhang at 41.5°."""

    overhang: float  # [m], simulated
    reference: float  # [m], the heavy elastica's Λ* c
    cantilever: Cantilever  # the strip at the simulated overhang

    @property
    def error(self) -> float:
        """(simulated - reference) / reference [-]."""
        return self.overhang / self.reference - 1.0


def cantilever(material: ClothMaterial, overhang: float, *, cells: int, width_cells: int = 2,
               device=None) -> Cantilever:
    """The static strip of ``material`` overhanging the edge by ``overhang`` [m] over ``cells`` cells."""
    overhang = checks.positive("overhang", overhang)
    cells = checks.count("cells", cells, minimum=2)
    width_cells = checks.count("width_cells", width_cells, minimum=1)
    nx, ny = cells + 2, width_cells + 1
    builder = ModelBuilder(up_axis="Z", gravity=(0.0, 0.0, -GRAVITY))
    clamp = [r * nx + c for r in range(ny) for c in (0, 1)]
    builder.add_cloth_grid(nx=nx, ny=ny, spacing=overhang / cells, material=material, pin=clamp)
    model = builder.finalize(device, precision="float64")
    integrator = ImplicitEuler(model, cg_iterations=20 * model.particle_count, cg_tolerance=1e-10)
    state, scratch = model.state(), model.state()
    for steps in range(1, _MAX_STEPS + 1):
        integrator.step(state, scratch, None, _STEP)
        state, scratch = scratch, state
        move = float(np.abs(state.particle_q.numpy() - scratch.particle_q.numpy()).max())
        if move < _MOVE * overhang:
            break
    else:
        raise RuntimeError(f"the cantilever's static solve did not converge in {_MAX_STEPS} steps "
                           f"(last move {move:.2e} m at overhang {overhang} m)")
    q = state.particle_q.numpy().astype(np.float64).reshape(ny, nx, 3)
    edge, tip = q[:, 1].mean(axis=0), q[:, -1].mean(axis=0)
    return Cantilever(overhang, math.atan2(edge[2] - tip[2], tip[0] - edge[0]), q, steps)


def simulate(material: ClothMaterial, *, cells: int, width_cells: int = 2, device=None,
             angle: float = elastica.D1388_ANGLE) -> D1388:
    """The overhang [m] at which the simulated strip's chord falls by ``angle`` (41.5°), by the secant method."""
    if not isinstance(material, ClothMaterial):
        raise ConfigError(f"material must be a warpspring.ClothMaterial, got {type(material).__name__}")
    reference = elastica.overhang_ratio(angle) * elastica.bending_length(material.bending, material.density,
                                                                          GRAVITY)

    def solve(length):
        return cantilever(material, length, cells=cells, width_cells=width_cells, device=device)

    a, b = solve(reference), solve(1.05 * reference)
    for _ in range(30):
        if abs(b.overhang - a.overhang) < 1e-6 * b.overhang:
            return D1388(b.overhang, reference, b)
        slope = (b.chord_angle - a.chord_angle) / (b.overhang - a.overhang)
        a, b = b, solve(b.overhang + (angle - b.chord_angle) / slope)
    raise RuntimeError("the secant search for the D1388 overhang did not converge")  # pragma: no cover
