"""The Cusick drape test (BS 5058, ISO 9073-9) by simulation: a round specimen of a :class:`ClothMaterial` laid
centred on a round pedestal, left to settle, and its drape coefficient DC = (A_shadow - A_disc) /
(A_specimen - A_disc) measured from its shadow (its vertical projection).

The specimen is a square grid trimmed to the disc: the cells whose centres lie within the specimen's
radius, with the material grid's masses, springs and hinges restricted to them (``grid_masses``,
``grid_springs``, ``grid_hinges`` with a cell mask; a structural spring with one of its two cells gets half
its stiffness). The hinges are ``grid_hinges``' straight layout by default: the crossed layout (the material
grid's) let a checkerboard of up to 0.33 mm form in the drape at c/4, shortening the cloth in its plane. A_specimen is the area of those cells. The staircase edge is within one cell of the circle
and not biased inwards: the first rule tried, cells with all four corners inside, shortened the overhang by
about half a cell (at 15.77 mm spacing the grid reached only 0.142 m along the axes, and DC came out 0.437
with 8 folds against 0.354 with 12 folds at 15 mm). The pedestal is a closed mesh cylinder (``trimesh``, 256 sides) whose top face is at z = 0,
with Coulomb friction; the particles' contact radius is fixed in metres so that it does not change with the
spacing. The cloth starts flat, just above the pedestal, each particle raised by a random height below
``perturbation`` (the seed picks the start), and falls under gravity. Symplectic Euler at its stability step
(h ω_max ≤ 2 ``step_fraction``, ω_max by Gershgorin) with a drag that is a rate (``damping_rate`` [1/s] times an
interior particle's mass, the same at every spacing) advances it until, over a tenth of a second, its kinetic
energy stayed below ``settled`` [J] at every frame and no particle got ``creep_limit`` [m] or more away from where it
was at the start of it (sampled every frame, so that a specimen still swinging cannot pass at a turning point; on
the runs measured this stopped them at the same frames as the checks at the window's ends did). Kinetic
energy alone is not enough: an overdamped cloth creeps (measured at 15 mm with a per-particle drag of
2e-3 N·s/m: DC 0.357 at 1 s with 2e-8 J, 0.3285 at 3 s). The result states how far the settled state is from a
static equilibrium (``imbalance``: the force that no contact within Coulomb's cone can balance, over the weight).

Why not implicit Euler (``integrator="implicit_euler"``, the settling used before, kept to measure it): its
settled states were not equilibria, and that is what made the drape coefficient move with the spacing. A
contact here is a projection after the step. A step of implicit Euler moves each particle by
(M/h² + K)⁻¹ f, which at h ω_max ≫ 1 (about 60 at 4 substeps and spacing c) is K⁻¹ f: the springs carry a
particle's force to its neighbours, and the projection then takes back only the normal part of each contact
particle's move. The fixed point of step and projection leaves contact particles with forces that have
tangential parts of the order of K times their per-step dive, whatever the friction. Measured on the study
cloth at c (15.8 mm; force balance of the settled state in float64, gravity, springs and hinges): imbalance 200
(48 N of contact force for 0.088 N of weight), structural springs stretched up to 13 % around the rim (the
cloth pulled tight over the pedestal like a drum, 0.014 J of spring energy against 2e-4 J of bending), also
with friction 0 (0.028 J). At c/2 the same grew to springs stretched 30 % and 0.060 J, the artefact rising
with resolution as K h²/m ∝ 1/a² at a fixed step. With 64 substeps at c the spring energy fell to 8e-6 J and
the contact forces to 0.24 N. Symplectic Euler at its stability step has h²K/m = O(1) per particle and its
contact response is that particle's own: its fixed point is Coulomb's equilibrium (imbalance 0.033 at c, the
rest the 256-gon against the cylinder of ``imbalance`` and the drag of the last creep).

The shadow is the union of the triangles' projections, rasterised on square pixels of ``pixel`` [m]
(pixel centres tested against each triangle's edge functions: the area's error is of the order of the
outline's length times the pixel, 1e-4 of the area at the default). The folds are the maxima of the hem's
radius as a function of its angle around the pedestal.

Why the solve must converge: linearised implicit Euler dissipates energy only when its linear system is
solved; a conjugate-gradient solve cut off at its iteration cap leaves a residual that acts as a force of no
potential. Silk at c/2 (5.67 mm, 2293 particles, 4 steps per 1/60 s frame) stopped at the integrator's
default 100 iterations with a relative residual of 4e-4 to 2e-3 (the tolerance asked 1e-5): its kinetic
energy grew from 2.5e-5 J to 3e-4 J between 0.73 s and 0.88 s, its centre of mass rose by 8.6 mm (0.4 mJ from
nowhere) and by 1.0 s the specimen's middle had moved 12 mm sideways, on its way off the pedestal (the H200's
"slides off" at 4 and 8 substeps; more substeps lower ω h and with it the iterations needed, which is why 16
held at c/2 and not at c/4). The same run solved to 1e-7 (about 750 iterations) stays put: its middle moved
0.04 mm and its momentum stayed below 1e-6 kg·m/s up to 1.2 s (CPU).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import warp as wp
from scipy.signal import find_peaks

from .. import checks
from ..core.builder import ModelBuilder
from ..core.forces import eval_forces
from ..core.hinges import mesh_hinges
from ..core.integrators import make_integrator
from ..core.material import (
    ClothMaterial,
    grid_hinges,
    grid_masses,
    grid_springs,
    hinge_parameters,
)
from ..core.simulator import Simulator
from .omega import gershgorin_omega_max
from ..errors import ConfigError, SimulationError

GRAVITY = 9.81  # [m/s²]


class DiscCloth(NamedTuple):
    """A grid trimmed to a disc, in its own plane (centre at the origin)."""

    xy: np.ndarray  # [m], particle positions, shape [n, 2]
    faces: np.ndarray  # particle indices of the triangles, shape [t, 3]
    hem: np.ndarray  # particle indices of the outline (particles on a missing cell), shape [h]
    area: float  # [m²], the cells' total area


class Drape(NamedTuple):
    """A settled drape."""

    coefficient: float  # [-], DC
    folds: int  # maxima of the hem's radius around the pedestal
    shadow: float  # [m²]
    kinetic_energy: float  # [J], the largest over the frames of the last tenth of a second
    creep: float  # [m], the farthest any particle got from its place at the start of the last tenth of a second
    time: float  # [s] simulated
    positions: np.ndarray  # [m], shape [n, 3]
    faces: np.ndarray  # shape [t, 3]
    imbalance: float  # [-], the force no frictional contact can supply, over the specimen's weight (``imbalance``)
    substeps: int  # integrator steps per frame


def disc_grid(material: ClothMaterial, builder: ModelBuilder, *, radius: float, spacing: float,
              height: float = 0.0, contact_radius: float, perturbation: float = 0.0, seed: int = 0,
              hinges: str = "straight", folds: int = 0, fold_depth: float = 0.0, fold_from: float = 0.0) -> DiscCloth:
    """Add the trimmed-disc grid cloth of ``material`` (radius [m], spacing [m]) to ``builder``, flat at
    ``height`` [m], each particle raised by a uniform random height in [0, ``perturbation``) [m] (``seed``),
    centred on the z axis; with ``folds`` = n > 0, also lowered by ``fold_depth`` [m] × ½ (1 + cos nφ) × (r - ``fold_from``)
    / (``radius`` - ``fold_from``) beyond the radius ``fold_from`` [m] (n lobes to seed n folds). ``hinges``: "crossed" or "straight" (``grid_hinges``' layouts) or "triangles" (the triangles' own hinges
    by ``hinge_parameters``, as the material grid had before: kept to measure the difference)."""
    if hinges not in ("crossed", "straight", "triangles"):
        raise ConfigError(f"hinges must be 'crossed', 'straight' or 'triangles', got {hinges!r}")
    radius, spacing = checks.positive("radius", radius), checks.positive("spacing", spacing)
    half = math.ceil(radius / spacing)
    n = 2 * half + 1
    ticks = (np.arange(n) - half) * spacing
    x, y = np.meshgrid(ticks, ticks)
    centre = ticks[:-1] + 0.5 * spacing
    cx, cy = np.meshgrid(centre, centre)
    cells = cx**2 + cy**2 <= radius**2
    used = np.zeros((n, n), dtype=bool)
    for dr in (0, 1):
        for dc in (0, 1):
            used[dr:dr + n - 1, dc:dc + n - 1] |= cells
    index = np.full(n * n, -1)
    index[used.ravel()] = np.arange(used.sum())
    g = np.arange(n * n).reshape(n, n)

    mass = grid_masses(material, n, n, spacing, cells=cells)[used.ravel()]
    xy = np.c_[x.ravel(), y.ravel()][used.ravel()]
    z = float(height) + np.random.default_rng(seed).uniform(0.0, perturbation, len(xy))
    if folds:
        r, phi = np.hypot(xy[:, 0], xy[:, 1]), np.arctan2(xy[:, 1], xy[:, 0])
        ramp = np.clip((r - fold_from) / (radius - fold_from), 0.0, 1.0)
        z -= fold_depth * 0.5 * (1.0 + np.cos(checks.count("folds", folds, minimum=1) * phi)) * ramp
    ids = builder.add_particles(np.c_[xy, z], mass=mass, radius=contact_radius)

    k = grid_springs(material)
    # Structural springs: k_s × (cells beside it) / 2; shear springs: both diagonals of every cell.
    pad = np.zeros((n + 1, n + 1))
    pad[1:-1, 1:-1] = cells
    row_share = 0.5 * (pad[:-1, 1:-1] + pad[1:, 1:-1])  # spring (r, c) → (r, c+1): cells (r-1, c), (r, c)
    col_share = 0.5 * (pad[1:-1, :-1] + pad[1:-1, 1:])  # spring (r, c) → (r+1, c): cells (r, c-1), (r, c)
    pairs = np.concatenate([np.stack([g[:, :-1], g[:, 1:]], -1)[row_share > 0],
                            np.stack([g[:-1, :], g[1:, :]], -1)[col_share > 0]])
    share = np.concatenate([row_share[row_share > 0], col_share[col_share > 0]])
    # Rest lengths of the flat grid, not of the raised start: random heights δz would shorten the flat sheet's springs
    # by δz²/2a, a compression ∝ 1/a² (1e-3 at 2 mm with δz up to 0.1 mm).
    builder.add_springs(ids[index[pairs]], stiffness=k.structural_stiffness * share, rest_length=spacing,
                        damping=k.structural_damping * share, family="structural")
    diagonals = np.concatenate([np.stack([g[:-1, :-1], g[1:, 1:]], -1)[cells], np.stack([g[:-1, 1:], g[1:, :-1]], -1)[cells]])
    builder.add_springs(ids[index[diagonals]], stiffness=k.shear_stiffness, damping=k.shear_damping,
                        rest_length=math.sqrt(2.0) * spacing, family="shear")
    a, b, c, d = (corner[cells] for corner in (g[:-1, :-1], g[:-1, 1:], g[1:, 1:], g[1:, :-1]))
    faces = index[np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])]
    if hinges in ("crossed", "straight"):
        local, k_theta, kd_theta = grid_hinges(material, n, n, cells=cells, layout=hinges)
        local = index[local]
    else:
        flat = np.c_[xy, np.zeros(len(xy))]
        local, _ = mesh_hinges(flat, faces)
        k_theta, kd_theta = hinge_parameters(material, flat, local)
    builder.add_hinges(ids[local], stiffness=k_theta, damping=kd_theta, rest_angle=0.0)
    builder.add_triangles(ids[faces], name="specimen")
    full = np.zeros((n + 1, n + 1), dtype=bool)
    full[1:-1, 1:-1] = cells
    around = full[:-1, :-1] & full[:-1, 1:] & full[1:, :-1] & full[1:, 1:]  # the 4 cells of each point
    hem = index[(used & ~around).ravel()]
    return DiscCloth(xy, faces, hem[hem >= 0], float(cells.sum()) * spacing**2)


def shadow_area(positions, faces, *, pixel: float) -> float:
    """Area [m²] of the union of the triangles' projections on the xy plane, on pixels of side ``pixel`` [m]."""
    p = np.asarray(positions, dtype=np.float64)[:, :2]
    f = np.asarray(faces)
    lo = p.min(axis=0) - pixel
    shape = np.ceil((p.max(axis=0) + pixel - lo) / pixel).astype(int)
    covered = np.zeros(shape[::-1], dtype=bool)
    tri = p[f]  # [t, 3, 2]
    box_lo = np.floor((tri.min(axis=1) - lo) / pixel).astype(int)
    box_hi = np.ceil((tri.max(axis=1) - lo) / pixel).astype(int)
    for t in range(len(f)):
        (i0, j0), (i1, j1) = box_lo[t], box_hi[t]
        px = lo[0] + (np.arange(i0, i1) + 0.5) * pixel
        py = lo[1] + (np.arange(j0, j1) + 0.5) * pixel
        gx, gy = np.meshgrid(px, py)
        v = tri[t]
        signs = []
        for k in range(3):
            a, b = v[k], v[(k + 1) % 3]
            signs.append((b[0] - a[0]) * (gy - a[1]) - (b[1] - a[1]) * (gx - a[0]))
        s = np.stack(signs)
        inside = np.all(s >= 0.0, axis=0) | np.all(s <= 0.0, axis=0)
        covered[j0:j1, i0:i1] |= inside
    return float(covered.sum()) * pixel**2


