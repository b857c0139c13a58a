"""The three-wave resonance past √3/ω_max weighed against the motion that feeds it: the energy and strain the
cloth's upper band carries along a run, and the growth the resonant triads it drives can reach within a horizon.

The three-wave limit (:func:`~.stability.triad_step`) keeps every mode's phase per step θ ≤ 2π/3, so that no three
modes' phases sum to 2π: symplectic Euler and velocity Verlet (cos θ = 1 - (ωh)²/2) alias such a sum to zero, and
the springs' quadratic nonlinearity then trades energy between the three without a frequency mismatch. Past it,
a triad needs two daughters of phase θ_a, θ_b ≤ θ_top (the top mode's) and a pump of phase θ_p = 2π - θ_a - θ_b
≥ 2π - 2θ_top: every mode of a resonant triad lies in the *upper band*, ω ≥ ω_p with ω_p h = 2 sin(θ_p / 2)
(:func:`pump_cut`), which starts at ω_max itself at ωh = √3 and reaches down to 0 at the linear limit ωh = 2. A
step between the two is safe for a run of ``horizon`` seconds if the band's motion cannot grow a triad to a
visible energy in that time.

**Growth rate (an upper bound).** The pump modulates the daughters' stiffness: a spring of length l whose ends
move apart by Δu (the pump's displacement) turns by |Δu_⊥|/l and stretches by Δu_∥/l, which changes its stiffness
along any direction by at most 2|Δu|/l of its ke (the rotation enters the axial form ke (d̂·x)² twice; the stretch
the transverse ke (1 - L/l) once), so a daughter's ω² is modulated by a relative depth q ≤ 2 max_s |Δu_s|/l_s.
The leapfrog map x_{n+1} - 2 cos θ x_n + x_{n-1} = -h² ω² q cos(φ n) x_n grows at exact parametric resonance by
μ = h² ω² q / (4 sin θ) per step (first order in q; its continuous limit θ = ωh is Mathieu's ω q / 4), so at
γ = ω_max² h q / (4 sin θ_top) per second for daughters at the top. The pump's displacement is at most its
velocity over its lowest frequency, |Δu| ≤ |Δv_band| / ω_p; taking the band's whole motion as one coherent pump
at the triad's frequency makes γ an upper bound.

**Growth needed.** The daughters start with at most the band's own energy E_band (2× its kinetic energy) and must
gain ``GROWTH`` (1 %) of the motion's energy E (its largest kinetic energy: less than the release sets free, so
the test is the stricter) to be seen: ½ ln(GROWTH · E / E_band) e-folds of amplitude, none where the band already
carries that much.

**The motion** (:func:`record_motion`): the cloth run from its start by velocity Verlet at a small step, sampled
every ``RECORD_EVERY`` seconds, each sample split into the band above each of the ``CUTS`` by a Chebyshev filter of
M^(-1/2) K M^(-1/2) (K the springs' tangent stiffness there, :func:`~.modal.spring_tangent`; degree ``BAND_DEGREE``
with Jackson damping; checked against the float64 modes in ``tests/test_stability_battery.py``).

**What it shows** (``python bench/advisor_battery.py --bands``, ``bench/results/advisor_battery_cpu.md``): the upper
band fills within seconds in every case of the battery, 8² to 64², folded or flat, with or without gravity: by
10 s, 3-27 % of the motion's largest kinetic energy lies above 0.694 ω_max (the pump band of the triads at
1.083 √3), more than the 1 % of a visible growth from 0.75-5 s on, and the bound reaches 19-3300 e-folds at
1.02-1.083 √3. So a criterion that weighs the band's energy and stays an upper bound (:func:`growth_step`) passes no
step past the three-wave limit in any case, including those whose runs hold up to ωh = 1.9-2.0 (the 64² flat
cloth, the folded cloths without gravity at 32² and 64²): it is not the band's energy that keeps those runs from
growing, and the advisor keeps the three-wave verdict (:func:`~.stability.passed_step`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import eigsh

from ..core.integrators import VelocityVerlet
from ..core.model import Model
from ..core.simulator import Simulator
from .modal import spring_tangent
from .omega import free_particles

#: Growth that shows: the battery's 1 % of the motion's energy (``stability_battery.GROWTH``).
GROWTH = 0.01
#: How often :func:`record_motion` samples the motion [s].
RECORD_EVERY = 0.25
#: The band's lower edges, ω_p / ω_max.
CUTS = tuple(np.round(np.linspace(0.30, 1.0, 29), 4))
#: The Chebyshev filter's degree.
BAND_DEGREE = 120
#: The integrators whose phase per step is cos θ = 1 - (ωh)²/2 (the pump band's edge above).
LEAPFROG = ("symplectic_euler", "velocity_verlet")


@dataclass(frozen=True)
class BandRecord:
    """The upper band's motion along a run, per sample (:func:`band_record`).

    Attributes:
        times: when each sample was taken [s], shape [samples].
        omega: ω_max at each sample [rad/s] (the filter's scale), shape [samples].
        energy: the band's kinetic energy above each cut [J], shape [samples, len(CUTS)].
        strain: the band's largest |Δv| / (ω_p l) over the springs, ω_p = cut · ω_max, shape [samples, len(CUTS)].
        kinetic: the whole motion's kinetic energy [J], shape [samples].
        duration: how far the record reaches [s].
    """

    times: np.ndarray
    omega: np.ndarray
    energy: np.ndarray
    strain: np.ndarray
    kinetic: np.ndarray
    duration: float


def _jackson(degree: int) -> np.ndarray:
    k = np.arange(degree + 1)
    m = degree + 2
    return ((m - k) * np.cos(np.pi * k / m) + np.sin(np.pi * k / m) / np.tan(np.pi / m)) / m


def band_sample(model: Model, positions: np.ndarray, velocities: np.ndarray, *, world: int = 0,
                degree: int = BAND_DEGREE) -> tuple[float, np.ndarray, np.ndarray, float]:
    """One state's upper bands: (ω_max [rad/s], kinetic energy above each of ``CUTS`` · ω_max [J], the largest
    |Δv_band| / (ω_p l) over the springs for each [-], the whole kinetic energy [J]); ``positions`` [m] and
    ``velocities`` [m/s] of ``world``'s particles, float64, shape [particle_count, 3]."""
    free = np.repeat(free_particles(model)[world], 3)
    mass = np.repeat(model.world_values("particle_mass")[world].astype(np.float64), 3)[free]
    root = np.sqrt(mass)
    stiffness, _ = spring_tangent(model, positions, world=world)
    stiffness = stiffness.tocsr()[free][:, free]
    scaled = sp.diags(1.0 / root) @ stiffness @ sp.diags(1.0 / root)
    scaled = scaled.tocsr()
    bound = float(np.abs(scaled).sum(axis=1).max()) * 1.0001  # Gershgorin: the filter's interval
    w = root * np.asarray(velocities, dtype=np.float64).reshape(-1)[free]
    top = float(eigsh(scaled, k=1, which="LA", return_eigenvectors=False, tol=1e-6)[0])
    cuts = np.asarray(CUTS)
    edges = np.clip(2.0 * cuts * cuts * top / bound - 1.0, -1.0, 1.0)
    angles = np.arccos(edges)
    k = np.arange(degree + 1)
    coefficients = np.where(k == 0, angles[:, None] / math.pi,
                            2.0 * np.sin(k[None, :] * angles[:, None]) / (np.maximum(k, 1)[None, :] * math.pi))
    coefficients *= _jackson(degree)[None, :]
    previous, current = w, (2.0 / bound) * (scaled @ w) - w
    bands = np.outer(coefficients[:, 0], previous) + np.outer(coefficients[:, 1], current)
    for order in range(2, degree + 1):
        previous, current = current, 2.0 * ((2.0 / bound) * (scaled @ current) - current) - previous
        bands += np.outer(coefficients[:, order], current)
    energy = 0.5 * (bands * bands).sum(axis=1)
    band_velocity = np.zeros((len(cuts), model.particle_count * 3))
    band_velocity[:, free] = bands / root[None, :]
    band_velocity = band_velocity.reshape(len(cuts), -1, 3)
    i, j = model.spring_indices.numpy().reshape(-1, 2).T
    q = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    length = np.maximum(np.linalg.norm(q[j] - q[i], axis=1), 1e-12)
    omega = math.sqrt(max(top, 0.0))
    relative = np.linalg.norm(band_velocity[:, j] - band_velocity[:, i], axis=2) / length[None, :]
    strain = relative.max(axis=1) / np.maximum(cuts * omega, 1e-300)
    return omega, energy, strain, 0.5 * float(w @ w)


