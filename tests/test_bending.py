"""Dihedral bending: the hinge angle and its gradient, forces, Hessian blocks, and mesh hinges.

The forces are checked against central finite differences of the energy in float64 (step h = 1e-6 m on
O(1) hinges: truncation h² θ''' ~ 1e-12, round-off ε E / h ~ 1e-10, so rtol 1e-6 has two orders of margin).
"""

import functools

import numpy as np
import pytest
import trimesh
import warp as wp
from scipy.spatial.transform import Rotation

from warpspring.core.hinges import (
    dihedral_angle,
    hinge_energy_np,
    hinge_lengths_areas,
    mesh_hinges,
    wrap_angle,
)
from warpspring.kernels.bending import dihedral_funcs
from warpspring.kernels.precision import mat33_type, scalar_type, vec3_type

FD_STEP = 1.0e-6  # [m]


@functools.cache
def hinge_kernel(scalar):
    """Everything the bending funcs compute for hinges x [n, 4] (roles 0..3) in one launch."""
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)
    funcs = dihedral_funcs(scalar)
    dihedral_angle_gradient = funcs.dihedral_angle_gradient
    hinge_energy = funcs.hinge_energy
    hinge_force = funcs.hinge_force
    hinge_stiffness_block = funcs.hinge_stiffness_block

    @wp.kernel(module="unique", enable_backward=False)
    def kernel(
        x: wp.array2d[vec3],
        v: wp.array2d[vec3],
        rest: wp.array[scalar],
        ke: wp.array[scalar],
        kd: wp.array[scalar],
        theta: wp.array[scalar],
        grad: wp.array2d[vec3],
        energy: wp.array[scalar],
        force: wp.array2d[vec3],
        stiffness: wp.array3d[mat33],
        damping: wp.array3d[mat33],
    ):
        h = wp.tid()
        x0, x1, x2, x3 = x[h, 0], x[h, 1], x[h, 2], x[h, 3]
        t, g0, g1, g2, g3 = dihedral_angle_gradient(x0, x1, x2, x3)
        theta[h] = t
        grad[h, 0] = g0
        grad[h, 1] = g1
        grad[h, 2] = g2
        grad[h, 3] = g3
        energy[h] = hinge_energy(x0, x1, x2, x3, rest[h], ke[h])
        for a in range(4):
            force[h, a] = hinge_force(a, x0, x1, x2, x3, v[h, 0], v[h, 1], v[h, 2], v[h, 3], rest[h], ke[h], kd[h])
            for b in range(4):
                stiffness[h, a, b] = hinge_stiffness_block(a, b, x0, x1, x2, x3, ke[h])
                damping[h, a, b] = hinge_stiffness_block(a, b, x0, x1, x2, x3, kd[h])

    return kernel


def evaluate(device, x, v=None, rest=0.0, ke=1.0, kd=0.0, precision="float64") -> dict:
    """Run the bending funcs on hinges x [n, 4, 3]; scalars broadcast. Results as float64 NumPy arrays:
    theta [n], grad [n, 4, 3], energy [n], force [n, 4, 3], stiffness and damping blocks [n, 4, 4, 3, 3]."""
    scalar = scalar_type(precision)
    vec3, mat33 = vec3_type(scalar), mat33_type(scalar)
    n = len(x)
    v = np.zeros_like(x) if v is None else v
    outputs = {
        "theta": wp.empty(n, dtype=scalar, device=device),
        "grad": wp.empty((n, 4), dtype=vec3, device=device),
        "energy": wp.empty(n, dtype=scalar, device=device),
        "force": wp.empty((n, 4), dtype=vec3, device=device),
        "stiffness": wp.empty((n, 4, 4), dtype=mat33, device=device),
        "damping": wp.empty((n, 4, 4), dtype=mat33, device=device),
    }
    inputs = [wp.array(a, dtype=vec3, device=device) for a in (x, v)]
    inputs += [wp.array(np.broadcast_to(a, n), dtype=scalar, device=device) for a in (rest, ke, kd)]
    wp.launch(hinge_kernel(scalar), dim=n, inputs=inputs, outputs=list(outputs.values()), device=device)
    return {name: a.numpy().astype(np.float64) for name, a in outputs.items()}


def assemble(blocks: np.ndarray) -> np.ndarray:
    """12 × 12 matrices from blocks [n, 4, 4, 3, 3]."""
    return blocks.transpose(0, 1, 3, 2, 4).reshape(-1, 12, 12)


