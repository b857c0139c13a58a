"""The prims :class:`~warpspring.io.usd.UsdWriter` writes for one exported world: cloth meshes (their faces as
authored, UVs, face sets, primvars), soft bodies' meshes, particles, spring curves, emitters' points and
colliders, each with the attributes it samples per frame; and the per-frame samples of embedded surfaces and
emitters. pxr loads only when a writer is made: this module (its ``PRIMVARS`` and ``PURPOSES`` too) imports
without it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..core.transforms import quat_to_matrix
from .usd_normals import FaceNormals, vertex_normals

#: The optional per-vertex primvars of :class:`~warpspring.io.usd.UsdWriter`.
PRIMVARS = ("strain", "pinned", "rest")
#: The purposes a collider prim may have.
PURPOSES = ("guide", "default", "render", "proxy")


class UsdPrims:
    """Prim definitions of :class:`~warpspring.io.usd.UsdWriter`, a base of it: the writer holds ``stage`` (the
    static stage), ``model``, the pxr modules (``_UsdGeom``, ``_Vt``, ``_Gf``), the chosen ``_primvars``,
    ``_purpose`` and ``_tile``, ``_previous_normals`` (the normals written last, by attribute: the fallback of a
    vertex whose faces cancel or have no area, :func:`~warpspring.io.usd_normals.fallback_normals`), and :meth:`~warpspring.io.usd_stream.UsdStream._animate` to register the
    attributes sampled per frame."""

    def _define_polygon_mesh(self, path: str, group):
        """A Mesh prim at ``path`` with ``group``'s faces as authored (its polygons where it has them, quads
        staying quads; else its triangles) and the attributes every warpspring surface carries: no
        subdivision, double-sided, right-handed, per-vertex normals. ``group``: a MeshGroup or a SkinGroup."""
        UsdGeom, Vt = self._UsdGeom, self._Vt
        mesh = UsdGeom.Mesh.Define(self.stage, path)
        dressing = getattr(group, "dressing", None)
        if group.polygon_counts is not None:
            counts, indices = group.polygon_counts, group.polygon_indices
        else:
            counts, indices = np.full(len(group.faces), 3, np.int32), group.faces.reshape(-1)
        scheme, orientation = UsdGeom.Tokens.none, UsdGeom.Tokens.rightHanded
        if dressing is not None:  # the faces as authored (a faceVarying primvar follows their order)
            indices, scheme = dressing.face_vertex_indices, dressing.subdivision_scheme
            orientation = dressing.orientation
            if dressing.mirrored:  # points are written in world space: a mirroring transform's flip goes here
                orientation = (UsdGeom.Tokens.rightHanded if orientation == UsdGeom.Tokens.leftHanded
                               else UsdGeom.Tokens.leftHanded)
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(counts.astype(np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(indices.astype(np.int32)))
        mesh.CreateSubdivisionSchemeAttr(scheme)
        mesh.CreateDoubleSidedAttr(True)
        mesh.CreateOrientationAttr(orientation)
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
        return mesh

    def _dress(self, mesh, dressing) -> set:
        """Author a USD input's dressing on the output ``mesh``: its primvars (values, interpolation, indices,
        elementSize, type with role), its GeomSubsets (element type, family name and type) and the material
        bindings of the mesh and the subsets, to the bound Materials copied into this stage under
        ``/World/Looks`` (the output stands alone); its kind. Returns the names of the primvars authored,
        which the simulation's own primvars (``strain``, ``rest``, ``pinned``) then do not replace: where an
        authored primvar has one of their names, the authored one is kept and the simulation's is skipped."""
        from pxr import Kind, Sdf, Usd, UsdShade  # noqa: F401 - Kind registers the kind tokens

        UsdGeom, Vt = self._UsdGeom, self._Vt
        api = UsdGeom.PrimvarsAPI(mesh)
        for primvar in dressing.primvars:
            created = api.CreatePrimvar(primvar.name, Sdf.ValueTypeNames.Find(primvar.type_name),
                                        primvar.interpolation, primvar.element_size)
            created.Set(primvar.value)
            if primvar.indices is not None:
                created.SetIndices(Vt.IntArray.FromNumpy(primvar.indices))
        bound = self._copy_materials(dressing)
        if dressing.material:
            UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(UsdShade.Material(
                self.stage.GetPrimAtPath(bound[dressing.material])))
        imageable = UsdGeom.Imageable(mesh.GetPrim())
        for subset in dressing.subsets:
            made = UsdGeom.Subset.CreateGeomSubset(imageable, subset.name, subset.element_type,
                                                   Vt.IntArray.FromNumpy(subset.indices), familyName=subset.family)
            if subset.family and subset.family_type:
                UsdGeom.Subset.SetFamilyType(imageable, subset.family, subset.family_type)
            if subset.material:
                UsdShade.MaterialBindingAPI.Apply(made.GetPrim()).Bind(UsdShade.Material(
                    self.stage.GetPrimAtPath(bound[subset.material])))
        if dressing.kind:
            Usd.ModelAPI(mesh.GetPrim()).SetKind(dressing.kind)
        return {p.name for p in dressing.primvars}

    def _copy_materials(self, dressing) -> dict:
        """Copy the Materials ``dressing`` binds from its source file into this stage, once per source
        Material, under ``/World/Looks`` (the source's flattened specs, so their shaders come along);
        returns source path -> path in this stage."""
        from pxr import Sdf, Usd

        copied = self.__dict__.setdefault("_copied_materials", {})
        wanted = [m for m in dressing.materials if (dressing.source, m) not in copied]
        if wanted:
            flat = Usd.Stage.Open(dressing.source).Flatten()
            layer = self.stage.GetRootLayer()
            looks, n = Sdf.Path("/World/Looks"), 1
            while layer.GetPrimAtPath(looks) and layer.GetPrimAtPath(looks).typeName != "Scope":
                n += 1  # a mesh of that name: the materials go beside it
                looks = Sdf.Path(f"/World/Looks_{n}")
            if not layer.GetPrimAtPath(looks):
                Sdf.CreatePrimInLayer(layer, looks).specifier = Sdf.SpecifierDef
                layer.GetPrimAtPath(looks).typeName = "Scope"
            for source in wanted:
                name, n = Sdf.Path(source).name, 1
                target = looks.AppendChild(name)
                while layer.GetPrimAtPath(target):
                    n += 1
                    target = looks.AppendChild(f"{name}_{n}")
                if flat.GetPrimAtPath(source) is None:
                    continue  # a binding to a material the source does not have: nothing to copy
                Sdf.CopySpec(flat, source, layer, target)
                copied[(dressing.source, source)] = str(target)
        return {m: copied[(dressing.source, m)] for m in dressing.materials if (dressing.source, m) in copied}

    def _define_world(self, world: int, root: str, *, particles: bool, springs: bool,
                      surfaces: bool = True) -> _WorldPrims:
        """Define the prims of one exported world under ``root``; topology and constant attributes once. With
        ``surfaces`` false (a layer over an asset: its surfaces are overrides, :meth:`_define_surface`), only the
        particles, springs and emitters."""
        from pxr import Sdf

        stage, UsdGeom, Vt, model = self.stage, self._UsdGeom, self._Vt, self.model
        q0 = model.particle_q.numpy().reshape(model.world_count, model.particle_count, 3)[world]
        meshes = [self._define_surface(root, group, q0[group.particles]) for group in model.meshes] if surfaces else []

        points = None
        if particles:
            prim = UsdGeom.Points.Define(stage, f"{root}/particles")
            radius = model.particle_radius.numpy().astype(np.float32)
            self._widths = Vt.FloatArray.FromNumpy(2.0 * radius)
            prim.CreateWidthsAttr(self._widths)
            prim.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
            points = _PointsPrims(points=self._animate(prim.CreatePointsAttr()),
                                  extent=self._animate(prim.CreateExtentAttr()),
                                  velocities=self._animate(prim.CreateVelocitiesAttr()))

        curves = []
        if springs and model.spring_count:
            UsdGeom.Scope.Define(stage, f"{root}/springs")
            width = float(0.5 * model.particle_radius.numpy().mean()) or 1.0e-3
            self._curve_widths = Vt.FloatArray([width])
            ends = model.spring_indices.numpy()
            for family, members in model.spring_families.items():
                counts, particles, segments = spring_chains(ends[members])
                prim = UsdGeom.BasisCurves.Define(stage, f"{root}/springs/{family}")
                prim.CreateTypeAttr(UsdGeom.Tokens.linear)
                prim.CreateCurveVertexCountsAttr(Vt.IntArray.FromNumpy(counts))
                prim.CreateWidthsAttr(self._curve_widths)
                prim.SetWidthsInterpolation(UsdGeom.Tokens.constant)
                api = UsdGeom.PrimvarsAPI(prim)
                api.CreatePrimvar("warpspring:particle", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex).Set(
                    Vt.IntArray.FromNumpy(particles))
                strain = api.CreatePrimvar("strain", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex).GetAttr()
                curves.append(_CurvePrims(
                    particles=particles, segments=members[segments],
                    points=self._animate(prim.CreatePointsAttr()), extent=self._animate(prim.CreateExtentAttr()),
                    velocities=self._animate(prim.CreateVelocitiesAttr()), strain=self._animate(strain),
                ))
        emitters = []
        for emitter in model.emitters:  # the live particles only, with their birth serials as stable ids
            prim = UsdGeom.Points.Define(stage, f"{root}/{emitter.name}")
            prim.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
            emitters.append(_EmitterPrims(
                emitter, points=self._animate(prim.CreatePointsAttr()), ids=self._animate(prim.CreateIdsAttr()),
                widths=self._animate(prim.CreateWidthsAttr()), velocities=self._animate(prim.CreateVelocitiesAttr()),
                extent=self._animate(prim.CreateExtentAttr()),
            ))
        return _WorldPrims(world, meshes, points, curves, emitters)

    def _define_surface(self, root: str, group, rest: np.ndarray) -> _SurfacePrims:
        """Define the USD mesh of a simulated surface, a cloth's (``MeshGroup``) or a soft body's (``SkinGroup``,
        its vertices following the particles), by one path: its faces as authored, UVs and face sets once (a USD
        input: its whole dressing, :meth:`_dress`); the simulation's primvars asked for (``rest``: ``rest`` [m],
        the vertices at the start); per frame its points, extent, normals (the interpolation the input authors,
        :class:`~warpspring.core.usd_dressing.UsdDressing`), velocities and accelerations. Over an asset
        (``_layer``): an override at the asset's prim path of the animated attributes only."""
        from pxr import Sdf

        UsdGeom, Vt = self._UsdGeom, self._Vt
        dressing = group.dressing
        layer = getattr(self, "_layer", None)
        if layer is not None:  # the asset's own prim: only what the simulation changes
            mesh = UsdGeom.Mesh(self.stage.OverridePrim(dressing.prim_path))
            authored = {p.name for p in dressing.primvars}
            rest = layer.local(dressing.prim_path, self._time_code(0), rest)[0]
        else:
            mesh = self._define_polygon_mesh(f"{root}/{group.name}", group)
            if group.uvs is not None:  # per vertex, or per corner where seams give a particle two UVs
                corners = group.uvs.ndim == 3
                UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
                    "st", Sdf.ValueTypeNames.TexCoord2fArray,
                    UsdGeom.Tokens.faceVarying if corners else UsdGeom.Tokens.vertex,
                ).Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(group.uvs.reshape(-1, 2), dtype=np.float32)))
            authored = set()
            if dressing is not None:  # a USD input: its primvars, subsets and bindings as authored
                authored = self._dress(mesh, dressing)
            else:
                for name, faces in group.face_sets.items():
                    UsdGeom.Subset.CreateGeomSubset(mesh, name, UsdGeom.Tokens.face, Vt.IntArray.FromNumpy(faces),
                                                    familyName="warpspring")
        primvars = UsdGeom.PrimvarsAPI(mesh)
        strain = pinned = None
        if "strain" in self._primvars and "strain" not in authored:
            strain = self._animate(primvars.CreatePrimvar(
                "strain", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex).GetAttr())
        if "pinned" in self._primvars and "pinned" not in authored:  # a skin: 1 where all its particles are
            pinned = self._animate(primvars.CreatePrimvar(
                "pinned", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex).GetAttr())
        if "rest" in self._primvars and "rest" not in authored:
            primvars.CreatePrimvar("rest", Sdf.ValueTypeNames.Point3fArray, UsdGeom.Tokens.vertex).Set(
                vec3_array(Vt, rest))
        interpolation = (dressing.normals if dressing is not None else None) or UsdGeom.Tokens.vertex
        if layer is not None and dressing.normals_primvar:  # USD prefers primvars:normals: override that one
            normals = primvars.CreatePrimvar("normals", Sdf.ValueTypeNames.Normal3fArray, interpolation)
            if dressing.normals_indexed:
                normals.BlockIndices()  # the values written are per element, not indexed
            normals = normals.GetAttr()
        else:
            normals = mesh.CreateNormalsAttr()
            mesh.SetNormalsInterpolation(interpolation)
        front = None
        if dressing is not None and interpolation != UsdGeom.Tokens.vertex:  # per face-vertex or per face
            flip = (dressing.orientation == UsdGeom.Tokens.leftHanded) != dressing.mirrored
            counts = np.asarray(group.polygon_counts if group.polygon_counts is not None
                                else np.full(len(group.faces), 3), dtype=np.int64)
            front = FaceNormals(counts, dressing.face_vertex_indices.astype(np.int64), -1.0 if flip else 1.0,
                           dressing.smoothing)
        return _SurfacePrims(
            group, points=self._animate(mesh.CreatePointsAttr()), extent=self._animate(mesh.CreateExtentAttr()),
            normals=self._animate(normals), velocities=self._animate(mesh.CreateVelocitiesAttr()),
            accelerations=self._animate(mesh.CreateAccelerationsAttr()) if self._accelerations else None,
            strain=strain, pinned=pinned, interpolation=str(interpolation), front=front,
            prim_path=dressing.prim_path if layer is not None else None,
        )

    def _surface_samples(self, prims, x: np.ndarray, v: np.ndarray, *, normals=None, strain=None, pinned=None) -> list:
        """One frame's samples of a simulated surface from its vertices ``x`` [m] and velocities ``v`` [m/s]
        (shape [vertex_count, 3], world space): points, extent, normals (``normals``: vertex normals computed on the
        device; else found here, :meth:`_host_vertex_normals` or per face / per smoothing group of face-vertices),
        velocities, its ``strain`` [-] and ``pinned`` (0/1) per vertex when given, accelerations (the frame before's,
        once this frame is known, :meth:`_look_ahead`). Over an asset, every value in the prim's frame."""
        Vt, UsdGeom = self._Vt, self._UsdGeom
        x = np.asarray(x, dtype=np.float64)
        if prims.front is not None:
            normals = prims.front.normals(x, self.model.up_axis, prims.interpolation == UsdGeom.Tokens.uniform)
        elif normals is None:
            normals = self._host_vertex_normals(prims.normals, x, prims.group.faces)
        if prims.prim_path is not None:
            x, (v,), normals = self._layer.local(prims.prim_path, self._time_code(self.frame_count), x, [v], normals)
        points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(x, dtype=np.float32))
        samples = [(prims.points, points), (prims.extent, UsdGeom.PointBased.ComputeExtent(points)),
                   (prims.normals, vec3_array(Vt, normals)), (prims.velocities, vec3_array(Vt, v))]
        if prims.accelerations is not None:
            self._look_ahead(prims.accelerations, x, v)
        if prims.strain is not None and strain is not None:
            samples.append((prims.strain, Vt.FloatArray.FromNumpy(np.asarray(strain, dtype=np.float32))))
        if prims.pinned is not None and pinned is not None:
            samples.append((prims.pinned, Vt.IntArray.FromNumpy(np.asarray(pinned, dtype=np.int32))))
        return samples

    def _look_ahead(self, attribute, x: np.ndarray, v: np.ndarray) -> None:
        """Keep this frame's points and velocities for the accelerations of this frame, and give the frame before
        its accelerations a = 2 (x₁ − x₀ − v₀ Δt) / Δt² (Δt = 1 / fps) of the float32 values written (a resumed run's
        kept frame gives the same): the quadratic x₀ + v₀ t + ½ a t² that renderers draw between samples passes
        through this frame's points (written into the frame before by
        :meth:`~warpspring.io.usd_stream.UsdStream._append`)."""
        x, v = (np.asarray(a, dtype=np.float32).astype(np.float64) for a in (x, v))  # the values as written
        held = self._held.get(attribute)
        if held is not None:
            x0, v0 = held
            dt = 1.0 / self.fps
            self._amend.append((attribute, vec3_array(self._Vt, 2.0 * (x - x0 - v0 * dt) / (dt * dt))))
        self._held_next[attribute] = (x, v)

    def _host_vertex_normals(self, key, x: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """Area-weighted unit vertex normals of triangles ``faces`` at vertices ``x`` (:func:`~warpspring.io.usd_normals.vertex_normals`), the
        normals written last for ``key`` (an attribute) kept where a vertex's faces cancel or have no area."""
        normal = vertex_normals(x, faces, self.model.up_axis, self._previous_normals.get(key))
        self._previous_normals[key] = normal
        return normal

    def _skin_values(self, skin, q: np.ndarray, v: np.ndarray, vertex_strain, kinematic) -> dict:
        """An embedded surface's vertices Σ w x and velocities Σ w v (a host product over the positions already read
        back: no extra transfer, a fixed order), the weighted mean of its particles' strain [-] and, per vertex,
        whether every particle it follows (of nonzero weight) is pinned: the arguments of :meth:`_surface_samples`."""
        values = dict(x=skin.points(q), v=skin.points(v))
        if vertex_strain is not None:
            values["strain"] = (skin.weights * vertex_strain[skin.indices]).sum(axis=1)
        if kinematic is not None:  # held: no weight on a free particle
            values["pinned"] = ~((skin.weights != 0.0) & ~kinematic[skin.indices]).any(axis=1)
        return values

    def _emitter_samples(self, prims, world: int, q: np.ndarray, v: np.ndarray) -> list:
        """One frame's samples of an emitter's live particles in ``world``: points, ids, widths, velocities,
        extent (a point at the emitter's centre when none lives)."""
        Vt, Gf = self._Vt, self._Gf
        emitter = prims.emitter
        serial = emitter.serials(world)
        live = np.flatnonzero(serial >= 0)
        index = emitter.first + live
        points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(q[index]))
        widths = Vt.FloatArray.FromNumpy((2.0 * self._radius[index]).astype(np.float32))
        if len(live):
            extent = self._UsdGeom.Points.ComputeExtent(points, widths)
        else:
            c = Gf.Vec3f(*(float(x) for x in emitter.center))
            extent = Vt.Vec3fArray([c, c])
        return [(prims.points, points), (prims.ids, Vt.Int64Array.FromNumpy(serial[live].astype(np.int64))),
                (prims.widths, widths), (prims.velocities, vec3_array(Vt, v[index])), (prims.extent, extent)]

    def _write_colliders(self, root: str) -> list:
        """Define the collider prims of one exported world under ``root``, each of the chosen purpose and posed
        at rest; returns (ShapeInfo, translate path, orient path) of each moving collider, sampled every frame."""
        from pxr import Gf, Vt

        UsdGeom = self._UsdGeom
        model = self.model
        if not model.shapes:
            return []
        UsdGeom.Scope.Define(self.stage, f"{root}/colliders")
        q0 = model.particle_q.numpy()
        moving = []
        for shape in model.shapes:
            path = f"{root}/colliders/{shape.name}"
            scale = None
            if shape.kind == "sphere":
                prim = UsdGeom.Sphere.Define(self.stage, path)
                r = float(shape.size[0])
                prim.CreateRadiusAttr(r)
                prim.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(-r, -r, -r), Gf.Vec3f(r, r, r)]))
            elif shape.kind == "box":  # a cube of size 2 spans ±1: scaled by the half extents, it spans the box
                prim = UsdGeom.Cube.Define(self.stage, path)
                prim.CreateSizeAttr(2.0)
                prim.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(-1.0, -1.0, -1.0), Gf.Vec3f(1.0, 1.0, 1.0)]))
                scale = Gf.Vec3d(*shape.size)
            elif shape.kind == "capsule":
                prim = UsdGeom.Capsule.Define(self.stage, path)
                r, half = float(shape.size[0]), float(shape.size[1])
                prim.CreateRadiusAttr(r)
                prim.CreateHeightAttr(2.0 * half)  # USD's height is the spine's length, without the caps
                prim.CreateAxisAttr(UsdGeom.Tokens.z)
                prim.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(-r, -r, -half - r), Gf.Vec3f(r, r, half + r)]))
            elif shape.kind == "plane":
                prim = UsdGeom.Mesh.Define(self.stage, path)
                half = _plane_half_size(shape, q0, self._tile)
                corners = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]], np.float32)
                prim.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(corners))
                prim.CreateFaceVertexCountsAttr(Vt.IntArray([4]))
                prim.CreateFaceVertexIndicesAttr(Vt.IntArray([0, 1, 2, 3]))
                prim.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
                prim.CreateDoubleSidedAttr(True)
                prim.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(-half, -half, 0), Gf.Vec3f(half, half, 0)]))
            elif shape.kind == "mesh":  # its triangles in its own frame; a deforming one's points sampled every frame
                prim = UsdGeom.Mesh.Define(self.stage, path)
                collider = model.mesh_collider(model.shapes.index(shape))
                points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(collider.points(), dtype=np.float32))
                prim.CreatePointsAttr(points)
                prim.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(shape.mesh.faces), 3, np.int32)))
                prim.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(shape.mesh.faces.reshape(-1).astype(np.int32)))
                prim.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
                prim.CreateDoubleSidedAttr(shape.mesh.sides != "closed")
                prim.CreateExtentAttr(UsdGeom.PointBased.ComputeExtent(points))
                if shape.mesh.deforming:
                    self._deforming_meshes.setdefault(root, []).append(
                        (collider, self._animate(prim.GetPointsAttr()), self._animate(prim.GetExtentAttr())))
            else:  # pragma: no cover - every collider kind is exported; a new kind must add a branch
                raise NotImplementedError(f"USD export of {shape.kind} colliders")
            prim.CreatePurposeAttr(self._purpose)
            translate = prim.AddTranslateOp()  # double precision, as the shape's frame
            orient = prim.AddOrientOp(UsdGeom.XformOp.PrecisionDouble)
            if scale is not None:
                prim.AddScaleOp(UsdGeom.XformOp.PrecisionDouble).Set(scale)
            _set_pose(translate, orient, shape.frame(0.0))  # default value: the rest pose, or a moving one's at t = 0
            if shape.moving:
                moving.append((shape, self._animate(translate.GetAttr()), self._animate(orient.GetAttr())))
        return moving


