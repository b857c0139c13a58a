"""Geometry helpers for export: area-weighted vertex normals of a triangle mesh."""

import functools

import warp as wp

from .precision import vec3_type

wp.set_module_options({"enable_backward": False})


@functools.cache
def vertex_normal_kernels(scalar: type):
    """Two kernels: accumulate triangle normals (area-weighted) into vertices, then normalise to float32."""
    vec3 = vec3_type(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def accumulate(
        tri_indices: wp.array2d[wp.int32],
        particle_q: wp.array[vec3],
        normal_sum: wp.array[wp.vec3f],
    ):
        t = wp.tid()
        i = tri_indices[t, 0]
        j = tri_indices[t, 1]
        k = tri_indices[t, 2]
        # The cross product's length is twice the area: an area-weighted sum without normalising.
        n = wp.vec3f(wp.cross(particle_q[j] - particle_q[i], particle_q[k] - particle_q[i]))
        wp.atomic_add(normal_sum, i, n)
        wp.atomic_add(normal_sum, j, n)
        wp.atomic_add(normal_sum, k, n)

    @wp.kernel(module="unique", enable_backward=False)
    def normalize(normal_in_out: wp.array[wp.vec3f]):
        i = wp.tid()
        n = normal_in_out[i]
        length = wp.length(n)
        if length > 0.0:
            normal_in_out[i] = n / length
        else:
            normal_in_out[i] = wp.vec3f(0.0, 0.0, 1.0)

    return accumulate, normalize
