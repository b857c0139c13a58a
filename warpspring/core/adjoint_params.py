"""Named scalar parameters of a differentiable run: how a user's values (a ``ClothMaterial``'s stretch, a soft
body's E, the drag, the wind) move the arrays a :class:`~warpspring.core.adjoint.DiffRun` differentiates.

A :class:`ParameterMap` holds a function ``make(values) -> Model`` that builds the scene for a dict of values
(one world, the run's precision and device) and finds, by building it at θ ± δ, the derivative of every array of
``DiffRun.values`` with respect to every parameter. Most maps are linear (a spring's ke is proportional to the
material's stretch, a hinge's to its bending, the drag is the drag): the map checks that at a second point and
then writes any θ as base + J (θ - θ₀) with no rebuild, and the chain rule is exact. A map that is not linear
(E and ν into the neo-Hookean Lamé values, density into inverse masses) is rebuilt at each θ and its J found by
central differences of the builder, accurate to O(δ²) ≈ 1e-10 relative.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..errors import ConfigError
from .adjoint import DiffRun
from .model import Model

#: Relative step of the central differences of a builder, and the relative change of a linear map's J between
#: two points below which the map counts as linear.
BUILD_STEP = 1.0e-5
LINEAR_TOLERANCE = 1.0e-7


def model_values(model: Model) -> dict[str, np.ndarray]:
    """The arrays of ``DiffRun(model).values`` as float64 host arrays of world 0 (particle arrays [n, 3], the rest
    one row); of the contact's values only the colliders' friction is the scene's (the rest are the run's)."""
    run = DiffRun(model, dt=1.0, steps=1)
    n = model.particle_count
    out = {}
    for name, array in run.values.items():
        host = np.asarray(array.numpy(), dtype=np.float64)
        out[name] = host[:n].copy() if name in ("particle_q", "particle_qd") else host[0].copy()
    return out


class ParameterMap:
    """Named scalars → the arrays of a differentiable run (see the module docstring).

    Args:
        make: builds the scene's model (one world) for a dict {name: value}.
        names: the parameters, in order.
        values: their values at which the map is first evaluated (and the linearity checked).
    """

    def __init__(self, make: Callable[[dict], Model], names, values):
        self.make = make
        self.names = tuple(names)
        theta = np.asarray(values, dtype=np.float64)
        if theta.shape != (len(self.names),):
            raise ConfigError(f"give one value per parameter ({len(self.names)}), got shape {theta.shape}")
        self.theta0 = theta
        self.base, self.jacobian0 = self._evaluate(theta)
        other = theta * 1.25 + (theta == 0.0) * 1.0
        _, jacobian1 = self._evaluate(other)
        self.linear = set(jacobian1) == set(self.jacobian0) and all(
            np.abs(jacobian1[name] - jac).max(initial=0.0) <= LINEAR_TOLERANCE * max(np.abs(jac).max(initial=0.0), 1e-300)
            for name, jac in self.jacobian0.items())

    def _build(self, theta: np.ndarray) -> dict[str, np.ndarray]:
        return model_values(self.make(dict(zip(self.names, map(float, theta)))))

    def _evaluate(self, theta: np.ndarray):
        """(arrays at θ, {array name: derivative, shape [P, *array shape]})."""
        base = self._build(theta)
        jac = {name: np.zeros((len(self.names), *a.shape)) for name, a in base.items()}
        for p in range(len(self.names)):
            step = BUILD_STEP * max(abs(theta[p]), 1e-12)
            up, down = theta.copy(), theta.copy()
            up[p] += step
            down[p] -= step
            a, b = self._build(up), self._build(down)
            for name in base:
                jac[name][p] = (a[name] - b[name]) / (2.0 * step)
        # Only the arrays some parameter moves matter.
        moved = [name for name in base if np.abs(jac[name]).max(initial=0.0) > 0.0]
        return base, {name: jac[name] for name in moved}

    def arrays(self, theta) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """The moved arrays at θ and their derivatives (as ``_evaluate``)."""
        theta = np.asarray(theta, dtype=np.float64)
        if self.linear:
            return ({name: self.base[name] + np.tensordot(theta - self.theta0, jac, axes=1)
                     for name, jac in self.jacobian0.items()}, self.jacobian0)
        base, jac = self._evaluate(theta)
        return {name: base[name] for name in jac}, jac

    def apply(self, run: DiffRun, thetas) -> list[dict[str, np.ndarray]]:
        """Write each world's θ (``thetas`` [world_count, P]) into the run's arrays; returns each world's
        derivatives (for :meth:`chain`)."""
        model = run.model
        worlds, n = model.world_count, model.particle_count
        thetas = np.asarray(thetas, dtype=np.float64).reshape(worlds, len(self.names))
        hosts = {}
        derivatives = []
        for w in range(worlds):
            values, jac = self.arrays(thetas[w])
            derivatives.append(jac)
            for name, value in values.items():
                host = hosts.setdefault(name, np.array(run.values[name].numpy(), dtype=np.float64))
                row = host[w * n:(w + 1) * n] if name in ("particle_q", "particle_qd") else host[w]
                moved = np.any(jac[name] != 0.0, axis=0)  # only the entries a parameter moves (the contact's
                row[moved] = value[moved]  # friction, not the run's own contact stiffness)
        for name, host in hosts.items():
            run.values[name].assign(host.astype(run.values[name].numpy().dtype))
        return derivatives

    def chain(self, run: DiffRun, grads: dict[str, np.ndarray], derivatives) -> np.ndarray:
        """dL_w/dθ_w [world_count, P] from the run's array gradients and :meth:`apply`'s derivatives."""
        worlds, n = run.model.world_count, run.model.particle_count
        out = np.zeros((worlds, len(self.names)))
        for w, jac in enumerate(derivatives):
            for name, d in jac.items():
                g = grads[name][w * n:(w + 1) * n] if name in ("particle_q", "particle_qd") else grads[name][w]
                out[w] += np.tensordot(d, g, axes=g.ndim)
        return out