def count_folds(positions, hem, *, bins: int = 360, smooth: int = 9, prominence: float = 2.0e-3) -> int:
    """Maxima of the hem's horizontal radius over its angle (binned, circularly smoothed over ``smooth`` bins) whose
    prominence (``scipy.signal.find_peaks``: the height above the higher of the two valleys that part it from
    higher maxima) is at least ``prominence`` [m]:
    the staircase hem of a stiff specimen that barely droops has no folds, only a few millimetres of ripple (the
    rubber sheet at c/2 counted 28 maxima without this)."""
    p = np.asarray(positions, dtype=np.float64)[np.asarray(hem)]
    angle = np.arctan2(p[:, 1], p[:, 0])
    r = np.hypot(p[:, 0], p[:, 1])
    which = np.floor((angle + np.pi) / (2 * np.pi) * bins).astype(int) % bins
    profile = np.full(bins, -np.inf)
    np.maximum.at(profile, which, r)
    filled = np.isfinite(profile)
    profile = np.interp(np.arange(bins), np.flatnonzero(filled), profile[filled], period=bins)
    kernel = np.ones(smooth) / smooth
    smooth_profile = np.convolve(np.r_[profile[-smooth:], profile, profile[:smooth]], kernel, "same")[smooth:-smooth]
    # Three turns, so that every peak of the middle one sees its neighbours across the seam.
    peaks, _ = find_peaks(np.tile(smooth_profile, 3), prominence=prominence)
    return int(np.sum((peaks >= bins) & (peaks < 2 * bins)))


