"""The builder's cloth recipes: triangles over particles (:meth:`ClothRecipes.add_triangles`), rectangular cloth
grids (:meth:`ClothRecipes.add_cloth_grid`) and cloth from any triangle or polygon mesh
(:meth:`ClothRecipes.add_cloth_mesh`), with their pins, seam welding, dihedral hinges and the check that a grid
fits in host memory before it is made."""

from __future__ import annotations

import math
import os

import numpy as np

from ... import checks
from ...errors import ConfigError
from .. import memory
from ..bending import DihedralMaterial
from ..hinges import mesh_hinges
from ..material import (ClothMaterial, edge_springs, grid_hinges, grid_masses, grid_springs, hinge_parameters,
                        lumped_masses)
from ..mesh_counts import mesh_file_counts
from ..mesh_files import USD_EXTENSIONS, load_mesh_file, read_usd_mesh
from ..records import MeshGroup
from .arguments import RESERVED_PRIM_NAMES, _indices, _points
from .spring_materials import DEFAULT_BEND, DEFAULT_SHEAR, DEFAULT_STRUCTURAL, SpringMaterial, spring_family

#: Host bytes of the temporaries of making a cloth grid, per spring and per particle (measured; see
#: ``ModelBuilder._check_grid_room``).
GRID_TEMPORARY_PER_SPRING = 72
GRID_TEMPORARY_PER_PARTICLE = 48
#: Host bytes per triangle of making a cloth from a mesh beyond the builder's arrays (welding, trimesh's edge
#: and adjacency tables, the springs' checks; measured ~370 B on a 318k-triangle sheet and ~530 B on a 179k one,
#: ~930 B with dihedral hinges: ``bench/memory.py``), and of trimesh reading a mesh file (measured ~166 B per
#: OBJ face).
MESH_TEMPORARY_PER_TRIANGLE = 600
MESH_HINGE_TEMPORARY_PER_TRIANGLE = 1200
MESH_LOAD_PER_FACE = 200

_GRID_PINS = ("top-left", "top-right", "bottom-left", "bottom-right", "top", "bottom", "left", "right")