def band_record(model: Model, times, positions, velocities, duration: float, *, world: int = 0) -> BandRecord:
    """:func:`band_sample` of each recorded state (``times`` [s]; ``positions``, ``velocities`` of ``world``, shape
    [samples, particle_count, 3]); ``duration``: how far the run reached [s]."""
    rows = [band_sample(model, q, v, world=world) for q, v in zip(positions, velocities)]
    return BandRecord(np.asarray(times, dtype=np.float64), np.array([r[0] for r in rows]),
                      np.array([r[1] for r in rows]).reshape(len(rows), len(CUTS)),
                      np.array([r[2] for r in rows]).reshape(len(rows), len(CUTS)),
                      np.array([r[3] for r in rows]), float(duration))


def record_motion(model: Model, seconds: float, *, step: float, every: float = RECORD_EVERY,
                  world: int = 0) -> BandRecord:
    """The upper bands (:func:`band_record`) of ``model`` run from its start by velocity Verlet at ``step`` [s] for
    ``seconds`` [s], sampled every ``every`` [s] (rounded to whole steps); the model's own loads act, no control."""
    substeps = max(1, round(every / step))
    sim = Simulator(model, integrator=VelocityVerlet(model), fps=1.0 / (substeps * step), substeps=substeps, guard=None)
    n = model.particle_count
    times, positions, velocities = [], [], []
    while sim.time < seconds - 0.5 * substeps * step:
        sim.step_frame()
        times.append(sim.time)
        positions.append(sim.state.particle_q.numpy().astype(np.float64)[world * n:(world + 1) * n])
        velocities.append(sim.state.particle_qd.numpy().astype(np.float64)[world * n:(world + 1) * n])
    return band_record(model, times, positions, velocities, sim.time, world=world)