def imbalance(positions, forces, mass, *, disc_radius: float, contact_radius: float, friction: float,
              rim_radius: float = 0.0, reach: float = 1.0e-4, floor: float = 0.0) -> float:
    """How far a state is from a static equilibrium on the pedestal [-]: the part of the particles' forces that
    no contact within Coulomb's cone can balance, summed over the particles and divided by the total weight.

    The contact force a particle needs is -f (``forces``: gravity, drag and the elements, at rest nothing else
    acts). A particle within ``contact_radius`` + ``reach`` [m] of the pedestal (a solid cylinder of
    ``disc_radius`` [m] with its top at z = 0 and its rim rounded to ``rim_radius`` [m]: top, side or rim) can
    receive a force g with normal part
    g_n ≥ 0 and tangential part |g_t| ≤ μ g_n; what lies outside that cone, max(|g_t| - μ g_n, -g_n, 0), is
    unbalanced, and a particle out of reach has all of |g| unbalanced; ``floor`` [N] of each particle's excess is
    not counted (the round-off of its forces). 0 for an exact equilibrium.

    Args:
        positions: [m], shape [n, 3]; forces: [N], shape [n, 3]; mass: [kg], shape [n].
    """
    p = np.asarray(positions, dtype=np.float64)
    g = -np.asarray(forces, dtype=np.float64)
    rho = np.hypot(p[:, 0], p[:, 1])
    radial = np.c_[p[:, :2] / np.maximum(rho, 1e-30)[:, None], np.zeros(len(p))]
    # In the (ρ, z) half-plane: the top (ρ ≤ R - f), the side (z ≤ -f), else the rim's quarter circle around
    # (R - f, -f) (f = 0: the sharp corner).
    inner, low = disc_radius - rim_radius, -rim_radius
    corner = (rho - inner)[:, None] * radial + [0.0, 0.0, 1.0] * (p[:, 2:] - low)
    corner_length = np.linalg.norm(corner, axis=1)
    top, side = rho <= inner, (p[:, 2] <= low) & (rho > inner)
    normal = np.where(top[:, None], [0.0, 0.0, 1.0],
                      np.where(side[:, None], radial, corner / np.maximum(corner_length, 1e-30)[:, None]))
    distance = np.where(top, p[:, 2], np.where(side, rho - disc_radius, corner_length - rim_radius))
    touching = (distance <= contact_radius + reach) & (distance > 0.0)
    g_n = np.sum(g * normal, axis=1)
    g_t = np.linalg.norm(g - g_n[:, None] * normal, axis=1)
    excess = np.where(touching, np.maximum(np.maximum(g_t - friction * g_n, -g_n), 0.0), np.linalg.norm(g, axis=1))
    return float(np.maximum(excess - floor, 0.0).sum() / (np.sum(mass) * GRAVITY))