class ClothRecipes:
    """The cloth recipes of :class:`~warpspring.core.builder.ModelBuilder` (a mixin: it uses the builder's
    particles, springs and hinges)."""

    def add_triangles(self, faces, *, name: str = "mesh", uvs=None, polygon_counts=None, polygon_indices=None,
                      face_sets=None, dressing=None) -> MeshGroup:
        """Add a triangle mesh over existing particles (exported as one USD mesh; later used by
        aerodynamics and collisions).

        Args:
            faces: global particle indices, shape [t, 3].
            name: mesh name; made unique and a valid USD identifier.
            uvs: texture coordinates per referenced particle in ascending index order, shape [v, 2];
                or per triangle corner, shape [t, 3, 2] (a mesh with UV seams: one particle, two UVs).
            polygon_counts, polygon_indices: the authored faces the triangles come from, written to USD in
                their place (quads stay quads): vertices per face, shape [p], each ≥ 3, and their global
                particle indices, shape [polygon_counts.sum()]; they must use the triangles' particles.
                Not with per-corner ``uvs``.
            face_sets: named subsets of the authored faces (or of the triangles without polygons), kept on
                export as USD face sets: a mapping name -> face indices.
            dressing: a :class:`~warpspring.core.usd_dressing.UsdDressing` (what the USD prim the mesh was read
                from carries besides its geometry) to write back on export, with ``polygon_counts`` given
                as authored and the particles in the prim's point order; ``None``: none.
        """
        faces = np.asarray(faces)
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise ConfigError(f"triangles must have shape [t, 3] with t > 0, got {faces.shape}")
        faces = _indices("triangle vertex", faces, self._particle_count).reshape(-1, 3)
        used = np.zeros(self._particle_count, dtype=bool)
        used[faces] = True
        particles = np.flatnonzero(used)  # ascending, like np.unique, in O(n) instead of a sort
        remap = np.empty(self._particle_count, dtype=np.int64)
        remap[particles] = np.arange(len(particles))
        local = remap[faces]
        if uvs is not None:
            uvs = np.asarray(uvs, dtype=np.float64)
            if uvs.shape not in ((len(particles), 2), (len(faces), 3, 2)):
                raise ConfigError(f"uvs must have shape ({len(particles)}, 2) per vertex or ({len(faces)}, 3, 2) "
                                  f"per triangle corner, got {uvs.shape}")
            if not np.isfinite(uvs).all():
                raise ConfigError("uvs are not finite")
        counts = indices = None
        if (polygon_counts is None) != (polygon_indices is None):
            raise ConfigError("give polygon_counts and polygon_indices together, or neither")
        if polygon_counts is not None:
            counts = np.asarray(polygon_counts)
            if counts.ndim != 1 or len(counts) == 0 or not np.issubdtype(counts.dtype, np.integer) or counts.min() < 3:
                raise ConfigError("polygon_counts must be a non-empty list of integers >= 3 (vertices per face)")
            indices = _indices("polygon vertex", np.asarray(polygon_indices).ravel(), self._particle_count)
            if len(indices) != counts.sum():
                raise ConfigError(f"polygon_indices holds {len(indices)} entries, polygon_counts needs {counts.sum()}")
            if not used[indices].all():
                raise ConfigError("the polygons use a particle that no triangle uses: they must cover the same vertices")
            if uvs is not None and uvs.ndim == 3:
                raise ConfigError("per-corner uvs go with triangles, not with polygons: give uvs per vertex")
            counts, indices = counts.astype(np.int32), remap[indices].astype(np.int32)
        face_count = len(faces) if counts is None else len(counts)
        sets = {}
        for set_name, members in (face_sets or {}).items():
            members = np.unique(np.asarray(members, dtype=np.int64).ravel())
            if len(members) and (members[0] < 0 or members[-1] >= face_count):
                raise ConfigError(f"face set {set_name!r} names face {int(members[-1] if members[-1] >= face_count else members[0])}, "
                                  f"but the mesh has faces 0..{face_count - 1}")
            sets[checks.identifier("face set name", set_name)] = members.astype(np.int32)
        group = MeshGroup(
            name=self._unique_name(name, [m.name for m in self._meshes] + list(RESERVED_PRIM_NAMES)
                                   + [k.name for k in self._skins]),
            particles=particles,
            faces=local.reshape(-1, 3).astype(np.int32),
            uvs=uvs,
            polygon_counts=counts,
            polygon_indices=indices,
            face_sets=sets,
            dressing=dressing,
        )
        self._meshes.append(group)
        return group

    def add_cloth_grid(
        self,
        *,
        nx: int,
        ny: int,
        spacing: float,
        origin=(0.0, 0.0, 0.0),
        rotation=(0.0, 0.0, 0.0, 1.0),
        mass: float | None = None,
        particle_mass: float | None = None,
        velocity=(0.0, 0.0, 0.0),
        radius: float | None = None,
        structural: SpringMaterial | dict | bool | None = DEFAULT_STRUCTURAL,
        shear: SpringMaterial | dict | bool | None = DEFAULT_SHEAR,
        bend: SpringMaterial | dict | bool | None = DEFAULT_BEND,
        dihedral: DihedralMaterial | bool | None = None,
        material: ClothMaterial | None = None,
        pin=(),
        name: str = "cloth",
    ) -> np.ndarray:
        """Add a rectangular cloth of nx × ny particles.

        The grid lies in its local xy plane: column c at x = c·spacing, row r at y = r·spacing, local
        +z its front normal; ``rotation`` then ``origin`` place it in the world. Row ny-1 is the "top"
        edge, column 0 the "left" one.

        Without ``material``, the spring families take their constants as given: the cloth's response then
        depends on the resolution (a finer grid of the same springs is stiffer in bending and softer in
        stretch). With a :class:`ClothMaterial` the cloth is the same at any resolution: masses from
        :func:`~warpspring.core.material.grid_masses` (density × each particle's dual cell), structural and
        shear springs from :func:`~warpspring.core.material.grid_springs` (structural springs along the
        outer rows and columns at half stiffness and damping: each spans half a cell), no skip-one bend
        springs, and two crossed hinges on every interior row and column edge with rest angle 0 (flat), which
        bend it as an isotropic plate (:func:`~warpspring.core.material.grid_hinges`; a hinge with one side
        in a pinned region twice as stiff).

        Args:
            nx, ny: particles per row and per column (≥ 2).
            spacing: distance between neighbouring particles [m].
            origin: world position of particle (row 0, column 0) [m].
            rotation: orientation as a quaternion (x, y, z, w).
            mass: total mass [kg], shared equally; or give ``particle_mass`` [kg] instead (neither with
                ``material``).
            velocity: initial velocity of every particle [m/s].
            radius: contact radius [m]; default a quarter of the spacing.
            structural: springs to the 4-neighbours (ke [N/m], kd [N·s/m]). Each spring family takes what a
                scene file takes: a :class:`SpringMaterial`, a mapping ``{"ke": ..., "kd": ...}`` (a missing
                one takes the family's default), ``True`` for the default, or ``False``/``None`` for none.
            shear: springs along both diagonals of each quad (as ``structural``).
            bend: springs skipping one particle along rows and columns (as ``structural``).
            dihedral: dihedral springs on every interior edge of the cloth's triangles (ke [N·m/rad],
                kd [N·m·s/rad]), or ``None``/``False``.
            material: the cloth in physical units (stretch, shear [N/m], bending [N·m], density [kg/m²]),
                which then decides masses, springs, hinges and their damping: ``mass``/``particle_mass``
                must not be given, nor ``structural``, ``shear``, ``bend`` or ``dihedral`` other than
                their defaults (a :class:`~warpspring.ConfigError` says which).
            pin: corners/edges by name ("top-left", "top-right", "bottom-left", "bottom-right", "top",
                "bottom", "left", "right") and/or local particle indices r·nx + c.
            name: mesh name for export.

        Returns:
            Global particle indices, shape [ny, nx].
        """
        nx, ny = checks.count("nx", nx, minimum=2), checks.count("ny", ny, minimum=2)
        spacing = checks.positive("spacing", spacing)
        n = nx * ny
        structural = spring_family("structural", structural, DEFAULT_STRUCTURAL)
        shear = spring_family("shear", shear, DEFAULT_SHEAR)
        bend = spring_family("bend", bend, DEFAULT_BEND)
        dihedral = None if dihedral is False else dihedral
        self._check_grid_room(nx, ny, structural=structural, shear=shear, bend=bend,
                              hinges=material is not None or dihedral is not None, material=material is not None)
        if material is None:
            m = _mass_per_particle(mass, particle_mass, n)
        else:
            _material_decides(material, "add_cloth_grid", mass=mass is not None,
                              particle_mass=particle_mass is not None, structural=structural != DEFAULT_STRUCTURAL,
                              shear=shear != DEFAULT_SHEAR, bend=bend != DEFAULT_BEND, dihedral=dihedral is not None)
            m = grid_masses(material, nx, ny, spacing)
        rows, cols = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
        local = np.stack([cols * spacing, rows * spacing, np.zeros_like(rows, dtype=float)], axis=-1).reshape(-1, 3)
        q = self._place(local, origin, rotation)
        pinned = self._grid_pins(pin, nx, ny)
        ids = self.add_particles(
            q,
            velocities=np.broadcast_to(checks.vector("velocity", velocity), (n, 3)),
            mass=m,
            radius=0.25 * spacing if radius is None else radius,
            pinned=pinned,
        )
        grid = ids.reshape(ny, nx)
        self._cloth_grids.append((int(ids[0]), nx, ny))

        def pairs(a, b):
            return np.stack([a.ravel(), b.ravel()], axis=1)

        along_rows, along_columns = pairs(grid[:, :-1], grid[:, 1:]), pairs(grid[:-1, :], grid[1:, :])
        diagonals = np.concatenate([pairs(grid[:-1, :-1], grid[1:, 1:]), pairs(grid[:-1, 1:], grid[1:, :-1])])
        if material is None:
            families = [
                ("structural", structural, np.concatenate([along_rows, along_columns])),
                ("shear", shear, diagonals),
                ("bend", bend, np.concatenate([pairs(grid[:, :-2], grid[:, 2:]), pairs(grid[:-2, :], grid[2:, :])])),
            ]
            for family, springs, blocks in families:
                if springs is not None:
                    self.add_springs(blocks, stiffness=springs.ke, damping=springs.kd, family=family,
                                     **springs.spring_options())
        else:
            k = grid_springs(material)
            # A structural spring on an outer row or column spans half a cell: half stiffness and damping.
            row_share, column_share = np.ones((ny, nx - 1)), np.ones((ny - 1, nx))
            row_share[[0, -1], :] = column_share[:, [0, -1]] = 0.5
            share = np.concatenate([row_share.ravel(), column_share.ravel()])
            self.add_springs(np.concatenate([along_rows, along_columns]), stiffness=k.structural_stiffness * share,
                             damping=k.structural_damping * share, family="structural")
            self.add_springs(diagonals, stiffness=k.shear_stiffness, damping=k.shear_damping, family="shear")

        a, b = grid[:-1, :-1].ravel(), grid[:-1, 1:].ravel()
        c, d = grid[1:, 1:].ravel(), grid[1:, :-1].ravel()
        faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
        uv = np.stack([cols / (nx - 1), rows / (ny - 1)], axis=-1).reshape(-1, 2)
        quads = np.stack([a, b, c, d], 1)  # written to USD as quads, as a modeller would make the grid
        self.add_triangles(faces, name=name, uvs=uv, polygon_counts=np.full(len(quads), 4), polygon_indices=quads)
        if material is not None:
            hinges, k_theta, kd_theta = grid_hinges(material, nx, ny, pinned=pinned)
            self.add_hinges(ids[hinges], stiffness=k_theta, damping=kd_theta, rest_angle=0.0)
        elif dihedral is not None:
            self._add_mesh_hinges(q, faces - ids[0], ids, dihedral)
        return grid

    def add_cloth_mesh(
        self,
        mesh,
        faces=None,
        *,
        origin=(0.0, 0.0, 0.0),
        rotation=(0.0, 0.0, 0.0, 1.0),
        scale: float = 1.0,
        mass: float | None = None,
        density: float | None = None,
        velocity=(0.0, 0.0, 0.0),
        radius: float | None = None,
        structural: SpringMaterial | dict | bool | None = DEFAULT_STRUCTURAL,
        bend: SpringMaterial | dict | bool | None = DEFAULT_BEND,
        dihedral: DihedralMaterial | bool | None = None,
        material: ClothMaterial | None = None,
        pin=(),
        name: str | None = None,
        prim: str | None = None,
    ) -> np.ndarray:
        """Add a cloth from any triangle or polygon mesh.

        Every mesh edge becomes a structural spring; for every interior edge, the two vertices opposite
        it are joined by a bend spring. Mass is lumped to the vertices by triangle area. With a
        :class:`ClothMaterial` the cloth is the same at any resolution: masses from
        :func:`~warpspring.core.material.lumped_masses`, one spring per edge with
        :func:`~warpspring.core.material.edge_springs` (Van Gelder's rule), no bend springs, and dihedral
        hinges on every interior edge with :func:`~warpspring.core.material.hinge_parameters`, rest angles
        from the mesh as given. A file or
        ``trimesh.Trimesh`` is welded first: vertices at the same position (which loaders split along UV
        seams) become one particle, in order of first appearance (an OBJ file's ``v`` order), and the UVs
        are kept per triangle corner where a seam needs two.

        Args:
            mesh: a ``trimesh.Trimesh``, a file path trimesh can load (OBJ, STL, PLY, GLB, ...), a USD file
                (``.usd``, ``.usda``, ``.usdc``: see :func:`~warpspring.core.mesh_files.read_usd_mesh` for what is
                applied; the output prim comes back dressed as authored: its polygons, primvars, subsets with
                their material bindings, subdivision scheme, orientation, name and kind, see
                :class:`~warpspring.core.usd_dressing.UsdDressing`), or a vertex array
                [m], shape [v, 3] (then ``faces`` is required).
            faces: vertex indices of each triangle, shape [t, 3], when ``mesh`` is an array.
            origin, rotation, scale: placement; world = origin + rotation · (scale · vertex).
            mass: total mass [kg]; or ``density``: areal density [kg/m²] (neither with ``material``).
            velocity: initial velocity [m/s].
            radius: contact radius [m]; default a quarter of the mean edge length.
            structural, bend: spring families (ke [N/m], kd [N·s/m]) as in :meth:`add_cloth_grid`: a
                :class:`SpringMaterial`, a mapping ``{"ke": ..., "kd": ...}``, ``True`` (the default) or
                ``False``/``None`` (none).
            dihedral: dihedral springs on every interior edge (ke [N·m/rad], kd [N·m·s/rad]), or
                ``None``/``False``.
            material: the cloth in physical units (stretch [N/m], bending [N·m], density [kg/m²]; an edge
                network's shear modulus is 3/8 stretch whatever ``shear`` says), which then decides masses,
                springs, hinges and their damping: ``mass``/``density`` must not be given, nor
                ``structural``, ``bend`` or ``dihedral`` other than their defaults.
            pin: vertex indices of pinned particles.
            name: mesh name for export; ``None``: a USD mesh prim's own name, else ``"cloth"``.
            prim: for a USD file, the path of the mesh prim to read (``"/World/cloth"``); ``None``: the
                file's only mesh.

        Returns:
            Global particle indices of the mesh vertices, shape [v].
        """
        import trimesh  # trimesh loads lazily

        structural = spring_family("structural", structural, DEFAULT_STRUCTURAL)
        bend = spring_family("bend", bend, DEFAULT_BEND)
        dihedral = None if dihedral is False else dihedral
        uv = polygons = dressing = None
        face_sets = {}
        usd = isinstance(mesh, (str, os.PathLike)) and os.fspath(mesh).lower().endswith(USD_EXTENSIONS)
        if prim is not None and not usd:
            raise ConfigError(f"prim= chooses a mesh of a USD file ({', '.join(USD_EXTENSIONS)}), not of {mesh!r}")
        if usd:
            read = read_usd_mesh(mesh, prim=prim, up_axis=self.up_axis)
            vertices, faces = read.vertices, read.triangles
            polygons = (read.polygon_counts, read.polygon_indices)
            face_sets = read.face_sets
            dressing = read.dressing
            name = dressing.prim_name if name is None else name
        elif isinstance(mesh, (str, os.PathLike)):
            self._check_mesh_room(str(os.fspath(mesh)), mesh_file_counts(mesh), hinges=bool(material or dihedral),
                                  loading=True)
            mesh = load_mesh_file(mesh)
        loaded = not usd and isinstance(mesh, trimesh.Trimesh)
        if loaded:
            vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)
            visual_uv = getattr(getattr(mesh, "visual", None), "uv", None)
            if visual_uv is not None and len(visual_uv) == len(vertices):
                uv = np.asarray(visual_uv, dtype=np.float64)
        elif not usd:
            if faces is None:
                raise ConfigError("add_cloth_mesh needs faces= when the mesh is given as a vertex array")
            vertices = np.asarray(mesh, dtype=np.float64)
        vertices = _points("mesh vertices", vertices)
        faces = np.asarray(faces)
        if len(vertices) == 0 or faces.size == 0:
            raise ConfigError("the cloth mesh is empty: it needs at least one triangle")
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ConfigError(f"mesh faces must be triangles, shape [t, 3], got {faces.shape}")
        faces = _indices("mesh face vertex", faces, len(vertices)).reshape(-1, 3)
        name = "cloth" if name is None else name
        self._check_mesh_room(name, (len(vertices), len(faces)), hinges=bool(material or dihedral))
        if loaded:  # loaders split a vertex wherever its UVs differ (a texture seam): the cloth must not tear
            vertices, faces, uv = _weld_seams(vertices, faces, uv)
        scale = checks.positive("scale", scale)

        tri = trimesh.Trimesh(vertices * scale, faces, process=False, validate=False)
        area = tri.area_faces
        if not (area > 0.0).any():
            raise ConfigError("every triangle of the cloth mesh has zero area")
        lumped = np.bincount(faces.ravel(), weights=np.repeat(area / 3.0, 3), minlength=len(vertices))
        lonely = np.flatnonzero(lumped <= 0.0)
        if len(lonely):
            raise ConfigError(
                f"mesh vertex {int(lonely[0])} belongs to no triangle of nonzero area "
                f"({len(lonely)} such vertices): remove unreferenced vertices and degenerate faces"
            )
        if material is None:
            if (mass is None) == (density is None):
                raise ConfigError("give exactly one of mass= (total, kg) or density= (kg/m²) for a cloth mesh, "
                                  "or material=")
            areal = checks.positive("mass", mass) / area.sum() if density is None else checks.positive("density", density)
            particle_mass = lumped * areal
        else:
            _material_decides(material, "add_cloth_mesh", mass=mass is not None, density=density is not None,
                              structural=structural != DEFAULT_STRUCTURAL, bend=bend != DEFAULT_BEND,
                              dihedral=dihedral is not None)
            particle_mass = lumped_masses(material, vertices * scale, faces)

        edges = tri.edges_unique
        ids = self.add_particles(
            self._place(vertices * scale, origin, rotation),
            velocities=np.broadcast_to(checks.vector("velocity", velocity), (len(vertices), 3)),
            mass=particle_mass,
            radius=0.25 * float(tri.edges_unique_length.mean()) if radius is None else radius,
            pinned=_indices("pinned vertex", np.atleast_1d(pin), len(vertices)) if np.size(pin) else None,
        )
        if material is not None:
            ke, kd = edge_springs(material, vertices * scale, faces, edges)
            self.add_springs(ids[edges], stiffness=ke, damping=kd, family="structural")
        else:
            if structural is not None and len(edges):
                self.add_springs(ids[edges], stiffness=structural.ke, damping=structural.kd, family="structural",
                                 **structural.spring_options())
            if bend is not None:
                opposite = tri.face_adjacency_unshared
                if len(opposite):
                    self.add_springs(ids[opposite], stiffness=bend.ke, damping=bend.kd, family="bend",
                                     **bend.spring_options())
        self.add_triangles(ids[faces], name=name, uvs=uv, face_sets=face_sets, dressing=dressing,
                           polygon_counts=None if polygons is None else polygons[0],
                           polygon_indices=None if polygons is None else ids[polygons[1]])
        if material is not None:
            self._add_mesh_hinges(vertices * scale, faces, ids, material, rest="mesh")
        elif dihedral is not None:
            self._add_mesh_hinges(vertices * scale, faces, ids, dihedral)
        return ids

    # -- helpers --------------------------------------------------------------------------------------

    def _check_grid_room(self, nx: int, ny: int, *, structural, shear, bend, hinges: bool, material: bool) -> None:
        """Refuse, before any array is made, a grid whose builder arrays (and the temporaries of making them)
        exceed the host memory available (``memory.available_memory``): a ConfigError with the estimate and a
        smaller grid that fits. ``finalize`` checks the whole model later."""
        n = nx * ny
        structural_count = ny * (nx - 1) + (ny - 1) * nx
        shear_count = 2 * (nx - 1) * (ny - 1)
        bend_count = ny * max(nx - 2, 0) + max(ny - 2, 0) * nx
        if material:
            springs = structural_count + shear_count
        else:
            springs = sum(c for family, c in ((structural, structural_count), (shear, shear_count), (bend, bend_count))
                          if family is not None)
        triangles = 2 * (nx - 1) * (ny - 1)
        edges = structural_count + (nx - 1) * (ny - 1)
        interior = edges - 2 * (nx - 1) - 2 * (ny - 1)
        hinges = interior if hinges else 0
        # The whole scene with the grid: the builder's arrays, and beside them the larger of making the grid's
        # temporaries (each family's pairs twice, built then checked as int64, and its rest-length differences,
        # float64: ~70 bytes per spring, measured) and finalize's host copies of the scene (whatever the device).
        estimate = memory.estimate_memory(
            particles=self._particle_count + n, springs=self._spring_count + springs,
            hinges=self._hinge_count + hinges, triangles=sum(len(g.faces) for g in self._meshes) + triangles)
        temporary = GRID_TEMPORARY_PER_SPRING * springs + GRID_TEMPORARY_PER_PARTICLE * n
        needed = estimate.builder + max(temporary, estimate.finalize_host)
        available = memory.available_memory(None).host  # the host's (Warp need not be initialised yet)
        if available is not None and needed > available:
            share = available / (needed * 1.05)
            side = max(int(math.sqrt(share * n)), 2)
            raise ConfigError(
                f"a {nx} × {ny} cloth grid needs an estimated {memory.format_bytes(needed)} of host memory to build "
                f"with finalize's copies ({n:,} particles, {springs:,} springs), but {memory.format_bytes(available)} is "
                f"available: use a smaller grid (about {side} × {side} fits), and see warpspring.estimate_memory for "
                "the run's needs"
            )

    def _check_mesh_room(self, what: str, counts: tuple[int, int] | None, *, hinges: bool,
                         loading: bool = False) -> None:
        """Refuse a cloth mesh of ``counts`` (vertices, triangles) whose making (or, ``loading``, reading its file
        too) needs more host memory than is available, before the work starts (``counts`` ``None``: unknown)."""
        if counts is None:
            return
        vertices, faces = counts
        edges = 3 * faces // 2  # a closed or nearly closed surface: each interior edge shared by two triangles
        temporary = (MESH_HINGE_TEMPORARY_PER_TRIANGLE if hinges else MESH_TEMPORARY_PER_TRIANGLE) * faces
        if loading:
            temporary += MESH_LOAD_PER_FACE * faces
        self._check_room(f"a cloth mesh of {faces:,} triangles ({what})", particles=vertices,
                         springs=2 * edges, hinges=edges if hinges else 0, triangles=faces, temporary=temporary,
                         remedy="decimate the mesh (fewer triangles), or split it into parts built apart")

    def _add_mesh_hinges(self, vertices: np.ndarray, faces: np.ndarray, ids: np.ndarray,
                         material: DihedralMaterial | ClothMaterial, *, rest: str = "mesh") -> None:
        """Hinges on every interior edge of a mesh (local ``faces`` into ``vertices`` [m], particles ``ids``).

        A :class:`DihedralMaterial` gives every hinge its ke, kd and rest rule; a :class:`ClothMaterial`
        gives each hinge its own k_θ [N·m/rad] and kd_θ [N·m·s/rad] from its rest geometry
        (:func:`~warpspring.core.material.hinge_parameters`), with rest angles by ``rest``: "mesh" (as
        given) or "flat" (0).
        """
        if not isinstance(material, (DihedralMaterial, ClothMaterial)):
            raise ConfigError(f"dihedral must be a warpspring.DihedralMaterial, got {type(material).__name__}")
        try:
            hinges, mesh_rest = mesh_hinges(vertices, faces)
        except ValueError as exc:
            raise ConfigError(f"cannot add dihedral springs: {exc}") from None
        if isinstance(material, ClothMaterial):
            stiffness, damping = hinge_parameters(material, vertices, hinges)
        else:
            stiffness, damping, rest = material.ke, material.kd, material.rest
        self.add_hinges(ids[hinges], stiffness=stiffness, damping=damping,
                        rest_angle=mesh_rest if rest == "mesh" else 0.0)

    @staticmethod
    def _grid_pins(pin, nx: int, ny: int) -> np.ndarray:
        if isinstance(pin, (str, int, np.integer)):
            pin = [pin]
        mask = np.zeros((ny, nx), dtype=bool)
        for p in pin:
            if isinstance(p, str):
                key = p.strip().lower()
                if key not in _GRID_PINS:
                    raise ConfigError(f"unknown pin {p!r}: use one of {', '.join(_GRID_PINS)} or particle indices")
                top, right = "top" in key, "right" in key
                if "-" in key:
                    mask[ny - 1 if top else 0, nx - 1 if right else 0] = True
                elif key in ("top", "bottom"):
                    mask[ny - 1 if top else 0, :] = True
                else:
                    mask[:, nx - 1 if right else 0] = True
            else:
                mask.flat[_indices("pin", [p], nx * ny)] = True
        return mask.ravel()


