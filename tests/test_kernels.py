"""Kernel-level maths (@wp.func helpers) against NumPy float64 references."""

import functools

import numpy as np
import warp as wp

from warpspring.kernels.contacts import contact_funcs
from warpspring.kernels.springs import spring_funcs, spring_law_type
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
    _, sphere_distance, contact_response = contact_funcs(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def kernel(
        x: wp.array[vec3],
        v: wp.array[vec3],
        radius: scalar,
        sphere_radius: scalar,
        friction: scalar,
        dt: scalar,
        x_out: wp.array[vec3],
        v_out: wp.array[vec3],
    ):
        t = wp.tid()
        distance, normal = sphere_distance(x[t], sphere_radius)
        xo, vo = contact_response(x[t], v[t], radius, distance, normal, friction, dt)
        x_out[t] = xo
        v_out[t] = vo

    return kernel


def test_sphere_contact_response_matches_reference(device, precision):
    """Penetrating particles are projected to |x| = R + r; approaching normal velocity is removed and
    the tangential speed drops by μ·|v_n| (to zero when smaller: sticking), the position moving by h
    times that tangential change; others are untouched."""
    scalar = scalar_type(precision)
    vec3 = vec3_type(scalar)
    rng = np.random.default_rng(11)
    n, R, r, mu, h = 400, 0.5, 0.02, 0.4, 0.01
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    x = direction * rng.uniform(0.3, 0.6, (n, 1))
    v = rng.normal(size=(n, 3))
    x_out, v_out = wp.empty(n, dtype=vec3, device=device), wp.empty(n, dtype=vec3, device=device)
    wp.launch(
        contact_kernel(scalar),
        dim=n,
        inputs=[wp.array(x, dtype=vec3, device=device), wp.array(v, dtype=vec3, device=device), r, R, mu, h],
        outputs=[x_out, v_out],
        device=device,
    )
    x_out, v_out = x_out.numpy().astype(np.float64), v_out.numpy().astype(np.float64)

    dist = np.linalg.norm(x, axis=1)
    inside = dist < R + r
    vn = np.sum(v * direction, axis=1)
    vt = v - vn[:, None] * direction
    vt_len = np.linalg.norm(vt, axis=1)
    scale = np.clip(vt_len + mu * np.minimum(vn, 0.0), 0.0, None) / vt_len
    approaching = (inside & (vn < 0))[:, None]
    v_ref = np.where(approaching, vt * scale[:, None], v)
    x_ref = np.where(inside[:, None], direction * (R + r), x) + np.where(approaching, h * (v_ref - vt), 0.0)
    np.testing.assert_allclose(x_out, x_ref, **TOLERANCE[precision])
    np.testing.assert_allclose(v_out, v_ref, **TOLERANCE[precision])
    assert inside.sum() > 50 and (~inside).sum() > 50  # both branches exercised
    assert ((vt_len < mu * -vn) & inside).sum() > 5  # sticking exercised


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