def _check_solve(integrator, t: float) -> None:
    """Raise where the last implicit solve stopped at its iteration cap above its tolerance (module docstring)."""
    iterations, residual, rhs = integrator.solve_report()
    if iterations >= integrator.cg_iterations and residual > integrator.cg_tolerance * rhs:
        raise SimulationError(
            f"the implicit solve did not converge at t = {t:.2f} s (relative residual {residual / rhs:.1e} after "
            f"{iterations} iterations, tolerance {integrator.cg_tolerance:.0e}): a truncated solve adds energy and "
            f"the specimen can pop and slide off; raise cg_iterations or the substeps")


def _check_on_pedestal(q: np.ndarray, xy: np.ndarray, disc_radius: float, contact_radius: float, t: float,
                       substeps: int) -> None:
    """Raise where the specimen no longer rests centred on the pedestal: the particles that started over the
    pedestal's inner half must still lie over it and on its top (within 5 contact radii below it); a shadow
    of anything else is no drape. (Silk at c/2 slid off whole when its implicit solves were cut off at 100
    iterations: the module docstring; ``_check_solve`` now stops such a run first.)"""
    inner = np.hypot(xy[:, 0], xy[:, 1]) < 0.5 * disc_radius
    over = np.hypot(q[inner, 0], q[inner, 1]) < disc_radius
    on_top = q[inner, 2] > -5.0 * contact_radius
    if not (over.all() and on_top.all()):
        raise SimulationError(
            f"the specimen slid off the pedestal by t = {t:.2f} s ({int((~over | ~on_top).sum())} of the "
            f"{int(inner.sum())} particles that started over its centre left it, {substeps} substeps per frame): "
            f"its drape is not measurable")


