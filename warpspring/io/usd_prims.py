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

#: The optional per-vertex primvars of :class:`~warpspring.io.usd.UsdWriter`.
PRIMVARS = ("strain", "pinned", "rest")
#: The purposes a collider prim may have.
PURPOSES = ("guide", "default", "render", "proxy")


class UsdPrims:
    """Prim definitions of :class:`~warpspring.io.usd.UsdWriter`, a base of it: the writer holds ``stage`` (the
    static stage), ``model``, the pxr modules (``_UsdGeom``, ``_Vt``, ``_Gf``), the chosen ``_primvars``,
    ``_purpose`` and ``_tile``, ``_previous_normals`` (the normals written last, by attribute: the fallback of a
    vertex whose faces cancel or have no area, :func:`fallback_normals`), and :meth:`~warpspring.io.usd_stream.UsdStream._animate` to register the
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

    def _define_world(self, world: int, root: str, *, particles: bool, springs: bool) -> _WorldPrims:
        """Define the prims of one exported world under ``root``; topology and constant attributes once."""
        from pxr import Sdf

        stage, UsdGeom, Vt, model = self.stage, self._UsdGeom, self._Vt, self.model
        meshes = []
        for group in model.meshes:
            mesh = self._define_polygon_mesh(f"{root}/{group.name}", group)
            primvars = UsdGeom.PrimvarsAPI(mesh)
            if group.uvs is not None:  # per vertex, or per corner where seams give a particle two UVs
                corners = group.uvs.ndim == 3
                st = primvars.CreatePrimvar(
                    "st", Sdf.ValueTypeNames.TexCoord2fArray,
                    UsdGeom.Tokens.faceVarying if corners else UsdGeom.Tokens.vertex,
                )
                st.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(group.uvs.reshape(-1, 2), dtype=np.float32)))
            authored = set()
            if group.dressing is not None:  # a USD input: its primvars, subsets and bindings as authored
                authored = self._dress(mesh, group.dressing)
            else:
                for name, faces in group.face_sets.items():
                    UsdGeom.Subset.CreateGeomSubset(mesh, name, UsdGeom.Tokens.face, Vt.IntArray.FromNumpy(faces),
                                                    familyName="warpspring")
            strain = pinned = None
            if "strain" in self._primvars and "strain" not in authored:
                strain = self._animate(primvars.CreatePrimvar(
                    "strain", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex).GetAttr())
            if "pinned" in self._primvars and "pinned" not in authored:
                pinned = self._animate(primvars.CreatePrimvar(
                    "pinned", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex).GetAttr())
            if "rest" in self._primvars and "rest" not in authored:  # the world's positions at the start
                q0 = model.particle_q.numpy().reshape(model.world_count, model.particle_count, 3)[world]
                primvars.CreatePrimvar("rest", Sdf.ValueTypeNames.Point3fArray, UsdGeom.Tokens.vertex).Set(
                    vec3_array(Vt, q0[group.particles]))
            meshes.append(_MeshPrims(
                group,
                points=self._animate(mesh.CreatePointsAttr()),
                extent=self._animate(mesh.CreateExtentAttr()),
                normals=self._animate(mesh.CreateNormalsAttr()),
                velocities=self._animate(mesh.CreateVelocitiesAttr()),
                strain=strain, pinned=pinned,
            ))

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

    def _define_skin(self, skin, world: int, root: str) -> _SkinPrims:
        """Define the USD mesh of a surface embedded in the particles (a soft body's mesh as authored): its faces,
        UVs and face sets once, like a cloth mesh's; its points, extent, normals and velocities per frame."""
        from pxr import Sdf

        UsdGeom, Vt, model = self._UsdGeom, self._Vt, self.model
        mesh = self._define_polygon_mesh(f"{root}/{skin.name}", skin)
        primvars = UsdGeom.PrimvarsAPI(mesh)
        if skin.uvs is not None:
            primvars.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex).Set(
                Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(skin.uvs, dtype=np.float32)))
        for name, faces in skin.face_sets.items():
            UsdGeom.Subset.CreateGeomSubset(mesh, name, UsdGeom.Tokens.face, Vt.IntArray.FromNumpy(faces),
                                            familyName="warpspring")
        strain = None
        if "strain" in self._primvars:
            strain = self._animate(primvars.CreatePrimvar(
                "strain", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex).GetAttr())
        if "rest" in self._primvars:
            q0 = model.particle_q.numpy().reshape(model.world_count, model.particle_count, 3)[world]
            primvars.CreatePrimvar("rest", Sdf.ValueTypeNames.Point3fArray, UsdGeom.Tokens.vertex).Set(
                vec3_array(Vt, skin.points(q0)))
        pinned = None
        if "pinned" in self._primvars:  # per frame: 1 where every particle the vertex follows is pinned
            pinned = self._animate(primvars.CreatePrimvar(
                "pinned", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex).GetAttr())
        return _SkinPrims(skin, points=self._animate(mesh.CreatePointsAttr()),
                          extent=self._animate(mesh.CreateExtentAttr()),
                          normals=self._animate(mesh.CreateNormalsAttr()),
                          velocities=self._animate(mesh.CreateVelocitiesAttr()), strain=strain, pinned=pinned)

    def _skin_samples(self, prims, q: np.ndarray, v: np.ndarray, vertex_strain, *, kinematic=None) -> list:
        """One frame's samples of an embedded surface: its vertices Σ w x and velocities Σ w v by a host product
        over the positions already read back (no extra transfer, a fixed order: the same bytes on a rerun),
        area-weighted vertex normals, and the weighted mean of its particles' strain [-] when asked for."""
        Vt, UsdGeom = self._Vt, self._UsdGeom
        skin = prims.skin
        x = skin.points(q)
        corner = x[skin.faces]
        face_normal = np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0])  # length 2 × area
        normal = np.zeros_like(x)
        total = np.zeros(len(x))  # the lengths summed: what the normal would be without cancellation
        face_length = np.linalg.norm(face_normal, axis=1)
        for k in range(3):
            np.add.at(normal, skin.faces[:, k], face_normal)
            np.add.at(total, skin.faces[:, k], face_length)
        length = np.linalg.norm(normal, axis=1)
        normal = np.divide(normal, length[:, None], out=np.zeros_like(normal), where=length[:, None] > 0.0)
        cancelled = np.flatnonzero(~(length > _CANCELLED * total))  # opposite faces, or no area around it
        if len(cancelled):
            previous = self._previous_normals.get(prims.normals)
            normal[cancelled] = fallback_normals(x, skin.faces, cancelled, self.model.up_axis,
                                                 None if previous is None else previous[cancelled])
        self._previous_normals[prims.normals] = normal
        points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(x, dtype=np.float32))
        samples = [(prims.points, points), (prims.extent, UsdGeom.PointBased.ComputeExtent(points)),
                   (prims.normals, vec3_array(Vt, normal)), (prims.velocities, vec3_array(Vt, skin.points(v)))]
        if prims.strain is not None and vertex_strain is not None:
            strain = (skin.weights * vertex_strain[skin.indices]).sum(axis=1)
            samples.append((prims.strain, Vt.FloatArray.FromNumpy(strain.astype(np.float32))))
        if prims.pinned is not None and kinematic is not None:  # held: no weight on a free particle
            held = ~((skin.weights != 0.0) & ~kinematic[skin.indices]).any(axis=1)
            samples.append((prims.pinned, Vt.IntArray.FromNumpy(held.astype(np.int32))))
        return samples

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