def vec3_array(Vt, values: np.ndarray):
    return Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(values, dtype=np.float32))


def spring_chains(ends: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Springs as few linear chains as pairing them at each particle gives (each spring once): a grid's
    structural springs become its rows and columns, so a chain's inner points are shared by two springs.

    Args:
        ends: the two particles of each spring, shape [s, 2].

    Returns:
        counts: vertices per chain, shape [c], int32; particles: the particle of each chain vertex, shape
        [counts.sum()], int32; segments: for each chain vertex, the springs (indices into ``ends``) on either
        side of it, shape [counts.sum(), 2], int64 (a chain's end vertex repeats its one spring).
    """
    s = len(ends)
    corner = np.asarray(ends, dtype=np.int64).ravel()  # corner 2i + side is spring i's end at that side
    order = np.argsort(corner, kind="stable")
    sorted_vertex = corner[order]
    group_start = np.flatnonzero(np.r_[True, np.diff(sorted_vertex) != 0])
    rank = np.arange(2 * s) - np.repeat(group_start, np.diff(np.r_[group_start, 2 * s]))
    first = np.flatnonzero((rank % 2 == 0)[:-1] & (sorted_vertex[:-1] == sorted_vertex[1:]))
    mate = np.full(2 * s, -1, dtype=np.int64)  # the corner a chain continues through at the same particle
    mate[order[first]], mate[order[first + 1]] = order[first + 1], order[first]
    visited = np.zeros(s, dtype=bool)
    counts, particles, segments = [], [], []
    starts = np.r_[np.flatnonzero(mate < 0), np.arange(2 * s)]  # open chains first, then closed loops
    for begin in starts.tolist():
        if visited[begin // 2]:
            continue
        chain, springs = [int(corner[begin])], []
        c = begin
        while True:
            spring = c // 2
            visited[spring] = True
            springs.append(spring)
            other = c ^ 1
            chain.append(int(corner[other]))
            c = int(mate[other])
            if c < 0 or visited[c // 2]:
                break
        counts.append(len(chain))
        particles.extend(chain)
        springs = np.asarray(springs)
        segments.append(np.stack([np.r_[springs[:1], springs], np.r_[springs, springs[-1:]]], axis=1))
    return (np.asarray(counts, dtype=np.int32), np.asarray(particles, dtype=np.int32),
            np.concatenate(segments) if segments else np.zeros((0, 2), dtype=np.int64))


@dataclass
class _SurfacePrims:
    """The animated attributes (paths) of one exported surface: a cloth mesh (``group``: MeshGroup) or an embedded
    one (a SkinGroup); how its normals are found; its prim path in the asset when written over one."""

    group: object
    points: object
    extent: object
    normals: object
    velocities: object
    accelerations: object = None
    strain: object = None
    pinned: object = None
    interpolation: str = "vertex"
    front: FaceNormals | None = None  # the faces, for normals per face or per face-vertex
    prim_path: str | None = None

    @property
    def skin(self):
        return self.group


@dataclass
class _PointsPrims:
    """The animated attributes (paths) of the particles' points prim."""

    points: object
    extent: object
    velocities: object


@dataclass
class _CurvePrims:
    """One spring family's curves: the particle of each curve vertex, the springs beside it, and the animated
    attributes (paths)."""

    particles: np.ndarray
    segments: np.ndarray
    points: object
    extent: object
    velocities: object
    strain: object


@dataclass
class _EmitterPrims:
    """An emitter's points prim: its animated attributes (paths)."""

    emitter: object  # core.emitters.Emitter
    points: object
    ids: object
    widths: object
    velocities: object
    extent: object


@dataclass
class _WorldPrims:
    """The animated prims of one exported world."""

    world: int
    meshes: list  # _SurfacePrims per cloth mesh
    points: object  # _PointsPrims of the particles, or None
    curves: list  # _CurvePrims per spring family
    emitters: list = field(default_factory=list)  # _EmitterPrims per emitter
    colliders: list = field(default_factory=list)  # (ShapeInfo, translate path, orient path) per moving collider
    skins: list = field(default_factory=list)  # _SurfacePrims per embedded surface (soft bodies)
    mesh_colliders: list = field(default_factory=list)  # (MeshCollider, points path, extent path) per deforming mesh


def _set_pose(translate, orient, frame, time=None) -> None:
    """Set a collider's translate and orient ops to ``frame`` = (position [m], quaternion (x, y, z, w)): as a
    time sample at ``time``, or as the default value when ``time`` is None."""
    from pxr import Gf, Usd

    position, (x, y, z, w) = frame
    time = Usd.TimeCode.Default() if time is None else time
    translate.Set(Gf.Vec3d(*(float(p) for p in position)), time)
    orient.Set(Gf.Quatd(float(w), float(x), float(y), float(z)), time)


def _plane_half_size(shape, particle_q: np.ndarray, tile: float | None = None) -> float:
    """Half width [m] of the quad that shows a plane: a finite plane's own; an infinite plane's twice the
    scene's reach around it, ≥ 1 m, and at most ``tile`` (half a world's cell when worlds are laid out
    side by side, so that their ground quads tile the ground instead of overlapping)."""
    if shape.size[0] > 0.0:
        return float(shape.size[0])
    R = quat_to_matrix(shape.rotation)
    local = (particle_q - np.asarray(shape.position)) @ R  # rows: particle positions in the plane frame
    reach = float(np.abs(local[:, :2]).max()) if len(local) else 0.0
    half = max(2.0 * reach, 1.0)
    return min(half, tile) if tile is not None else half
