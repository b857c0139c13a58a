"""Geometry for export: area-weighted vertex normals of a triangle mesh, gathered without atomics.

Each vertex sums the cross products of its incident triangles in one fixed order (its row of a CSR
table of vertex → triangles, triangles ascending), so the normals, and the files they go into, are the
same bit for bit on every run on the same device: a float atomic sum's order, and with it the rounding,
changes from run to run on a GPU.
"""

import functools

import warp as wp

from .precision import vec3_type

wp.set_module_options({"enable_backward": False})


@wp.func
def unit_or_up(n: wp.vec3f) -> wp.vec3f:
    """``n`` normalised; +z for a zero vector (a vertex of degenerate triangles only)."""
    length = wp.length(n)
    if length > 0.0:
        return n / length
    return wp.vec3f(0.0, 0.0, 1.0)


@functools.cache
def vertex_normal_kernel(scalar: type):
    """The kernel of unit vertex normals (float32) for positions of precision ``scalar``."""
    vec3 = vec3_type(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def vertex_normals(
        # Topology:
        tri_indices: wp.array2d[wp.int32],  # [t, 3]
        vertex_tri_start: wp.array[wp.int32],  # [n + 1], CSR row starts
        vertex_tris: wp.array[wp.int32],  # [3 t], incident triangles of each vertex, ascending
        # State in:
        particle_q: wp.array[vec3],
        # Out:
        normal_out: wp.array[wp.vec3f],
    ):
        i = wp.tid()
        n = vec3(scalar(0.0))
        for e in range(vertex_tri_start[i], vertex_tri_start[i + 1]):
            t = vertex_tris[e]
            x0 = particle_q[tri_indices[t, 0]]
            # The cross product is the triangle's normal times twice its area: an area-weighted sum.
            n += wp.cross(particle_q[tri_indices[t, 1]] - x0, particle_q[tri_indices[t, 2]] - x0)
        normal_out[i] = unit_or_up(wp.vec3f(n))

    return vertex_normals
