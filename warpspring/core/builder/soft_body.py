"""The builder's soft-body recipe: :meth:`SoftBodyRecipes.add_soft_body` makes a body from a closed mesh by one of
the topologies of :mod:`warpspring.core.soft_topologies`, its elasticity carried by springs or by neo-Hookean tets
(:mod:`warpspring.core.neohookean`), optionally with the tet volume term (:mod:`warpspring.core.volume`)."""

from __future__ import annotations

import os
import time
from collections.abc import Mapping

import numpy as np

from ... import checks
from ...errors import ConfigError
from .. import soft_topologies, softbody, tet10
from ..mesh_files import USD_EXTENSIONS, load_mesh_file, read_usd_mesh
from ..neohookean import ELASTICITIES, add_neohookean_term, poisson
from ..records import SkinGroup
from ..soft_topologies import METHODS
from ..springs import SpringPlasticity
from ..volume import add_volume_term
from .arguments import RESERVED_PRIM_NAMES, _indices, _points


class SoftBodyRecipes:
    """The soft-body recipe of :class:`~warpspring.core.builder.ModelBuilder` (a mixin: it uses the builder's
    particles, springs and families)."""

    def add_soft_body(
        self,
        mesh,
        *,
        method: str = "voxel",
        youngs_modulus: float,
        density: float | None = None,
        mass: float | None = None,
        spacing: float | None = None,
        damping: float = 0.0,
        origin=(0.0, 0.0, 0.0),
        rotation=(0.0, 0.0, 0.0, 1.0),
        scale: float = 1.0,
        velocity=(0.0, 0.0, 0.0),
        radius: float | None = None,
        mass_distribution: str = "volume",
        mass_weights=None,
        skin_mass_factor: float = 1.0,
        mass_gradient=(0.0, 0.0, 0.0),
        options: Mapping | None = None,
        name: str | None = None,
        prim: str | None = None,
        plasticity: SpringPlasticity | None = None,
        volume: bool = False,
        bulk_modulus: float | None = None,
        elasticity: str = "springs",
        poisson_ratio: float = 0.25,
        element: str = "tet4",
    ):
        """Add a soft body made from a closed mesh by one of the seven mass-spring topologies.

        The topology, its springs' stiffness from E and the particles' volume shares come from
        :mod:`warpspring.core.soft_topologies` (where each method and each E → k mapping is stated). The mesh as
        authored (its faces, UVs, face sets) is exported as a USD mesh whose vertices follow the particles
        through the method's embedding weights (:class:`~warpspring.core.records.SkinGroup`).

        Args:
            mesh: a ``trimesh.Trimesh``, a file trimesh reads (OBJ, STL, PLY, GLB, ...) or a USD file (``prim``
                chooses its mesh). Vertices at one position are welded for the topology (a seam does not split
                the body); the export keeps the authored vertices.
            method: ``"brute_force"``, ``"voxel"``, ``"grid"``, ``"scaffold"``, ``"shell"``, ``"tetrahedral"``
                (needs ``pip install warpspring[tet]``) or ``"delaunay"``; all but brute force and scaffold need a
                closed (watertight) mesh.
            youngs_modulus: E [Pa], > 0.
            density: ρ [kg/m³] (the mass is ρ × the mesh's volume: a closed mesh); or ``mass``: total [kg].
            spacing: the method's resolution [m] (voxel pitch, grid spacing, tet edge length, Poisson-disk
                radius); default a sixth of the largest extent.
            damping: stiffness-proportional damping β [s], ≥ 0: each spring's kd = β·ke [N·s/m] (a mode of
                angular frequency ω is damped by ζ = βω/2 whatever the resolution).
            origin, rotation, scale: placement; world = origin + rotation · (scale · vertex).
            velocity: initial velocity [m/s].
            radius: particles' contact radius [m]; default a quarter of the mean spring length.
            mass_distribution: ``"volume"`` (each particle's volume share) or ``"uniform"``.
            mass_weights, skin_mass_factor, mass_gradient: relative weights per particle (an array or a function
                of the rest positions), a factor on the particles the surface follows (a heavier skin), a linear
                bias g [1/m] (weights × (1 + g·(x − centroid)): a body heavier on one side rights itself); see
                :func:`~warpspring.core.softbody.distribute_mass`. Positions are in the mesh's scaled frame.
            options: the method's own options (``body_diagonals``, ``neighbours``, ``ties``, ``scaffold``,
                ``thickness``, ``epsilon``, ``optimize``, ``seed``, ``max_vertices``, ...).
            name: the exported mesh's name (``None``: a USD mesh prim's own name, else ``"soft_body"``); the spring
                families are ``<name>_<group>``.
            prim: for a USD file, the path of the mesh prim to read.
            plasticity: how every spring of the body yields and breaks (:class:`SpringPlasticity`, its limits
                per spring, e.g. ``yield_strain``); default: elastic.
            volume: add a bulk energy ½ K V₀ (J − 1)² per tet on the signed volume (the tet volume family,
                :mod:`warpspring.core.volume`), for the ``"tetrahedral"`` and ``"delaunay"`` methods (their tets).
                Use it when the body meets strains beyond ~10 % (a drop, a squash, a soft jelly under its own
                weight): springs alone do not resist a change of volume, and tets pushed through themselves stay
                inverted (``bench/RESULTS.md`` §18b, §18d). It raises the body's bulk stiffness, so the
                stable step shrinks and E in tension grows (measured on a bar at the default K: by 11–14 %
                for tetrahedral bodies, ν from ~0.27 to ~0.39; by 19–20 % for Delaunay ones).
            bulk_modulus: the term's K [Pa], > 0; default E / (3(1 − 2ν)) = 2E/3 at the networks' ν = 1/4. Its
                damper has kd = ``damping`` × K [Pa·s]. Live per world after finalize
                (``VolumeFamily.set_values``).
            elasticity: what carries the body's elasticity: ``"springs"`` (the method's spring network), or, for the
                ``"tetrahedral"`` and ``"delaunay"`` methods, ``"neohookean"``: the tets carry it as the energy
                V₀[μ/2 (I_C − 3) + λ/2 (J − 1 − μ/λ)²] per tet (the neo-Hookean family,
                :mod:`warpspring.core.neohookean`), whose linearisation at rest is linear elasticity of (E, ν) and
                passes the patch test; no springs are made (masses as with springs). Its damper (β = ``damping``) acts
                on the strain rate: at rest it is Rayleigh's −β K v, and it spares rigid motions. Live per world
                after finalize (``NeoHookeanFamily.set_values``).
            poisson_ratio: ν of the ``"neohookean"`` material, in (−1, ½) (the spring networks are fixed at ¼).
            element: the tets that carry a ``"neohookean"`` body: ``"tet4"`` (linear: the method's tets) or ``"tet10"``
                (quadratic: a particle added at the middle of every tet edge, four Gauss points per element,
                :mod:`warpspring.core.tet10`). Linear tets lock in bending: a cantilever at 3 tets across its thickness
                is ~18 % too stiff with them and within 1 % with T10s, which cost more per element and add about as
                many particles as the body has tets (``bench/results/softbody_tet10.md``). Masses are lumped (HRZ:
                1/36 of a tet's mass at each corner, 4/27 at each mid-edge node) and the surface follows the
                quadratic field. Live per world after finalize (``QuadraticTetFamily.set_values``).

        Returns:
            A :class:`~warpspring.core.softbody.SoftBody`: the particles and springs added, per group counts,
            the embedding, the E → k rule, for tets the sliver report, and with ``volume`` the family's tets.
        """
        import trimesh  # trimesh loads lazily

        started = time.perf_counter()
        source = os.fspath(mesh) if isinstance(mesh, (str, os.PathLike)) else name or "soft_body"
        neohookean = _elasticity(elasticity, poisson_ratio, method=method, volume=volume, bulk_modulus=bulk_modulus,
                                 plasticity=plasticity, source=name or "soft_body")
        quadratic = _element(element, neohookean=neohookean, source=name or "soft_body")
        uv = polygons = dressing = None
        face_sets = {}
        usd = isinstance(mesh, (str, os.PathLike)) and os.fspath(mesh).lower().endswith(USD_EXTENSIONS)
        if prim is not None and not usd:
            raise ConfigError(f"prim= chooses a mesh of a USD file ({', '.join(USD_EXTENSIONS)}), not of {mesh!r}")
        if usd:
            read = read_usd_mesh(mesh, prim=prim, up_axis=self.up_axis)
            vertices, faces = read.vertices, read.triangles
            polygons, face_sets, dressing = (read.polygon_counts, read.polygon_indices), read.face_sets, read.dressing
        else:
            if isinstance(mesh, (str, os.PathLike)):
                mesh = load_mesh_file(mesh, what="soft-body mesh")
            if not isinstance(mesh, trimesh.Trimesh):
                raise ConfigError(f"a soft body's mesh must be a trimesh.Trimesh or a mesh file, got {type(mesh).__name__}")
            vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)
            visual_uv = getattr(getattr(mesh, "visual", None), "uv", None)
            if visual_uv is not None and len(visual_uv) == len(vertices):
                uv = np.asarray(visual_uv, dtype=np.float64)
        name = (dressing.prim_name if dressing is not None else "soft_body") if name is None else name
        vertices = _points("soft-body mesh vertices", vertices)
        faces = np.asarray(faces)
        if len(vertices) == 0 or faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise ConfigError(f"{source}: a soft body needs a triangle mesh with at least one face, got faces of "
                              f"shape {faces.shape}")
        faces = _indices("mesh face vertex", faces, len(vertices)).reshape(-1, 3)
        scale = checks.positive("scale", scale)
        welded, first, inverse = np.unique(vertices * scale, axis=0, return_index=True, return_inverse=True)
        body = trimesh.Trimesh(welded, inverse.reshape(-1)[faces], process=False, validate=False)

        if (mass is None) == (density is None):
            raise ConfigError("give exactly one of density= (kg/m³) or mass= (total, kg) for a soft body")
        if options is not None and not isinstance(options, Mapping):
            raise ConfigError(f"a soft body's options must be a mapping of the method's options, got {options!r}")
        if method in soft_topologies.METHODS:  # (an unknown method is refused by build_topology)
            planned = soft_topologies.estimate_topology(body, method, spacing=spacing, **dict(options or {}))
            self._check_room(
                f"{source}: a {method} soft body at spacing {spacing if spacing is not None else 'default'} "
                f"(~{planned.particles:,} particles, {planned.springs:,} springs"
                + (f", {planned.tets:,} tets)" if planned.tets else ")"),
                # T10: a particle per tet edge too, about as many as vertices plus tets (Euler's formula)
                particles=planned.particles + (planned.particles + planned.tets if quadratic else 0),
                springs=0 if neohookean else planned.springs, temporary=planned.host,
                remedy="use a larger spacing (memory grows as 1/spacing³) or a smaller body")
        topology = soft_topologies.build_topology(body, method, youngs_modulus=checks.positive("youngs_modulus", youngs_modulus),
                                           spacing=spacing, source=source, **dict(options or {}))
        if quadratic:
            topology = tet10.quadratic_topology(topology)
        if mass is None:
            if not body.is_watertight:
                raise ConfigError(f"{source}: density= needs the mesh's volume, and an open mesh has none: give mass= "
                                  "(total, kg)")
            mass = checks.positive("density", density) * float(body.volume)
        masses = softbody.distribute_mass(topology, checks.positive("mass", mass), distribution=mass_distribution,
                                          weights=mass_weights, skin_factor=skin_mass_factor, gradient=mass_gradient)
        beta = checks.non_negative("damping", damping)

        lengths = np.concatenate([np.linalg.norm(topology.positions[p[:, 1]] - topology.positions[p[:, 0]], axis=1)
                                  for p, _ in topology.springs.values()] or [np.ones(1)])
        ids = self.add_particles(
            self._place(topology.positions, origin, rotation),
            velocities=np.broadcast_to(checks.vector("velocity", velocity), (topology.particle_count, 3)),
            mass=masses,
            radius=(0.125 if quadratic else 0.25) * float(lengths.mean()) if radius is None else radius,
        )
        name = self._unique_name(name, [m.name for m in self._meshes] + [k.name for k in self._skins]
                                 + [e.name for e in self._emitters] + list(RESERVED_PRIM_NAMES))
        springs = {}
        for group, (pairs, ke) in topology.springs.items():
            if len(pairs) and not neohookean:
                springs[group] = self.add_springs(ids[pairs], stiffness=ke, damping=beta * ke, family=f"{name}_{group}",
                                                  plasticity=plasticity)
        skin = SkinGroup(
            name=name,
            indices=ids[topology.skin_indices][inverse.reshape(-1)],
            weights=topology.skin_weights[inverse.reshape(-1)],
            faces=faces.astype(np.int32),
            uvs=uv,
            polygon_counts=None if polygons is None else np.asarray(polygons[0], dtype=np.int32),
            polygon_indices=None if polygons is None else np.asarray(polygons[1], dtype=np.int32),
            face_sets={checks.identifier("face set name", k): np.asarray(v, dtype=np.int32) for k, v in face_sets.items()},
            dressing=dressing,
        )
        self._skins.append(skin)
        volume_tets = None
        if volume or bulk_modulus is not None:
            volume_tets = add_volume_term(self, topology, ids, volume=volume, method=method, youngs_modulus=youngs_modulus,
                                          bulk_modulus=bulk_modulus, damping=beta, source=name)
        elastic_tets = None
        if quadratic:
            elastic_tets = tet10.add_tet10_term(self, topology, ids, youngs_modulus=youngs_modulus,
                                                poisson_ratio=poisson_ratio, damping=beta, source=name)
        elif neohookean:
            elastic_tets = add_neohookean_term(self, topology, ids, method=method, youngs_modulus=youngs_modulus,
                                               poisson_ratio=poisson_ratio, damping=beta, source=name)
        return softbody.SoftBody(
            name=name, method=method, particles=ids, springs=springs, skin=skin,
            stiffness_rule=(f"{'quadratic (T10) ' if quadratic else ''}neo-Hookean tets (E = {float(youngs_modulus):g} Pa, "
                            f"ν = {float(poisson_ratio):g}), no springs" if neohookean else topology.stiffness_rule),
            youngs_modulus=float(youngs_modulus), mass=float(masses.sum()), slivers=topology.slivers,
            topology=topology, build_seconds=time.perf_counter() - started, volume_tets=volume_tets,
            elasticity=elasticity, elastic_tets=elastic_tets, element=element if neohookean else "tet4",
        )