def make_hinges(theta, length=1.0, alpha=(0.3, 0.6), height=(1.0, 1.0), rng=None) -> np.ndarray:
    """Hinges [n, 4, 3] of dihedral angle ``theta`` [rad]: edge along +x, wing x2 in the z = 0 plane at
    +y (n1 = +z), wing x3 turned from -y by θ about the edge; ``alpha``: the wings' feet along the edge
    (fractions of it), ``height``: their distances from it. With ``rng``, each hinge is rotated and moved."""
    theta = np.atleast_1d(np.asarray(theta, dtype=np.float64))
    n = len(theta)
    length, a2, a3, h2, h3 = (np.broadcast_to(np.asarray(p, dtype=np.float64), n) for p in (length, *alpha, *height))
    x = np.zeros((n, 4, 3))
    x[:, 1, 0] = length
    x[:, 2] = np.stack([a2 * length, h2, np.zeros(n)], axis=1)
    x[:, 3] = np.stack([a3 * length, -h3 * np.cos(theta), -h3 * np.sin(theta)], axis=1)
    if rng is not None:
        x = np.einsum("nij,nkj->nki", Rotation.random(n, random_state=rng).as_matrix(), x)
        x += rng.uniform(-2.0, 2.0, (n, 1, 3))
    return x


def random_hinges(rng, n, max_angle=np.pi - 0.2) -> tuple[np.ndarray, np.ndarray]:
    """n non-degenerate hinges of random shape, pose and angle in [-max_angle, max_angle], and their angles."""
    theta = rng.uniform(-max_angle, max_angle, n)
    x = make_hinges(
        theta,
        length=rng.uniform(0.5, 2.0, n),
        alpha=rng.uniform(-0.5, 1.5, (2, n)),  # obtuse triangles included
        height=rng.uniform(0.3, 1.5, (2, n)),
        rng=rng,
    )
    return x, theta


def perturbed(x: np.ndarray, h: float) -> np.ndarray:
    """Copies of x [n, 4, 3] with each of the 12 coordinates moved by +h and -h: shape [n, 12, 2, 4, 3]."""
    step = h * np.eye(12).reshape(12, 4, 3)
    return x[:, None, None] + np.stack([step, -step], axis=1)[None]


# --- The angle -----------------------------------------------------------------------------------------


def test_angle_of_known_folds(device):
    """Flat: 0; x3 folded to -z (away from n1 = n2 = +z): +π/2; to +z: -π/2; angles up to ±π."""
    x = make_hinges([0.0, 0.0, 0.0])
    x[1, 3] = [0.6, 0.0, -1.0]
    x[2, 3] = [0.6, 0.0, 1.0]
    np.testing.assert_allclose(evaluate(device, x)["theta"], [0.0, np.pi / 2, -np.pi / 2], atol=1e-15)

    # All the way round, wings nearly closed (θ → ±π) included: atan2 has no ill-conditioned range.
    theta = np.r_[np.linspace(-np.pi + 1e-9, np.pi - 1e-9, 41), -np.pi + 1e-12, np.pi - 1e-12, np.pi]
    x = make_hinges(theta, rng=np.random.default_rng(0))
    result = evaluate(device, x)["theta"]
    np.testing.assert_allclose(wrap_angle(result - theta), 0.0, atol=1e-12)  # θ = π may land on -π + ε
    assert np.all((result > -np.pi) & (result <= np.pi))
    np.testing.assert_allclose(wrap_angle(dihedral_angle(x[:, 0], x[:, 1], x[:, 2], x[:, 3]) - theta), 0.0, atol=1e-12)


def test_angle_difference_is_wrapped(device):
    """θ = 3 against θ0 = -3 is 2π - 6 short of rest, not 6 past it: E = ½ ke (6 - 2π)², and the force
    turns the hinge on through π (it does positive work on a motion that increases θ)."""
    angles = np.array([np.pi, -np.pi, 1.5 * np.pi, -1.5 * np.pi, 0.3])
    np.testing.assert_allclose(wrap_angle(angles), [np.pi, np.pi, -np.pi / 2, np.pi / 2, 0.3])
    d = 6.0 - 2.0 * np.pi
    result = evaluate(device, make_hinges([3.0]), rest=-3.0, ke=2.0)
    np.testing.assert_allclose(result["energy"], [d * d], rtol=1e-12)
    np.testing.assert_allclose(result["force"], -2.0 * d * result["grad"], rtol=1e-12)
    assert np.sum(result["force"] * result["grad"]) > 0.0