def fallback_normals(x: np.ndarray, faces: np.ndarray, vertices: np.ndarray, up_axis: str,
                     previous: np.ndarray | None = None) -> np.ndarray:
    """Unit normals for ``vertices`` whose summed face normals cancel (two faces of the same corners with
    opposite winding, as when two quads triangulate to one triangle both ways) or vanish (faces of no area):
    the normal of the vertex's first face (lowest index) of nonzero area; where it has none, its ``previous``
    frame's normal; where there is none, the up axis. Never a zero vector.

    Args:
        x: positions [m], shape [n, 3].
        faces: triangles, shape [t, 3] (indices into ``x``); those of the vertices suffice, in their order.
        vertices: the vertices to find normals for, shape [k].
        up_axis: "Y" or "Z", the last resort.
        previous: the vertices' normals of the frame before, shape [k, 3], or ``None``.

    Returns:
        Unit normals, shape [k, 3].
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    x = np.asarray(x, dtype=np.float64)
    corner = x[faces]
    face_normal = np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0])
    face_length = np.linalg.norm(face_normal, axis=1)
    usable = np.isfinite(face_length) & (face_length > 0.0)
    slot = np.full(len(x), -1, dtype=np.int64)
    slot[vertices] = np.arange(len(vertices))
    first = np.full(len(vertices), len(faces), dtype=np.int64)
    for k in range(3):
        s = slot[faces[:, k]]
        chosen = usable & (s >= 0)
        np.minimum.at(first, s[chosen], np.flatnonzero(chosen))
    out = np.zeros((len(vertices), 3))
    out[:, 1 if up_axis == "Y" else 2] = 1.0
    if previous is not None:
        previous = np.asarray(previous, dtype=np.float64)
        kept = np.linalg.norm(previous, axis=1) > 0.5  # a unit normal written before
        out[kept] = previous[kept]
    found = first < len(faces)
    out[found] = face_normal[first[found]] / face_length[first[found], None]
    return out


def cancelled_vertices(faces: np.ndarray) -> np.ndarray:
    """The vertices every incident triangle of which is cancelled by another of the same three vertices with the
    opposite winding: their area-weighted normal is zero at every frame. Shape [k], ascending.

    Args:
        faces: triangles, shape [t, 3].
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if not len(faces):
        return np.zeros(0, dtype=np.int64)
    order = np.argsort(faces, axis=1, kind="stable")
    key = np.take_along_axis(faces, order, axis=1)  # the corners, sorted
    sign = np.where((order[:, 1] - order[:, 0]) % 3 == 1, 1, -1)  # +1: the sorting was a rotation (same winding)
    rows = np.column_stack([faces.ravel(), np.repeat(key, 3, axis=0)])  # per corner: vertex, triangle's corners
    unique, inverse = np.unique(rows, axis=0, return_inverse=True)
    total = np.zeros(len(unique), dtype=np.int64)
    np.add.at(total, inverse.ravel(), np.repeat(sign, 3))
    return np.setdiff1d(np.unique(faces), unique[total != 0, 0])


#: Relative length below which a vertex's summed face normals count as cancelled (float64 rounding is ~1e-16).
_CANCELLED = 1.0e-9


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
class _MeshPrims:
    """The animated attributes (paths) of one exported cloth mesh."""

    group: object  # MeshGroup
    points: object
    extent: object
    normals: object
    velocities: object
    strain: object = None
    pinned: object = None


@dataclass
class _SkinPrims:
    """The animated attributes (paths) of one exported embedded surface (a soft body's mesh)."""

    skin: object  # SkinGroup
    points: object
    extent: object
    normals: object
    velocities: object
    strain: object = None
    pinned: object = None


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
    meshes: list  # _MeshPrims per cloth mesh
    points: object  # _PointsPrims of the particles, or None
    curves: list  # _CurvePrims per spring family
    emitters: list = field(default_factory=list)  # _EmitterPrims per emitter
    colliders: list = field(default_factory=list)  # (ShapeInfo, translate path, orient path) per moving collider
    skins: list = field(default_factory=list)  # _SkinPrims per embedded surface (soft bodies)
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
