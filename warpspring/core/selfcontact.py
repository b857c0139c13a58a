"""Self-collision of the model's triangle surfaces (cloth, soft-body skins): the host side of
``kernels/selfcontact.py``.

``ModelBuilder.add_self_collision(thickness=..., friction=...)`` asks for it; the model then holds a
:class:`SelfContact` (``Model.self_contact``), and :class:`~warpspring.core.constraints.StepFinisher` runs it
last in every step of every integrator, reading the step's start and its result. Scenes without it compile
and launch none of it.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..errors import ConfigError
from ..kernels.flatten import flat_launch
from ..kernels.selfcontact import (
    COUNT_CAPPED,
    COUNT_PAIRS,
    COUNTER_COUNT,
    PARAM_COUNT,
    PARAM_FRICTION,
    PARAM_RELAXATION,
    PARAM_THICKNESS,
    Surface,
    cap_kernel,
    points_kernel,
    proximity_kernel,
    repel_kernel,
)

#: The default relaxation γ of the displacement cap: a vertex moves at most a quarter of its distance to the
#: nearest primitive, so a pair beyond the repulsion's reach (2 τ) ends a step at least τ apart.
DEFAULT_RELAXATION = 0.25
#: The thickness must stay below this share of the surface's smallest triangle altitude: at rest, a vertex and
#: a triangle of its neighbourhood that do not share it are an altitude apart or more, and must not repel.
MAX_THICKNESS_SHARE = 0.7


def check_settings(thickness: float, friction: float, relaxation: float) -> tuple[float, float, float]:
    """The three live values checked: τ > 0 [m], μ ≥ 0 [-], γ in (0, 1/2) [-]."""
    values = []
    for name, value, ok, rule in (
        ("thickness", thickness, lambda v: v > 0.0, "> 0 [m]"),
        ("friction", friction, lambda v: v >= 0.0, ">= 0"),
        ("relaxation", relaxation, lambda v: 0.0 < v < 0.5, "in (0, 0.5): the cap's proof needs γ < 1/2"),
    ):
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"self-collision {name} must be a number {rule}, got {value!r}") from None
        if not np.isfinite(value) or not ok(value):
            raise ConfigError(f"self-collision {name} must be {rule}, got {value!r}")
        values.append(value)
    return tuple(values)


def surface_topology(triangles: np.ndarray, particle_count: int) -> dict:
    """The arrays of :class:`~warpspring.kernels.selfcontact.Surface` (but the meshes) for ``triangles``
    [triangle_count, 3] of per-world particle indices, as NumPy int32 arrays (vectorised: no loop per
    element)."""
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    count = len(triangles)
    sides = np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)  # [3 · count, 2], side k of t at 3t + k
    edges, side_edge = np.unique(sides, axis=0, return_inverse=True)
    side_edge = side_edge.reshape(-1)
    triangle_edges = side_edge.reshape(count, 3)
    # Each edge (vertex) is reported by the first triangle that holds it.
    edge_owner = np.full(len(edges), -1, dtype=np.int64)
    edge_owner[side_edge[::-1]] = np.repeat(np.arange(count), 3)[::-1]
    vertex_owner = np.full(particle_count, -1, dtype=np.int64)
    vertex_owner[triangles.ravel()[::-1]] = np.repeat(np.arange(count), 3)[::-1]

    def csr(owners: np.ndarray, items: np.ndarray):
        order = np.argsort(owners, kind="stable")
        start = np.zeros(particle_count + 1, dtype=np.int64)
        np.cumsum(np.bincount(owners, minlength=particle_count), out=start[1:])
        return start, items[order]

    tri_start, tri_list = csr(triangles.ravel(), np.repeat(np.arange(count), 3))
    edge_start, edge_list = csr(edges.ravel(), np.repeat(np.arange(len(edges)), 2))
    as32 = lambda a: np.ascontiguousarray(a, dtype=np.int32)  # noqa: E731
    return dict(triangle=as32(triangles), triangle_edges=as32(triangle_edges), edge=as32(edges),
                edge_owner=as32(edge_owner), vertex_owner=as32(vertex_owner), vertex_triangle_start=as32(tri_start),
                vertex_triangle=as32(tri_list), vertex_edge_start=as32(edge_start), vertex_edge=as32(edge_list))


def smallest_altitude(positions: np.ndarray, triangles: np.ndarray) -> float:
    """The smallest altitude [m] of the triangles (twice the area over the longest side), float64."""
    x = np.asarray(positions, dtype=np.float64)[np.asarray(triangles)]
    doubled_area = np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)
    longest = np.max(np.linalg.norm(x - np.roll(x, 1, axis=1), axis=2), axis=1)
    return float(np.min(doubled_area / np.maximum(longest, 1e-300))) if len(x) else np.inf


class SelfContact:
    """Self-collision of a model's triangle surface: the BVHs, the live values and the counters.

    Attributes:
        triangle_count: triangles of the colliding surface (per world).
        edge_count: its unique edges.
        params: live values per world, shape [world_count, 3] in the model's precision: thickness τ [m],
            friction μ [-], relaxation γ [-] (``kernels/selfcontact.py`` PARAM_*); write through :meth:`set`.
        counters: int32, shape [world_count, 2]: pairs pushed apart and vertices capped, summed over the steps
            since the model was made or :meth:`reset`.
    """

    def __init__(self, model, triangles: np.ndarray, *, thickness: float, friction: float, relaxation: float):
        self.model = model
        n, worlds, device = model.particle_count, model.world_count, model.device
        topology = surface_topology(triangles, n)
        self.triangle_count = len(topology["triangle"])
        self.edge_count = len(topology["edge"])
        surface = Surface()
        for name, values in topology.items():
            dtype = {"triangle": wp.vec3i, "triangle_edges": wp.vec3i, "edge": wp.vec2i}.get(name, wp.int32)
            setattr(surface, name, wp.array(values, dtype=dtype, device=device))
        # One BVH per world over single-precision copies of the step's start positions, built at the model's
        # initial positions (its topology follows them: built on coincident points it would degenerate into a
        # list) and refit every step.
        self.points = wp.array(model.particle_q.numpy().astype(np.float32), dtype=wp.vec3f, device=device)
        indices = wp.array(topology["triangle"].ravel(), dtype=wp.int32, device=device)
        self.meshes = [wp.Mesh(points=self.points[w * n:(w + 1) * n], indices=indices) for w in range(worlds)]
        surface.mesh = wp.array(np.array([m.id for m in self.meshes], dtype=np.uint64), dtype=wp.uint64,
                                device=device)
        self.surface = surface
        self.params = wp.zeros((worlds, PARAM_COUNT), dtype=model.scalar, device=device)
        self.set(thickness=thickness, friction=friction, relaxation=relaxation)
        self.corrected = wp.zeros(model.state_size, dtype=model.vec3, device=device)
        self.counters = wp.zeros((worlds, COUNTER_COUNT), dtype=wp.int32, device=device)

    def set(self, *, thickness: float | None = None, friction: float | None = None,
            relaxation: float | None = None, world: int | None = None) -> None:
        """Write live values (in every world, or in ``world``): read by the next step, nothing compiles and a
        captured graph stays valid.

        Args:
            thickness: τ [m], > 0: the separation the repulsion keeps between the surface's layers.
            friction: μ [-], ≥ 0: Coulomb friction between layers in contact.
            relaxation: γ [-] in (0, 1/2): each vertex moves at most γ times its distance to the nearest
                primitive per step.
        """
        current = self.params.numpy()
        rows = range(self.model.world_count) if world is None else [int(world)]
        for row in rows:
            old = current[row]
            tau, mu, gamma = check_settings(
                old[PARAM_THICKNESS] if thickness is None else thickness,
                old[PARAM_FRICTION] if friction is None else friction,
                old[PARAM_RELAXATION] if relaxation is None else relaxation,
            )
            current[row, [PARAM_THICKNESS, PARAM_FRICTION, PARAM_RELAXATION]] = (tau, mu, gamma)
        self.params.assign(current)
        self.model.input_version += 1

    @property
    def thickness(self) -> float:
        """World 0's thickness τ [m]."""
        return float(self.params.numpy()[0, PARAM_THICKNESS])

    def counts(self) -> dict[str, np.ndarray]:
        """Per world, summed since the start or :meth:`reset`: ``pairs`` pushed apart by the repulsion and
        ``capped`` vertices (int64 arrays [world_count]; reads the device)."""
        counters = self.counters.numpy().astype(np.int64)
        return {"pairs": counters[:, COUNT_PAIRS], "capped": counters[:, COUNT_CAPPED]}

    def reset(self) -> None:
        """Zero the counters."""
        self.counters.zero_()

    def history(self) -> list:
        """The device arrays one step leaves to the next: the counters."""
        return [self.counters]

    @property
    def capturable(self) -> bool:
        """Whether a step with self-collision can be captured in a graph: on CUDA (the BVH refit is device work),
        not on the CPU (Warp refits a CPU mesh on the host, outside what its CPU graphs record)."""
        return self.model.device.is_cuda

    def refit(self, positions: wp.array) -> None:
        """Bring every world's BVH to ``positions`` (a state's ``particle_q``)."""
        model = self.model
        wp.launch(points_kernel(model.scalar), dim=model.particle_dim, block_dim=model.block_dim,
                  inputs=[positions], outputs=[self.points], device=model.device)
        for mesh in self.meshes:
            mesh.refit()

    def proximity(self, state, reach: float) -> tuple[np.ndarray, np.ndarray]:
        """The device's broad and narrow phase at ``state``, for audits: per particle of every world, the
        distance [m] to the nearest vertex–triangle or edge–edge pair it belongs to within ``reach`` [m]
        (``reach`` when none) and how many such pairs there are (-1 off the surface); NumPy arrays
        [world_count · particle_count]."""
        model = self.model
        self.refit(state.particle_q)
        nearest = wp.empty(model.state_size, dtype=model.scalar, device=model.device)
        count = wp.empty(model.state_size, dtype=wp.int32, device=model.device)
        flat_launch(proximity_kernel(model.scalar),
                    inputs=[model.particle_count, model.particle_flags, model.particle_inv_mass, self.surface,
                            state.particle_q, model.scalar(reach)],
                    outputs=[nearest, count], dim=model.particle_dim, block_dim=model.block_dim, device=model.device)
        return nearest.numpy().astype(np.float64), count.numpy()

    def __call__(self, state_in, state_out, dt: float) -> None:
        """Make ``state_out`` (the integrator's result from ``state_in``) free of self-intersections: refit the
        BVHs at ``state_in``, repel, cap (device work only: capturable)."""
        model = self.model
        common = dict(dim=model.particle_dim, block_dim=model.block_dim, device=model.device)
        self.refit(state_in.particle_q)
        shared = dict(
            particle_count=model.particle_count,
            particle_flags=model.particle_flags,
            particle_inv_mass=model.particle_inv_mass,
            world_enabled=model.world_enabled,
            surface=self.surface,
            params=self.params,
            particle_q_start=state_in.particle_q,
        )
        flat_launch(repel_kernel(model.scalar), inputs=[*shared.values(), state_out.particle_q],
                    outputs=[self.corrected, self.counters], **common)
        flat_launch(cap_kernel(model.scalar), inputs=[*shared.values(), self.corrected, model.scalar(dt)],
                    outputs=[state_out.particle_q, state_out.particle_qd, self.counters], **common)


def make_self_contact(model, triangles: np.ndarray, positions: np.ndarray, settings: dict) -> SelfContact:
    """The model's :class:`SelfContact` for ``triangles`` (per-world particle indices) at rest ``positions``,
    or a ConfigError when the thickness does not fit the mesh."""
    thickness, friction, relaxation = check_settings(settings["thickness"], settings["friction"],
                                                     settings["relaxation"])
    if len(triangles) == 0:
        raise ConfigError("self-collision needs triangles: add a cloth or a mesh before add_self_collision")
    altitude = smallest_altitude(positions, triangles)
    if thickness >= MAX_THICKNESS_SHARE * altitude:
        raise ConfigError(
            f"self-collision thickness {thickness:.4g} m is too large for the mesh: its smallest triangle altitude "
            f"is {altitude:.4g} m, so neighbouring elements would repel at rest; use a thickness below "
            f"{MAX_THICKNESS_SHARE * altitude:.4g} m or a coarser mesh"
        )
    return SelfContact(model, triangles, thickness=thickness, friction=friction, relaxation=relaxation)