def test_angle_of_either_face_first_and_of_the_reversed_edge():
    """Either face may come first: (x1, x0, x3, x2) has the same θ; reversing the edge alone negates it."""
    x, theta = random_hinges(np.random.default_rng(1), 32)
    swapped = x[:, [1, 0, 3, 2]]
    np.testing.assert_allclose(dihedral_angle(*x.transpose(1, 0, 2)), theta, atol=1e-12)
    np.testing.assert_allclose(dihedral_angle(*swapped.transpose(1, 0, 2)), theta, atol=1e-12)
    reversed_edge = x[:, [1, 0, 2, 3]]
    np.testing.assert_allclose(dihedral_angle(*reversed_edge.transpose(1, 0, 2)), -theta, atol=1e-12)


def test_float32_matches_float64(device, precision):
    """θ and ∇θ of either precision against float64; float32 rounding of O(1) hinges (a few ulp)."""
    x, theta = random_hinges(np.random.default_rng(2), 256)
    result = evaluate(device, x, precision=precision)
    reference = evaluate(device, x)
    atol = 1e-5 if precision == "float32" else 1e-13
    np.testing.assert_allclose(result["theta"], theta, atol=atol)
    scale = np.abs(reference["grad"]).max(axis=(1, 2), keepdims=True)
    np.testing.assert_allclose(result["grad"] / scale, reference["grad"] / scale, atol=atol)


# --- Forces ---------------------------------------------------------------------------------------------


def test_force_is_the_negative_energy_gradient(device):
    """f_a = -∂E/∂x_a against central differences of hinge_energy, θ0 ≠ 0 and angles up to ±(π - 0.2)."""
    rng = np.random.default_rng(3)
    n = 64
    x, theta = random_hinges(rng, n)
    # Rest angles anywhere in (-π, π], but not within 0.1 of the energy's kink at wrap(θ - θ0) = ±π.
    rest = wrap_angle(theta + rng.uniform(-np.pi + 0.1, np.pi - 0.1, n))
    ke = rng.uniform(0.5, 5.0, n)
    result = evaluate(device, x, rest=rest, ke=ke)
    np.testing.assert_allclose(result["energy"], hinge_energy_np(*x.transpose(1, 0, 2), rest, ke), rtol=1e-12)

    xs = perturbed(x, FD_STEP)
    energy = evaluate(device, xs.reshape(-1, 4, 3), rest=np.repeat(rest, 24), ke=np.repeat(ke, 24))["energy"]
    energy = energy.reshape(n, 12, 2)
    gradient = ((energy[..., 0] - energy[..., 1]) / (2.0 * FD_STEP)).reshape(n, 4, 3)
    force = result["force"]
    scale = np.abs(force).max(axis=(1, 2), keepdims=True)
    np.testing.assert_allclose(force / scale, -gradient / scale, rtol=1e-6, atol=1e-6)


def test_forces_have_no_net_force_or_torque(device):
    """Σ_a f_a = 0 and Σ_a x_a × f_a = 0: the angle is invariant under translation and rotation."""
    rng = np.random.default_rng(4)
    x, _ = random_hinges(rng, 64)
    v = rng.normal(size=x.shape)
    force = evaluate(device, x, v, rest=rng.uniform(-3, 3, 64), ke=3.0, kd=0.5)["force"]
    scale = np.abs(force).max() * np.abs(x).max()
    np.testing.assert_allclose(force.sum(axis=1) / scale, 0.0, atol=1e-14)
    np.testing.assert_allclose(np.cross(x, force).sum(axis=1) / scale, 0.0, atol=1e-14)


def test_damping_force_opposes_the_angular_rate(device):
    """f_a = -kd θ̇ ∇_aθ, θ̇ a central difference of θ along the velocities; forces of ke and kd add."""
    rng = np.random.default_rng(5)
    n = 64
    x, _ = random_hinges(rng, n)
    v = rng.normal(size=x.shape)
    kd = rng.uniform(0.1, 2.0, n)
    result = evaluate(device, x, v, ke=0.0, kd=kd)
    ahead, behind = (evaluate(device, x + s * FD_STEP * v)["theta"] for s in (1.0, -1.0))
    theta_dot = (ahead - behind) / (2.0 * FD_STEP)
    expected = -(kd * theta_dot)[:, None, None] * result["grad"]
    scale = np.abs(expected).max(axis=(1, 2), keepdims=True)
    np.testing.assert_allclose(result["force"] / scale, expected / scale, atol=1e-6)

    rest, ke = rng.uniform(-3, 3, n), rng.uniform(0.5, 5.0, n)
    both = evaluate(device, x, v, rest=rest, ke=ke, kd=kd)["force"]
    elastic = evaluate(device, x, v, rest=rest, ke=ke)["force"]
    np.testing.assert_allclose(both, elastic + result["force"], rtol=1e-12, atol=1e-12)


