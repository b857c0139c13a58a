"""Wind on cloth triangles, on the host: the aerodynamic family (``kernels/aero.py`` has the model and the
kernels' hooks) built from a model's cloth meshes by :meth:`ModelBuilder.add_aerodynamics`.

The wind itself is a live input of the model, per world: ``wind`` [m/s] (a constant or a keyframe track,
gusts as a time series), ``air_density`` [kg/m³] and ``wind_noise`` [-] (the relative amplitude of a
spatial Perlin noise of length scale ``noise_scale`` [m] and a seed fixed when the model is built).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .. import checks
from ..errors import ConfigError
from ..kernels.aero import AeroSpec, aero_arrays_type
from .families import ElementFamily, build_incidence, incidence_bytes

#: Default coefficients: C_D of a flat square plate normal to the flow (Hoerner, "Fluid-Dynamic Drag",
#: 1965: 1.17 at high Reynolds numbers) and a lift coefficient of the same order (a tuning value: cloth
#: flutters and is porous, so measured values vary widely).
DEFAULT_DRAG = 1.2
DEFAULT_LIFT = 1.0
#: The density of air at sea level and 20 °C [kg/m³].
AIR_DENSITY = 1.204
#: Triangles per world from which a noisy wind's forces are precomputed per triangle by default (measured on
#: an H100: 60 % of a substep instead of 68 % at 1024² (2 M triangles), no gain at 256²).
PRECOMPUTE_TRIANGLES = 1 << 20


class AeroFamily(ElementFamily):
    """Drag and lift of the wind on triangles of three particles (see ``kernels/aero.py``).

    Args:
        triangles: the particles of each triangle, per-world indices, shape [t, 3].
        drag, lift: C_D and C_L [-], ≥ 0: numbers, or one per triangle, shape [t].
        noise_scale: length scale L [m] of the wind's spatial noise; 0: no noise (compiled out).
        seed: the noise's seed.
        precompute: compute each triangle's force once per force evaluation in a pass of its own and gather
            it (one launch and one array more, a third of the arithmetic); ``None``: only with noise and from
            ``PRECOMPUTE_TRIANGLES`` triangles, where it pays (bench/RESULTS.md §14: without noise the
            corners' own evaluation is as fast or faster at every size).
    """

    name = "wind triangles"
    does_work = True
    moves_air = True  # the model's air moves: viscous drag acts relative to the wind

    def __init__(self, triangles, *, drag=DEFAULT_DRAG, lift=DEFAULT_LIFT, noise_scale: float = 0.0, seed: int = 0,
                 precompute: bool | None = None):
        self.triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        count = len(self.triangles)
        if count == 0:
            raise ConfigError("aerodynamics needs triangles: add a cloth (a grid or a mesh) first")
        self.drag = _coefficient("drag coefficient", drag, count)
        self.lift = _coefficient("lift coefficient", lift, count)
        self.noise_scale = checks.non_negative("wind noise_scale", noise_scale)
        self.seed = checks.count("wind noise seed", seed, minimum=0)
        self.precompute = (count >= PRECOMPUTE_TRIANGLES and self.noise_scale > 0.0 if precompute is None
                           else bool(precompute))

    @property
    def element_count(self) -> int:
        return len(self.triangles)

    def device_bytes(self, particle_count: int, scalar_bytes: int, worlds: int) -> int:
        """Indices, C_D and C_L per triangle, the noise's scale and seed, and the incidence table."""
        cache = 3 * scalar_bytes * (worlds * len(self.triangles) if self.precompute else 1)
        return ((12 + 2 * scalar_bytes) * len(self.triangles) + scalar_bytes + 4 + cache
                + incidence_bytes(self.triangles, particle_count))

    def finalize(self, model) -> None:
        device, scalar = model.device, model.scalar
        corners = np.broadcast_to(np.arange(3), self.triangles.shape)
        self.incidence, self.shape = build_incidence(self.triangles, model.particle_count, corners, -1,
                                                     device=device)
        self._indices = wp.array(self.triangles.astype(np.int32), dtype=wp.vec3i, device=device)
        self._drag = wp.array(self.drag[None, :], dtype=scalar, device=device)
        self._lift = wp.array(self.lift[None, :], dtype=scalar, device=device)
        self._noise_scale = wp.array([self.noise_scale or 1.0], dtype=scalar, device=device)
        self._seed = wp.array([self.seed], dtype=wp.int32, device=device)
        self._triangle_force = wp.zeros(model.world_count * len(self.triangles) if self.precompute else 1,
                                        dtype=model.vec3, device=device)

    def damping_rates(self, model, positions: np.ndarray) -> np.ndarray:
        """Per particle, a third of the largest eigenvalue of D_u = ½ρA(C_D|u·n| I + (C_D + C_L)|u| n nᵀ) of
        each of its triangles, at rest in the current wind (``kernels/aero.py``): the damping of the cloth's
        smooth motions, where a triangle's corners move together (the wind's noise amplitude raises |u|)."""
        wind = model.world_values("wind")
        rho = model.world_values("air_density")[:, 0]
        gust = 1.0 + model.world_values("wind_noise")[:, 0]
        tri = self.triangles
        rates = np.zeros((model.world_count, model.particle_count))
        for w in range(model.world_count):
            x = positions[w][tri]
            cross = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
            area = 0.5 * np.linalg.norm(cross, axis=1)
            n = cross / np.maximum(2.0 * area, 1e-300)[:, None]
            u = wind[w] * gust[w]
            speed = np.linalg.norm(u)
            top = 0.5 * rho[w] * area * (self.drag * np.abs(n @ u) + (self.drag + self.lift) * speed)
            for corner in range(3):
                np.add.at(rates[w], tri[:, corner], top / 3.0)
        return rates

    def spec(self, model, *, linear: bool = False) -> AeroSpec:
        return AeroSpec(incidence=self.shape, noise=self.noise_scale > 0.0, precomputed=self.precompute)

    def time_dependent(self, model) -> bool:
        """Only where precomputed (each corner's gather otherwise evaluates its triangles' forces itself)."""
        return self.precompute

    def at_time(self, model, state) -> None:
        """Where precomputed: each triangle's force at ``state``, before the corners gather it."""
        if not self.time_dependent(model):
            return
        spec = self.spec(model)
        wp.launch(spec.funcs(model.scalar).triangle_forces, dim=(model.world_count, len(self.triangles)),
                  inputs=[model.particle_count, model.inputs, state.particle_q, state.particle_qd, self.arrays(model)],
                  device=model.device)

    def arrays(self, model, *, stiffness=None):
        arrays = aero_arrays_type(model.scalar)()
        arrays.indices = self._indices
        arrays.drag = self._drag
        arrays.lift = self._lift
        arrays.noise_scale = self._noise_scale
        arrays.noise_seed = self._seed
        arrays.triangle_force = self._triangle_force
        arrays.incidence = self.incidence
        return arrays

    def gershgorin_rows(self, model, free: np.ndarray, stiffness: np.ndarray | None = None) -> np.ndarray:
        """The family's stiffness matrix is zero (``kernels/aero.py``): it adds nothing to the bound."""
        return np.zeros((model.world_count, model.particle_count))

    def describe_element(self, model, element: int) -> str:
        a, b, c = self.triangles[element]
        return f"wind triangle {element} (particles {a}, {b}, {c})"


def _coefficient(name: str, value, count: int) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64)
    if v.ndim == 0:
        v = np.full(count, float(v))
    if v.shape != (count,):
        raise ConfigError(f"the {name} must be a number or one per triangle, shape ({count},), got shape {v.shape}")
    bad = np.flatnonzero(~np.isfinite(v) | (v < 0.0))
    if len(bad):
        raise ConfigError(f"the {name} must be finite and >= 0, got {v[bad[0]]} (triangle {int(bad[0])})")
    return v
