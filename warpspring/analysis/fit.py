"""Fitting a scene's parameters to a captured motion: L-BFGS-B (SciPy) on the gradient of a differentiable run,
many starting points at once as the worlds of one model, and each parameter's uncertainty from the Gauss-Newton
Hessian and the residual variance.

The residuals are r = x_sim(tₖ) - x*(tₖ) over every observed particle (or marker) and time; the loss is |r|².
Parameters are searched in log space (all are positive physical values: stiffness, damping, density, E), each
start in a world of its own: one run steps every start, and the optimiser sees the sum of the worlds' losses,
which separates into one problem per world. The best world's values are the fit. Then, with J = ∂r/∂θ at the
fit (central differences of the float64 run, each perturbation a world of one batched run: 2P worlds), the
Gauss-Newton covariance is σ² (JᵀJ)⁻¹ with σ² = |r|² / (m - P) the residual variance (m residuals, P
parameters): the standard error of each parameter is the square root of its diagonal entry.
"""

from __future__ import annotations

import copy
import os
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..core.adjoint import DiffRun, SmoothContact, Target
from ..core.adjoint_params import ParameterMap
from ..core.model import Model
from ..errors import ConfigError
from ..io.scene import parse_scene, read_toml


@dataclass(frozen=True)
class Motion:
    """A captured motion: particles ``particles`` (indices within a world; markers) at ``positions`` [m],
    [len(times), len(particles), 3], at ``times`` [s] from the run's start."""

    times: np.ndarray
    particles: np.ndarray
    positions: np.ndarray

    def __post_init__(self):
        times = np.asarray(self.times, dtype=np.float64)
        particles = np.asarray(self.particles, dtype=np.int64)
        positions = np.asarray(self.positions, dtype=np.float64)
        if positions.shape != (len(times), len(particles), 3):
            raise ConfigError(f"a motion's positions must have shape [times, particles, 3] = [{len(times)}, "
                              f"{len(particles)}, 3], got {positions.shape}")
        if len(times) == 0 or not np.all(np.diff(times) > 0) or times[0] < 0:
            raise ConfigError("a motion's times must be increasing and ≥ 0 [s]")
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "particles", particles)
        object.__setattr__(self, "positions", positions)

    def steps(self, dt: float) -> np.ndarray:
        """The step count of every time at steps of ``dt`` [s]; each time must be a whole number of steps."""
        steps = np.rint(self.times / dt).astype(np.int64)
        if np.abs(steps * dt - self.times).max() > 1e-9 * max(1.0, self.times[-1]):
            raise ConfigError(f"the motion's times are not whole multiples of the step {dt:g} s: choose substeps so "
                              "that every captured time falls on a step")
        return steps


@dataclass
class FitResult:
    """What :func:`fit` found.

    Attributes:
        names: the parameters.
        values: the fit, one value per parameter (SI units).
        standard_error: each value's standard error (Gauss-Newton, residual variance), same units.
        covariance: [P, P] covariance of the values.
        residual_rms: the root-mean-square residual [m] per coordinate at the fit, √(|r|² / m).
        loss: |r|² [m²] at the fit.
        residual_count: m, the residuals (3 per observed point and time).
        starts: each start's initial and final values and loss (dicts), in world order.
        evaluations: loss-and-gradient evaluations of the optimiser.
        message: the optimiser's last word.
    """

    names: tuple
    values: np.ndarray
    standard_error: np.ndarray
    covariance: np.ndarray
    residual_rms: float
    loss: float
    residual_count: int
    starts: list = field(default_factory=list)
    evaluations: int = 0
    message: str = ""

    def table(self) -> str:
        """A plain-text table of the fit (name, value, standard error, relative error)."""
        lines = [f"{'parameter':<20} {'value':>14} {'std. error':>12} {'relative':>9}"]
        for name, value, error in zip(self.names, self.values, self.standard_error):
            lines.append(f"{name:<20} {value:>14.6g} {error:>12.3g} {error / abs(value):>9.2%}")
        lines.append(f"residual rms {self.residual_rms:.3e} m over {self.residual_count} residuals; loss "
                     f"{self.loss:.4e} m²")
        return "\n".join(lines)