# --- Hessian blocks -------------------------------------------------------------------------------------


def test_stiffness_blocks_are_the_hessian_at_rest(device):
    """K_ab = ke ∇_aθ ∇_bθᵀ: K_ab = K_baᵀ, the 12 × 12 matrix is PSD, and at θ = θ0 (where the
    Gauss-Newton approximation is exact) it is -∂f/∂x by central differences of the forces."""
    rng = np.random.default_rng(6)
    n = 32
    x, theta = random_hinges(rng, n)
    ke = rng.uniform(0.5, 5.0, n)
    result = evaluate(device, x, rest=theta, ke=ke)
    blocks = result["stiffness"]
    np.testing.assert_array_equal(blocks, blocks.transpose(0, 2, 1, 4, 3))
    k = assemble(blocks)
    eigenvalues = np.linalg.eigvalsh(k)
    assert np.all(eigenvalues >= -1e-12 * eigenvalues.max(axis=1, keepdims=True))

    xs = perturbed(x, FD_STEP).reshape(-1, 4, 3)
    force = evaluate(device, xs, rest=np.repeat(theta, 24), ke=np.repeat(ke, 24))["force"].reshape(n, 12, 2, 12)
    jacobian = ((force[:, :, 0] - force[:, :, 1]) / (2.0 * FD_STEP)).transpose(0, 2, 1)  # ∂f_i/∂x_j
    scale = np.abs(k).max(axis=(1, 2), keepdims=True)
    np.testing.assert_allclose(k / scale, -jacobian / scale, rtol=1e-5, atol=1e-7)


def test_damping_blocks_are_the_velocity_jacobian(device):
    """With k = kd the blocks give -∂f/∂v exactly: the damping force is linear in the velocities."""
    rng = np.random.default_rng(7)
    x, _ = random_hinges(rng, 32)
    v = rng.normal(size=x.shape)
    kd = rng.uniform(0.1, 2.0, 32)
    result = evaluate(device, x, v, ke=0.0, kd=kd)
    expected = -np.einsum("nij,nj->ni", assemble(result["damping"]), v.reshape(-1, 12)).reshape(-1, 4, 3)
    np.testing.assert_allclose(result["force"], expected, rtol=1e-12, atol=1e-12)


# --- Degenerate hinges ----------------------------------------------------------------------------------


def test_degenerate_hinges_give_zeros(device, precision):
    """A zero-length edge or a wing on the edge's line: θ = 0 and no force or stiffness, never NaN."""
    x = np.repeat(make_hinges([0.7]), 6, axis=0)
    x[0, 1] = x[0, 0]  # coincident edge ends
    x[1, 2] = [2.5, 0.0, 0.0]  # wing x2 on the edge's line
    x[2, 3] = [-0.5, 0.0, 0.0]  # wing x3 on the edge's line
    x[3, 2] = x[3, 0]  # wing x2 on an edge end
    x[4] = 0.0  # all four coincident
    x[5, 3] = [0.6, -1e-9, 1e-9]  # a sliver: wing height 1.4e-9 |e|
    v = np.random.default_rng(8).normal(size=x.shape)
    result = evaluate(device, x, v, rest=0.4, ke=2.0, kd=0.5, precision=precision)
    for name in ("theta", "grad", "force", "stiffness", "damping"):
        np.testing.assert_array_equal(result[name], 0.0, err_msg=name)
    np.testing.assert_allclose(result["energy"], 0.5 * 2.0 * 0.4**2, rtol=1e-6)  # θ = 0 against θ0 = 0.4
    np.testing.assert_array_equal(dihedral_angle(*x.transpose(1, 0, 2)), 0.0)


# --- Mesh hinges ----------------------------------------------------------------------------------------