def _element(element, *, neohookean: bool, source: str) -> bool:
    """Check a soft body's ``element=`` (one-line ConfigErrors); whether its tets are quadratic."""
    if element not in tet10.ELEMENTS:
        raise ConfigError(f"{source}: element must be one of {', '.join(tet10.ELEMENTS)}, got {element!r}")
    if element == "tet10" and not neohookean:
        raise ConfigError(f"{source}: element='tet10' is a neo-Hookean element: give elasticity='neohookean' with it")
    return element == "tet10"


def _elasticity(elasticity, poisson_ratio, *, method: str, volume, bulk_modulus, plasticity, source: str) -> bool:
    """Check a soft body's ``elasticity=`` and ``poisson_ratio=`` before its topology is built (one-line
    ConfigErrors); whether the neo-Hookean tets carry it."""
    if elasticity not in ELASTICITIES:
        raise ConfigError(f"{source}: elasticity must be one of {', '.join(ELASTICITIES)}, got {elasticity!r}")
    nu = poisson(poisson_ratio, source)
    if elasticity == "springs":
        if nu != 0.25:
            raise ConfigError(f"{source}: poisson_ratio={poisson_ratio!r} is the neo-Hookean material's (a spring "
                              "network is fixed at 0.25): give elasticity='neohookean' with it")
        return False
    if method in METHODS and method not in ("tetrahedral", "delaunay"):  # an unknown method: build_topology names it
        raise ConfigError(f"{source}: elasticity='neohookean' needs tets, which the {method} method does not make: use "
                          "method='tetrahedral' or 'delaunay'")
    if volume or bulk_modulus is not None:
        raise ConfigError(f"{source}: the neo-Hookean tets already carry the bulk stiffness (λ of E and ν): drop "
                          "volume=/bulk_modulus=")
    if plasticity is not None:
        raise ConfigError(f"{source}: plasticity= acts on springs, and a neo-Hookean body has none")
    return True