def _weld_seams(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray | None):
    """Merge vertices at identical positions, keeping the order of their first appearance; with a
    merge, UVs move to the triangle corners, shape [t, 3, 2]."""
    _, first, inverse = np.unique(vertices, axis=0, return_index=True, return_inverse=True)
    if len(first) == len(vertices):
        return vertices, faces, uv
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    corner_uv = None if uv is None else uv[faces]
    return vertices[first[order]], rank[inverse.reshape(-1)][faces], corner_uv


def _mass_per_particle(mass, particle_mass, n: int) -> float:
    if (mass is None) == (particle_mass is None):
        raise ConfigError("give exactly one of mass= (total, kg) or particle_mass= (kg per particle), or material=")
    return checks.positive("mass", mass) / n if particle_mass is None else checks.positive("particle_mass", particle_mass)


def _material_decides(material, method: str, **given: bool) -> None:
    """Check ``material`` is a ClothMaterial and that none of the arguments it decides was ``given``."""
    if not isinstance(material, ClothMaterial):
        raise ConfigError(f"material must be a warpspring.ClothMaterial, got {type(material).__name__}")
    clash = [name for name, value in given.items() if value]
    if clash:
        raise ConfigError(
            f"{method}: material= decides the masses, springs and hinges, so {', '.join(clash)} must not be "
            "given with it (drop them, or drop material= to set them yourself)"
        )
