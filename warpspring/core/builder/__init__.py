"""ModelBuilder: assemble particles, springs, triangles and colliders in bulk, then finalize to a Model.

Everything is vectorised over NumPy arrays: a cloth is a handful of array operations, never one Python
call per particle (a 1024 × 1024 cloth with its 6.3 M springs builds in seconds).

One module per topic: ``model_builder`` (:class:`ModelBuilder`: particles, springs, hinges, element families,
handles, emitters, wind, self-collision, pins and tracks; composed with the recipes and finalize below),
``cloth`` (triangles, cloth grids and cloth meshes), ``soft_body`` (soft bodies from closed meshes),
``colliders`` (plane, sphere, box, capsule and mesh colliders), ``finalize`` (the model on a device and the
memory estimate before it), ``spring_materials`` (:class:`SpringMaterial` and the cloth's spring-family
arguments) and ``arguments`` (the argument checks they share).
"""

from .model_builder import ModelBuilder
from .spring_materials import SpringMaterial

__all__ = ["ModelBuilder", "SpringMaterial"]