def cusick(material: ClothMaterial, *, spacing: float, specimen_radius: float = 0.15, disc_radius: float = 0.09,
           contact_radius: float = 1.0e-3, friction: float = 0.5, perturbation: float = 1.0e-4, seed: int = 0,
           settled: float = 1.0e-6, creep_limit: float = 1.0e-4, max_time: float = 20.0, fps: int = 60,
           substeps: int | None = None, pixel: float = 2.5e-4, hinges: str = "straight", drag: float = 0.0,
           fixed_time: float | None = None, cg_tolerance: float = 1.0e-7, cg_iterations: int = 5000,
           integrator: str = "symplectic_euler", damping_rate: float = 20.0, step_fraction: float = 0.8,
           rim_radius: float = 0.0, precision: str = "float32", folds: int = 0, fold_depth: float = 5.0e-3,
           device=None) -> Drape:
    """Drape ``material`` on the pedestal and measure it (module docstring).

    ``drag`` [N·s/m] is the builder's per-particle drag (its damping rate drag / m grows as 1 / spacing²), and
    ``fixed_time`` [s] stops at that time whether settled or not: both only to reproduce runs made that way.
    ``cg_tolerance`` and ``cg_iterations``: the implicit solve's relative residual and iteration cap; the run
    raises :class:`SimulationError` where a frame's last solve stops at the cap above the tolerance.
    ``precision``: the model's, "float32" or "float64". ``folds`` = n > 0 starts the skirt with n lobes ``fold_depth``
    [m] deep at the hem (``disc_grid``), to measure the coefficient of an n-fold drape at several spacings; it may
    still settle with another number of folds (``Drape.folds`` says).
    """
    import trimesh  # optional: trimesh (the pedestal's mesh)

    if not isinstance(material, ClothMaterial):
        raise ConfigError(f"material must be a warpspring.ClothMaterial, got {type(material).__name__}")
    if integrator not in ("symplectic_euler", "implicit_euler"):
        raise ConfigError(f"integrator must be 'symplectic_euler' or 'implicit_euler', got {integrator!r}")
    damping_rate = checks.non_negative("damping_rate", damping_rate)
    if integrator == "symplectic_euler" and drag == 0.0:
        # A rate, not a per-particle coefficient: an interior particle (mass ρ_A a²) loses damping_rate of its
        # momentum per second at every spacing.
        drag = damping_rate * material.density * spacing**2
    builder = ModelBuilder(up_axis="Z", gravity=(0.0, 0.0, -GRAVITY), drag=drag)
    cloth = disc_grid(material, builder, radius=specimen_radius, spacing=spacing, height=1.5 * contact_radius,
                      contact_radius=contact_radius, perturbation=perturbation, seed=seed, hinges=hinges,
                      folds=folds, fold_depth=fold_depth, fold_from=disc_radius)
    pedestal_height = 2.0 * specimen_radius
    rim_radius = checks.non_negative("rim_radius", rim_radius)
    if rim_radius == 0.0:
        pedestal = trimesh.creation.cylinder(radius=disc_radius, height=pedestal_height, sections=256)
        centre = (0.0, 0.0, -0.5 * pedestal_height)
    elif rim_radius < disc_radius:
        # The (ρ, z) profile from the bottom's centre up the side, round the rim and in to the top's centre.
        turn = np.linspace(0.0, 0.5 * np.pi, 17)
        profile = np.r_[[[0.0, -pedestal_height], [disc_radius, -pedestal_height]],
                        np.c_[disc_radius - rim_radius + rim_radius * np.cos(turn), -rim_radius + rim_radius * np.sin(turn)],
                        [[0.0, 0.0]]]
        pedestal = trimesh.creation.revolve(profile, sections=256)
        centre = (0.0, 0.0, 0.0)
    else:
        raise ConfigError(f"rim_radius must be below disc_radius ({disc_radius} m), got {rim_radius}")
    builder.add_collider_mesh(pedestal, center=centre, friction=friction)
    model = builder.finalize(device, precision=precision)
    if integrator == "implicit_euler":
        stepper = make_integrator("implicit_euler", model, cg_tolerance=cg_tolerance, cg_iterations=cg_iterations)
        substeps = 4 if substeps is None else substeps
    else:
        stepper = make_integrator("symplectic_euler", model)
        if substeps is None:  # h ω_max ≤ 2 step_fraction, ω_max by Gershgorin (an upper bound)
            substeps = math.ceil(gershgorin_omega_max(model) / (2.0 * step_fraction * fps))
    sim = Simulator(model, integrator=stepper, fps=fps, substeps=substeps)
    mass = model.particle_mass.numpy().reshape(-1)
    window = max(1, round(0.1 * fps))  # frames in a tenth of a second
    # Sampled every frame, not at the window's ends, where a specimen swinging with a period near the window's could
    # pass both checks at a turning point.
    frames, energy, creep, peak_energy, peak_creep = 0, math.inf, math.inf, 0.0, 0.0
    start = sim.state.particle_q.numpy().astype(np.float64)
    end = max_time if fixed_time is None else fixed_time
    while frames < round(end * fps):
        sim.step_frame()
        frames += 1
        if integrator == "implicit_euler":
            _check_solve(stepper, frames / fps)
        qd = sim.state.particle_qd.numpy().astype(np.float64)
        now = sim.state.particle_q.numpy().astype(np.float64)
        peak_energy = max(peak_energy, 0.5 * float(np.sum(mass * np.sum(qd**2, axis=1))))
        peak_creep = max(peak_creep, float(np.abs(now - start).max()))
        if frames % window:
            continue
        energy, creep, peak_energy, peak_creep, start = peak_energy, peak_creep, 0.0, 0.0, now
        _check_on_pedestal(now, cloth.xy, disc_radius, contact_radius, frames / fps, substeps)
        if fixed_time is None and energy < settled and creep < creep_limit:
            break
    q = sim.state.particle_q.numpy().astype(np.float64)
    eval_forces(model, sim.state, None)
    # Round-off: a stored position is off by up to ε |x| (float32: 1.8e-8 m at 0.15 m), which moves each of a
    # particle's springs (4 structural, 4 shear) by as much at either end: at c/4 such forces reach its weight.
    springs = grid_springs(material)
    epsilon = float(np.finfo(np.float32 if model.scalar == wp.float32 else np.float64).eps)
    floor = 8.0 * (springs.structural_stiffness + springs.shear_stiffness) * epsilon * float(np.abs(q).max())
    unbalanced = imbalance(q, sim.state.particle_f.numpy(), mass, disc_radius=disc_radius, rim_radius=rim_radius,
                           contact_radius=contact_radius, friction=friction, floor=floor)
    shadow = shadow_area(q, cloth.faces, pixel=pixel)
    disc = math.pi * disc_radius**2
    return Drape((shadow - disc) / (cloth.area - disc), count_folds(q, cloth.hem), shadow, energy, creep,
                 frames / fps, q, cloth.faces, unbalanced, substeps)
