"""Kernel-level maths (@wp.func helpers) against NumPy float64 references."""

import functools

import numpy as np
import pytest
import warp as wp

from warpspring.kernels.response import contact_response_func
from warpspring.kernels.shapes import distance_funcs
from warpspring.kernels.spring_laws import spring_funcs, spring_law_type
from warpspring.kernels.precision import scalar_type, vec3_type

# float32 rounding of O(1) inputs through a handful of operations; float64 is exact to ~1e-15.
TOLERANCE = {"float32": dict(rtol=2e-5, atol=2e-5), "float64": dict(rtol=1e-12, atol=1e-12)}


@functools.cache
def spring_kernel(scalar):
    vec3 = vec3_type(scalar)
    _, spring_force, spring_energy, _ = spring_funcs(scalar)
    hooke = spring_law_type(scalar)  # Hooke's law reads no value: an empty set of law values

    @wp.kernel(module="unique", enable_backward=False)
    def kernel(
        xi: wp.array[vec3],
        xj: wp.array[vec3],
        vi: wp.array[vec3],
        vj: wp.array[vec3],
        rest: wp.array[scalar],
        ke: wp.array[scalar],
        kd: wp.array[scalar],
        force: wp.array[vec3],
        energy: wp.array[scalar],
    ):
        t = wp.tid()
        force[t] = spring_force(xi[t], xj[t], vi[t], vj[t], rest[t], ke[t], kd[t], hooke())
        energy[t] = spring_energy(xi[t], xj[t], rest[t], ke[t], hooke())

    return kernel


def run_spring(device, precision, xi, xj, vi, vj, rest, ke, kd):
    scalar = scalar_type(precision)
    vec3 = vec3_type(scalar)
    n = len(xi)
    arrays = [wp.array(a, dtype=vec3, device=device) for a in (xi, xj, vi, vj)]
    arrays += [wp.array(a, dtype=scalar, device=device) for a in (rest, ke, kd)]
    force = wp.empty(n, dtype=vec3, device=device)
    energy = wp.empty(n, dtype=scalar, device=device)
    wp.launch(spring_kernel(scalar), dim=n, inputs=arrays, outputs=[force, energy], device=device)
    return force.numpy().astype(np.float64), energy.numpy().astype(np.float64)


def test_spring_force_matches_float64_reference(device, precision):
    """f_i = (ke(|d| - L) + kd (vj - vi)·d̂) d̂ and E = ½ ke (|d| - L)² on random springs."""
    rng = np.random.default_rng(7)
    n = 512
    xi, xj = rng.uniform(-1, 1, (n, 3)), rng.uniform(-1, 1, (n, 3))
    vi, vj = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    rest, ke, kd = rng.uniform(0, 1.5, n), rng.uniform(1, 10, n), rng.uniform(0, 2, n)
    force, energy = run_spring(device, precision, xi, xj, vi, vj, rest, ke, kd)

    d = xj - xi
    length = np.linalg.norm(d, axis=1, keepdims=True)
    dhat = d / length
    ref = dhat * (ke[:, None] * (length - rest[:, None]) + kd[:, None] * np.sum((vj - vi) * dhat, 1, keepdims=True))
    np.testing.assert_allclose(force, ref, **TOLERANCE[precision])
    np.testing.assert_allclose(energy, 0.5 * ke * (length[:, 0] - rest) ** 2, **TOLERANCE[precision])


def test_spring_force_is_antisymmetric_and_zero_for_coincident_particles(device, precision):
    """Swapping the ends negates the force exactly; coincident particles give 0, never NaN."""
    rng = np.random.default_rng(3)
    xi, xj = rng.uniform(-1, 1, (64, 3)), rng.uniform(-1, 1, (64, 3))
    vi, vj = rng.normal(size=(64, 3)), rng.normal(size=(64, 3))
    xj[:8] = xi[:8]  # coincident pairs, with and without rest length
    rest, ke, kd = np.r_[np.zeros(4), np.ones(60)], np.full(64, 5.0), np.full(64, 0.5)
    f_ij, _ = run_spring(device, precision, xi, xj, vi, vj, rest, ke, kd)
    f_ji, _ = run_spring(device, precision, xj, xi, vj, vi, rest, ke, kd)
    np.testing.assert_array_equal(f_ij, -f_ji)
    np.testing.assert_array_equal(f_ij[:8], 0.0)
    assert np.isfinite(f_ij).all()