def grid(m: int) -> tuple[np.ndarray, np.ndarray]:
    """A flat m × m-cell unit grid in z = 0, two triangles per cell wound counter-clockwise (normals +z)."""
    u = np.linspace(0.0, 1.0, m + 1)
    vertices = np.stack([*np.meshgrid(u, u, indexing="ij"), np.zeros((m + 1, m + 1))], axis=-1).reshape(-1, 3)
    i, j = (a.ravel() for a in np.meshgrid(np.arange(m), np.arange(m), indexing="ij"))
    c00, c10, c01, c11 = i * (m + 1) + j, (i + 1) * (m + 1) + j, i * (m + 1) + j + 1, (i + 1) * (m + 1) + j + 1
    faces = np.concatenate([np.stack([c00, c10, c11], 1), np.stack([c00, c11, c01], 1)])
    return vertices, faces


def assert_hinges_follow_the_faces(hinges: np.ndarray, faces: np.ndarray):
    """(x0, x1, x2) and (x1, x0, x3) of every hinge are faces of the mesh, in their winding."""
    rotations = {tuple(np.roll(f, r)) for f in faces.tolist() for r in range(3)}
    for h in hinges.tolist():
        assert (h[0], h[1], h[2]) in rotations and (h[1], h[0], h[3]) in rotations, h


def test_mesh_hinges_of_a_square():
    """Two triangles: one hinge along the diagonal, oriented as the first face, flat."""
    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    hinges, rest = mesh_hinges(vertices, np.array([[0, 1, 2], [0, 2, 3]]))
    np.testing.assert_array_equal(hinges, [[2, 0, 1, 3]])  # face (0, 1, 2) runs 2 → 0
    assert hinges.dtype == np.int64 and rest.dtype == np.float64
    np.testing.assert_array_equal(rest, [0.0])
    length, area = hinge_lengths_areas(vertices, hinges)
    np.testing.assert_allclose(length, [np.sqrt(2.0)], rtol=1e-15)
    np.testing.assert_allclose(area, [[0.5, 0.5]], rtol=1e-15)

    folded = vertices.copy()
    folded[3, 2] = 0.5  # x3 lifted to the side of the normals (+z): a valley, θ < 0
    assert mesh_hinges(folded, np.array([[0, 1, 2], [0, 2, 3]]))[1][0] < 0.0


def test_mesh_hinges_of_a_flat_grid():
    """A grid has V + F - 1 edges (Euler, a disk), 4m on the boundary; all hinges are flat."""
    m = 6
    vertices, faces = grid(m)
    hinges, rest = mesh_hinges(vertices, faces)
    assert len(hinges) == len(vertices) + len(faces) - 1 - 4 * m
    assert_hinges_follow_the_faces(hinges, faces)
    np.testing.assert_array_equal(rest, 0.0)


def test_mesh_hinges_of_icospheres(device):
    """Outward normals: every hinge is convex, θ0 > 0; the icosahedron's are all π - its dihedral angle,
    arccos(√5/3). Rest angles match the Warp θ; each face is counted once per edge in the areas."""
    ico = trimesh.creation.icosphere(subdivisions=0)
    hinges, rest = mesh_hinges(ico.vertices, ico.faces)
    assert len(hinges) == 30
    np.testing.assert_allclose(rest, np.arccos(np.sqrt(5.0) / 3.0), rtol=1e-14)

    sphere = trimesh.creation.icosphere(subdivisions=2)
    hinges, rest = mesh_hinges(sphere.vertices, sphere.faces)
    assert len(hinges) == len(sphere.edges_unique)  # closed: every edge is interior
    assert_hinges_follow_the_faces(hinges, sphere.faces)
    assert np.all(rest > 0.0)
    np.testing.assert_allclose(evaluate(device, sphere.vertices[hinges])["theta"], rest, rtol=1e-13)
    length, area = hinge_lengths_areas(sphere.vertices, hinges)
    np.testing.assert_allclose(area.sum(), 3.0 * sphere.area, rtol=1e-13)
    np.testing.assert_allclose(length, np.linalg.norm(np.diff(sphere.vertices[hinges[:, :2]], axis=1)[:, 0], axis=1))


def test_mesh_hinges_rejects_non_manifold_edges():
    """Three faces on one edge: a ValueError naming the edge."""
    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 1.0, 0.0], [0.5, -1.0, 0.0], [0.5, 0.0, 1.0]])
    faces = np.array([[0, 1, 2], [1, 0, 3], [1, 0, 4]])
    with pytest.raises(ValueError, match=r"edge \[0, 1\] is shared by 3 faces"):
        mesh_hinges(vertices, faces)