def pump_cut(omega_h: float) -> float:
    """ω_p / ω_max: the lowest pump of a resonant triad whose daughters are at most the top mode, for symplectic Euler
    and velocity Verlet at ω_max h = ``omega_h``: θ_p = 2π - 2θ_top gives ω_p h = 2 sin θ_top and, with ω_max h =
    2 sin(θ_top / 2), ω_p / ω_max = 2 cos(θ_top / 2) = √(4 - (ω_max h)²) (1 at √3 and below, 0 at 2)."""
    return 1.0 if omega_h <= math.sqrt(3.0) else math.sqrt(max(4.0 - omega_h * omega_h, 0.0))


def triad_growth(record: BandRecord, omega: float, h: float, horizon: float) -> tuple[float, float]:
    """(the e-folds ∫ γ dt that the triads at step ``h`` [s] reach over ``horizon`` [s] by the bound, the e-folds a
    visible growth needs) for a top mode of ``omega`` [rad/s] (the module docstring); (0, ∞) up to √3."""
    omega_h = omega * h
    if omega_h <= math.sqrt(3.0):
        return 0.0, math.inf
    theta = 2.0 * math.asin(min(omega_h / 2.0, 1.0))
    column = int(np.searchsorted(np.asarray(CUTS), pump_cut(omega_h), side="right")) - 1  # the cut below: more band
    if column < 0:
        return math.inf, 0.0
    rate = omega * omega * h * 2.0 * record.strain[:, column] / (4.0 * max(math.sin(theta), 1e-12))  # [1/s]
    spans = np.diff(np.concatenate([[0.0], record.times]))
    held = np.maximum(rate, np.concatenate([rate[:1], rate[:-1]]))  # each interval at its larger end
    reached = float((held * spans).sum()) + float(rate[-1]) * max(horizon - float(record.times[-1]), 0.0)
    band = 2.0 * float(record.energy[:, column].max())
    motion = float(record.kinetic.max())
    needed = 0.5 * math.log(GROWTH * motion / band) if band > 0.0 and motion > 0.0 else math.inf
    return reached, max(needed, 0.0)


def growth_step(integrator: str, omega: float, limit: float, record: BandRecord, horizon: float,
                points: int = 64) -> float:
    """The largest step [s] between the three-wave step √3/ω and ``limit`` (ω of the top mode ``omega`` [rad/s]) below
    which the triads of ``record``'s motion do not grow visibly within ``horizon`` [s] (:func:`triad_growth`); the
    three-wave step where the record does not reach the horizon or the integrator is not leapfrog-like."""
    start = math.sqrt(3.0) / omega
    if integrator not in LEAPFROG or record is None or record.duration < horizon or not limit > start:
        return min(start, limit)
    best = start
    for h in np.linspace(start, limit, points)[1:]:
        reached, needed = triad_growth(record, omega, float(h), horizon)
        if not reached <= needed:
            break
        best = float(h)
    return best