@functools.cache
def contact_kernel(scalar):
    vec3 = vec3_type(scalar)
    _, sphere_distance, _, _ = distance_funcs(scalar)
    contact_response = contact_response_func(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def kernel(
        x: wp.array[vec3],
        v: wp.array[vec3],
        surface_velocity: vec3,
        radius: scalar,
        sphere_radius: scalar,
        friction: scalar,
        restitution: scalar,
        bounce_speed: scalar,
        dt: scalar,
        x_out: wp.array[vec3],
        v_out: wp.array[vec3],
    ):
        t = wp.tid()
        distance, normal = sphere_distance(x[t], sphere_radius)
        xo, vo = contact_response(x[t], v[t], radius, distance, normal, surface_velocity, friction, restitution,
                                  bounce_speed, dt)
        x_out[t] = xo
        v_out[t] = vo

    return kernel


@pytest.mark.parametrize("moving", [False, True], ids=["static", "moving"])
def test_sphere_contact_response_matches_reference(device, precision, moving):
    """Penetrating particles are projected to |x| = R + r. Relative to the surface velocity u, an approaching
    normal velocity v_n is removed, or reversed to -e v_n when faster than the bounce speed; the tangential
    speed drops by μ (1 + e) |v_n| (to zero when smaller: sticking), the position moving by h times that
    tangential change; others are untouched."""
    scalar = scalar_type(precision)
    vec3 = vec3_type(scalar)
    rng = np.random.default_rng(11)
    n, R, r, mu, e, bounce_speed, h = 400, 0.5, 0.02, 0.4, 0.3, 0.5, 0.01
    u = np.array([0.3, -0.2, 0.5]) if moving else np.zeros(3)
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    x = direction * rng.uniform(0.3, 0.6, (n, 1))
    v = rng.normal(size=(n, 3))
    x_out, v_out = wp.empty(n, dtype=vec3, device=device), wp.empty(n, dtype=vec3, device=device)
    wp.launch(
        contact_kernel(scalar),
        dim=n,
        inputs=[wp.array(x, dtype=vec3, device=device), wp.array(v, dtype=vec3, device=device), vec3(*u), r, R, mu,
                e, bounce_speed, h],
        outputs=[x_out, v_out],
        device=device,
    )
    x_out, v_out = x_out.numpy().astype(np.float64), v_out.numpy().astype(np.float64)

    dist = np.linalg.norm(x, axis=1)
    inside = dist < R + r
    relative = v - u
    vn = np.sum(relative * direction, axis=1)
    vt = relative - vn[:, None] * direction
    vt_len = np.linalg.norm(vt, axis=1)
    bounce = np.where(-vn > bounce_speed, e, 0.0)
    scale = np.clip(vt_len + mu * (1.0 + bounce) * np.minimum(vn, 0.0), 0.0, None) / vt_len
    approaching = (inside & (vn < 0))[:, None]
    vt_out = vt * scale[:, None]
    v_ref = np.where(approaching, u + vt_out - (bounce * vn)[:, None] * direction, v)
    x_ref = np.where(inside[:, None], direction * (R + r), x) + np.where(approaching, h * (vt_out - vt), 0.0)
    np.testing.assert_allclose(x_out, x_ref, **TOLERANCE[precision])
    np.testing.assert_allclose(v_out, v_ref, **TOLERANCE[precision])
    assert inside.sum() > 50 and (~inside).sum() > 50  # both branches exercised
    assert ((vt_len < mu * -vn) & inside & (vn < 0)).sum() > 5  # sticking exercised
    assert (approaching[:, 0] & (bounce > 0)).sum() > 5 and (approaching[:, 0] & (bounce == 0)).sum() > 5


@functools.cache
def distance_kernel(scalar):
    vec3 = vec3_type(scalar)
    _, _, box_distance, capsule_distance = distance_funcs(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def kernel(p: wp.array[vec3], half: vec3, radius: scalar, half_height: scalar, box: wp.array[scalar],
               box_normal: wp.array[vec3], capsule: wp.array[scalar], capsule_normal: wp.array[vec3]):
        t = wp.tid()
        d, n = box_distance(p[t], half)
        box[t] = d
        box_normal[t] = n
        c, m = capsule_distance(p[t], radius, half_height)
        capsule[t] = c
        capsule_normal[t] = m

    return kernel


HALF, CAPSULE_RADIUS, HALF_HEIGHT = np.array([0.3, 0.5, 0.2]), 0.25, 0.4


def box_reference(q):
    """Signed distance from the box of half extents HALF, float64: exterior Euclidean distance outside,
    minus the distance to the nearest face inside."""
    e = np.abs(q) - HALF
    return np.linalg.norm(np.maximum(e, 0.0), axis=-1) + np.minimum(e.max(axis=-1), 0.0)


def capsule_reference(q):
    """Signed distance from the capsule along z: distance to the segment minus the radius, float64."""
    axis = np.clip(q[..., 2], -HALF_HEIGHT, HALF_HEIGHT)
    return np.linalg.norm(q - np.stack([0 * axis, 0 * axis, axis], -1), axis=-1) - CAPSULE_RADIUS


def test_box_and_capsule_distances_and_normals_match_references(device):
    """Signed distances of random points equal the float64 references, and each returned outward normal is
    the reference distance's gradient (central differences of step 1e-6), at points where that gradient
    exists: off the box's medial planes inside it and off the capsule's axis."""
    rng = np.random.default_rng(5)
    p = rng.uniform(-1.0, 1.0, (2000, 3))
    outputs = [wp.empty(len(p), dtype=dtype, device=device) for dtype in (wp.float64, wp.vec3d) * 2]
    wp.launch(distance_kernel(wp.float64), dim=len(p), inputs=[wp.array(p, dtype=wp.vec3d, device=device),
              wp.vec3d(*HALF), CAPSULE_RADIUS, HALF_HEIGHT], outputs=outputs, device=device)
    box, box_normal, capsule, capsule_normal = (a.numpy() for a in outputs)
    np.testing.assert_allclose(box, box_reference(p), atol=1e-12)
    np.testing.assert_allclose(capsule, capsule_reference(p), atol=1e-12)
    assert (box < 0).sum() > 20 and (capsule < 0).sum() > 30  # inside points exercised

    ordered = np.sort(np.abs(p) - HALF, axis=1)
    smooth = ((ordered[:, 2] - ordered[:, 1] > 1e-3) | (ordered[:, 2] > 0)) & (np.hypot(p[:, 0], p[:, 1]) > 1e-3)
    step = 1e-6
    for reference, normal in ((box_reference, box_normal), (capsule_reference, capsule_normal)):
        gradient = np.stack([(reference(p + step * k) - reference(p - step * k)) / (2 * step) for k in np.eye(3)],
                            axis=1)
        np.testing.assert_allclose(normal[smooth], gradient[smooth], atol=1e-6)


@functools.cache
def stiffness_kernel(scalar):
    vec3 = vec3_type(scalar)
    mat33 = wp.types.matrix((3, 3), scalar)
    _, _, _, spring_stiffness_matrix = spring_funcs(scalar)
    hooke = spring_law_type(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def kernel(xi: wp.array[vec3], xj: wp.array[vec3], rest: scalar, ke: scalar, clamp: bool, out: wp.array[mat33]):
        t = wp.tid()
        out[t] = spring_stiffness_matrix(xi[t], xj[t], rest, ke, clamp, hooke())

    return kernel


def test_spring_stiffness_matrix_is_the_force_jacobian(device):
    """∂f_i/∂x_j matches central finite differences of the spring force (float64); the clamped matrix
    drops the negative transverse term of compressed springs and is positive semi-definite."""
    scalar = wp.float64
    rng = np.random.default_rng(2)
    n, rest, ke = 64, 1.0, 7.0
    xi = rng.uniform(-1, 1, (n, 3))
    xj = xi + rng.normal(size=(n, 3)) * rng.uniform(0.3, 1.7, (n, 1))  # stretched and compressed
    out = wp.empty(n, dtype=wp.mat33d, device=device)
    kernel = stiffness_kernel(scalar)
    wp.launch(kernel, dim=n, inputs=[wp.array(xi, dtype=wp.vec3d, device=device), wp.array(xj, dtype=wp.vec3d, device=device), rest, ke, False], outputs=[out], device=device)
    K = out.numpy()

    def force(a, b):
        d = b - a
        length = np.linalg.norm(d, axis=1, keepdims=True)
        return ke * (length - rest) * d / length

    eps = 1e-6
    for c in range(3):
        step = np.zeros(3)
        step[c] = eps
        column = (force(xi, xj + step) - force(xi, xj - step)) / (2 * eps)
        np.testing.assert_allclose(K[:, :, c], column, rtol=1e-6, atol=1e-6)

    wp.launch(kernel, dim=n, inputs=[wp.array(xi, dtype=wp.vec3d, device=device), wp.array(xj, dtype=wp.vec3d, device=device), rest, ke, True], outputs=[out], device=device)
    eigenvalues = np.linalg.eigvalsh(out.numpy())
    compressed = np.linalg.norm(xj - xi, axis=1) < rest
    assert compressed.sum() > 5 and (~compressed).sum() > 5
    assert eigenvalues.min() > -1e-12
    np.testing.assert_allclose(out.numpy()[~compressed], K[~compressed], rtol=1e-12)