def _start_points(theta0: np.ndarray, lower: np.ndarray, upper: np.ndarray, starts: int, spread: float,
                  seed: int) -> np.ndarray:
    """Start 0 at ``theta0``; the others log-uniform within a factor ``spread`` of it (clipped to the bounds)."""
    rng = np.random.default_rng(seed)
    factors = np.exp(rng.uniform(-np.log(spread), np.log(spread), size=(starts - 1, len(theta0))))
    points = np.vstack([theta0[None], theta0[None] * factors])
    return np.clip(points, lower, upper)


def fit(build: Callable[[dict, int], Model], guess: dict, motion: Motion, *, dt: float,
        bounds: dict | None = None, integrator: str = "symplectic_euler", contact: SmoothContact | None = None,
        starts: int = 4, spread: float = 2.0, seed: int = 0, max_iterations: int = 100,
        checkpoint_every: int | None = None, device=None) -> FitResult:
    """Fit the parameters ``guess`` names to ``motion``.

    Args:
        build: (values {name: float}, worlds) → the scene's model with that many worlds (float64 advised), every
            value not named in ``guess`` at its own default.
        guess: the parameters to fit and the first start's values (SI units, > 0).
        motion: the captured motion (its times on whole steps of ``dt``).
        dt: the run's step [s].
        bounds: {name: (low, high)} per parameter; default a factor 10 either side of the guess.
        integrator: "symplectic_euler" or "velocity_verlet".
        contact: the smooth contact's values, for scenes with colliders.
        starts: starting points, one world each (the first at the guess, the others log-uniform within a factor
            ``spread`` of it, from ``seed``).
        max_iterations: L-BFGS-B's iteration cap.
        checkpoint_every: the run's checkpoint interval (default ⌈√steps⌉).
        device: where the run steps (the model's device when ``build`` ignores it).

    Returns:
        A :class:`FitResult`.
    """
    from scipy.optimize import minimize

    names = tuple(guess)
    if not names:
        raise ConfigError("name at least one parameter to fit")
    theta0 = np.array([float(guess[k]) for k in names])
    if np.any(theta0 <= 0.0):
        raise ConfigError("every fitted parameter must start > 0 (they are searched in log space)")
    bounds = bounds or {}
    lower = np.array([float(bounds.get(k, (v / 10.0, v * 10.0))[0]) for k, v in zip(names, theta0)])
    upper = np.array([float(bounds.get(k, (v / 10.0, v * 10.0))[1]) for k, v in zip(names, theta0)])
    if np.any(lower <= 0.0) or np.any(upper < lower):
        raise ConfigError("bounds must be 0 < low ≤ high for every parameter")
    if not (isinstance(starts, int) and starts >= 1):
        raise ConfigError(f"starts must be an int ≥ 1, got {starts!r}")
    steps = motion.steps(dt)
    mapping = ParameterMap(lambda values: build(values, 1), names, theta0)
    model = build(dict(zip(names, theta0)), starts)
    run = DiffRun(model, dt=dt, steps=int(steps[-1]), integrator=integrator, contact=contact,
                  checkpoint_every=checkpoint_every)
    run.set_targets([Target(int(s), motion.particles, motion.positions[k]) for k, s in enumerate(steps)])
    points = _start_points(theta0, lower, upper, starts, spread, seed)
    P = len(names)
    state = dict(evaluations=0, last=None)

    def evaluate(phi_all: np.ndarray):
        thetas = np.exp(phi_all.reshape(starts, P))
        derivatives = mapping.apply(run, thetas)
        loss, grads = run.gradient()
        state["evaluations"] += 1
        gradient = mapping.chain(run, grads, derivatives) * thetas  # d/d log θ
        bad = ~np.isfinite(loss) | ~np.all(np.isfinite(gradient), axis=1)
        loss = np.where(bad, 1e30, loss)
        gradient[bad] = 0.0
        state["last"] = (thetas, loss)
        return loss, gradient

    loss0, _ = evaluate(np.log(points).ravel())
    # A start whose run is not finite (an explicit step past its stability limit) is dropped: held at its values,
    # left out of the objective. A step of the search into such values meets a barrier (1e30) and backs off.
    dropped = loss0 >= 1e30
    if dropped.all():
        raise ConfigError("every start's run blew up (not finite): give more substeps or guesses and bounds nearer "
                          "the target's values")
    scale = max(float(np.min(loss0[~dropped])), 1e-300)  # the objective near 1 at the best start

    def objective(phi_all):
        loss, gradient = evaluate(phi_all)
        loss[dropped] = 0.0
        gradient[dropped] = 0.0
        return float(loss.sum() / scale), gradient.ravel() / scale

    low = np.tile(np.log(lower), (starts, 1))
    high = np.tile(np.log(upper), (starts, 1))
    low[dropped] = high[dropped] = np.log(points[dropped])
    result = minimize(objective, np.log(points).ravel(), jac=True, method="L-BFGS-B",
                      bounds=list(zip(low.ravel(), high.ravel())),
                      options=dict(maxiter=max_iterations, ftol=1e-12, gtol=1e-9))
    final = np.exp(result.x.reshape(starts, P))
    mapping.apply(run, final)
    losses = np.where(np.isfinite(run.loss()), run.loss(), np.inf)
    best = int(np.argmin(losses))
    values = final[best]
    covariance, residual_count = _gauss_newton(build, mapping, run, motion, steps, values, float(losses[best]),
                                               integrator, contact, dt)
    return FitResult(
        names=names, values=values, standard_error=np.sqrt(np.maximum(np.diag(covariance), 0.0)),
        covariance=covariance, residual_rms=float(np.sqrt(losses[best] / residual_count)), loss=float(losses[best]),
        residual_count=residual_count,
        starts=[dict(start=dict(zip(names, points[w])), fit=dict(zip(names, final[w])), loss=float(losses[w]))
                for w in range(starts)],
        evaluations=state["evaluations"], message=str(result.message))


def _gauss_newton(build, mapping: ParameterMap, run: DiffRun, motion: Motion, steps, values: np.ndarray,
                  loss: float, integrator: str, contact, dt: float, relative: float = 1.0e-5):
    """σ² (JᵀJ)⁻¹ at ``values`` and the residual count m; J by central differences, the 2P perturbed runs as the
    worlds of one run."""
    P = len(values)
    thetas = np.repeat(values[None], 2 * P, axis=0)
    h = relative * np.abs(values)
    for p in range(P):
        thetas[2 * p, p] += h[p]
        thetas[2 * p + 1, p] -= h[p]
    model = build(dict(zip(mapping.names, values)), 2 * P)
    batch = DiffRun(model, dt=dt, steps=int(steps[-1]), integrator=integrator, contact=contact)
    mapping.apply(batch, thetas)
    x = batch.positions(steps)[:, :, motion.particles]  # [times, worlds, markers, 3]
    jacobian = np.stack([(x[:, 2 * p] - x[:, 2 * p + 1]).ravel() / (2.0 * h[p]) for p in range(P)], axis=1)
    m = jacobian.shape[0]
    if m <= P:
        raise ConfigError(f"{m} residuals cannot give the uncertainty of {P} parameters: observe more points or times")
    variance = loss / (m - P)
    covariance = variance * np.linalg.inv(jacobian.T @ jacobian)
    return covariance, m


# -- targets and scenes from files ----------------------------------------------------------------------------


def motion_from_file(path: str, *, prim: str | None = None) -> Motion:
    """A captured motion from a file: a ``.npz`` of ``times`` [s], ``particles`` (indices) and ``positions`` [m]
    ([times, particles, 3]); or a USD file of the same mesh (every point of the mesh prim ``prim``, default the first
    mesh outside ``/colliders``, at every time sample after the first, times from the stage's time codes per second;
    its points are the particles in order, as ``warpspring run`` writes a cloth)."""
    if not os.path.isfile(path):
        raise ConfigError(f"no target file {path!r}: give a .npz of markers or a USD file of the same mesh")
    if path.endswith(".npz"):
        with np.load(path) as data:
            missing = {"times", "particles", "positions"} - set(data.files)
            if missing:
                raise ConfigError(f"{path}: a markers file needs arrays times, particles and positions; missing "
                                  f"{', '.join(sorted(missing))}")
            return Motion(times=data["times"], particles=data["particles"], positions=data["positions"])
    from pxr import Usd, UsdGeom  # optional: pxr (usd-core)

    stage = Usd.Stage.Open(path)
    if stage is None:
        raise ConfigError(f"{path}: not a USD file USD can open")
    meshes = [p for p in stage.Traverse() if p.GetTypeName() == "Mesh" and "colliders" not in str(p.GetPath())]
    chosen = [p for p in meshes if prim is None or str(p.GetPath()) == prim]
    if not chosen:
        raise ConfigError(f"{path}: no mesh prim {prim or ''} to fit to (meshes: "
                          f"{', '.join(str(p.GetPath()) for p in meshes) or 'none'})")
    points = UsdGeom.Mesh(chosen[0]).GetPointsAttr()
    samples = [t for t in points.GetTimeSamples()]
    if len(samples) < 2:
        raise ConfigError(f"{path}: the mesh {chosen[0].GetPath()} has {len(samples)} time samples: a motion needs 2 or more")
    rate = stage.GetTimeCodesPerSecond()
    first = samples[0]
    positions = np.stack([np.asarray(points.Get(t), dtype=np.float64) for t in samples[1:]])
    return Motion(times=(np.asarray(samples[1:]) - first) / rate, particles=np.arange(positions.shape[1]),
                  positions=positions)


def scene_parameters(path: str, names) -> tuple[Callable[[dict, int], Model], dict]:
    """A scene file's builder for :func:`fit` and the guesses: ``names`` are dotted keys of the file's tables
    (``cloth.material.stretch``, ``world.drag``, ``soft_body.0.youngs_modulus`` for the first of an array of
    tables), each holding a number there (the guess); the model is built in float64."""
    data = read_toml(path, "scene file")

    def locate(tree, name):
        keys = name.split(".")
        node = tree
        for key in keys[:-1]:
            node = node[int(key)] if isinstance(node, list) else node.get(key) if isinstance(node, dict) else None
            if node is None:
                raise ConfigError(f"{path}: no table {name.rsplit('.', 1)[0]!r} for the parameter {name!r}")
        if isinstance(node, list):
            raise ConfigError(f"{path}: {name!r} names an array of tables: add the index, e.g. {name}.0")
        return node, keys[-1]

    guess = {}
    for name in names:
        node, key = locate(data, name)
        value = node.get(key) if isinstance(node, dict) else None
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            raise ConfigError(f"{path}: the parameter {name!r} must be a number written in the scene file "
                              f"(its guess), got {value!r}")
        guess[name] = float(value)

    def build(values: dict, worlds: int, device=None) -> Model:
        tree = copy.deepcopy(data)
        for name, value in values.items():
            node, key = locate(tree, name)
            node[key] = float(value)
        scene = parse_scene(tree, path=path)
        scene.precision = "float64"
        scene.world_count = worlds
        scene.world_inputs, scene.world_scales = {}, {}
        return scene.finalize(device)

    return build, guess
