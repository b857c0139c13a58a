"""Hinges of a triangle mesh for dihedral bending, and NumPy float64 references of the hinge angle and energy.

A hinge (x0, x1, x2, x3) is an interior edge x0 → x1 with the wing x2 of the triangle (x0, x1, x2) and the
wing x3 of the triangle (x1, x0, x3); its signed dihedral angle θ ∈ (-π, π] is 0 when flat and positive
when the wings fold away from the side the face normals point to (``kernels/bending.py`` has the
conventions and the device maths these functions mirror).
"""

from __future__ import annotations

import numpy as np

from ..kernels.bending import HINGE_MIN_ASPECT, HINGE_MIN_EDGE


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """``angle`` [rad] wrapped into (-π, π] (unchanged there)."""
    return angle - 2.0 * np.pi * np.ceil((angle - np.pi) / (2.0 * np.pi))


def dihedral_angle(x0: np.ndarray, x1: np.ndarray, x2: np.ndarray, x3: np.ndarray) -> np.ndarray:
    """Signed dihedral angle θ [rad] of hinges, atan2((n̂1 × n̂2)·ê, n̂1·n̂2) with n1 = e × (x2 - x0),
    n2 = (x3 - x0) × e, e = x1 - x0.

    Args:
        x0, x1, x2, x3: particle positions [m], shape [..., 3] (broadcast together).

    Returns:
        θ in (-π, π], shape [...]; 0 for degenerate hinges (edge below ``HINGE_MIN_EDGE``, or a wing
        closer to the edge's line than ``HINGE_MIN_ASPECT`` |e|), as on the device.
    """
    e, n1, n2, len_e, valid = _hinge_frame(x0, x1, x2, x3)
    # atan2 is invariant under the common positive factor |n1| |n2| |e| of both arguments.
    theta = np.arctan2(_dot(np.cross(n1, n2), e), _dot(n1, n2) * len_e)
    return np.where(valid, theta, 0.0)


def dihedral_gradient(x0: np.ndarray, x1: np.ndarray, x2: np.ndarray, x3: np.ndarray) -> np.ndarray:
    """∇θ [1/m] of hinges with respect to the four positions, the device's closed form
    (``kernels/bending.py``): ∇₂θ = -|e| n1/|n1|², ∇₃θ = -|e| n2/|n2|², ∇₁θ = -(α₂ ∇₂θ + α₃ ∇₃θ),
    ∇₀θ = -(∇₁θ + ∇₂θ + ∇₃θ).

    Args:
        x0, x1, x2, x3: particle positions [m], shape [..., 3] (broadcast together).

    Returns:
        Shape [..., 4, 3]; zero for degenerate hinges, as on the device.
    """
    x0, x1, x2, x3 = (np.asarray(x, dtype=np.float64) for x in (x0, x1, x2, x3))
    e, n1, n2, len_e, valid = _hinge_frame(x0, x1, x2, x3)
    safe = np.where(valid, 1.0, 0.0)[..., None]
    with np.errstate(divide="ignore", invalid="ignore"):
        g2 = np.nan_to_num(-(len_e / _dot(n1, n1))[..., None] * n1) * safe
        g3 = np.nan_to_num(-(len_e / _dot(n2, n2))[..., None] * n2) * safe
        along = 1.0 / np.where(valid, len_e * len_e, 1.0)
    g1 = -((_dot(x2 - x0, e) * along)[..., None] * g2 + (_dot(x3 - x0, e) * along)[..., None] * g3)
    g0 = -(g1 + g2 + g3)
    return np.stack(np.broadcast_arrays(g0, g1, g2, g3), axis=-2)


def _hinge_frame(x0, x1, x2, x3):
    """(e, n1, n2, |e|, valid) of hinges in float64: the edge, the two wing normals and whether the hinge
    is non-degenerate (edge above ``HINGE_MIN_EDGE``, both wings above ``HINGE_MIN_ASPECT`` |e| from it)."""
    x0, x1, x2, x3 = (np.asarray(x, dtype=np.float64) for x in (x0, x1, x2, x3))
    e = x1 - x0
    n1 = np.cross(e, x2 - x0)
    n2 = np.cross(x3 - x0, e)
    len_e = np.linalg.norm(e, axis=-1)
    min_n = HINGE_MIN_ASPECT * len_e**2
    valid = (len_e > HINGE_MIN_EDGE) & (np.linalg.norm(n1, axis=-1) > min_n) & (np.linalg.norm(n2, axis=-1) > min_n)
    return e, n1, n2, len_e, valid


def hinge_energy_np(
    x0: np.ndarray, x1: np.ndarray, x2: np.ndarray, x3: np.ndarray, rest: np.ndarray, ke: np.ndarray
) -> np.ndarray:
    """Elastic energy [J] ½ ke wrap(θ - θ0)² of hinges.

    Args:
        x0, x1, x2, x3: particle positions [m], shape [H, 3].
        rest: rest angles θ0 [rad], shape [H].
        ke: bending stiffness [N·m/rad], shape [H].

    Returns:
        Energies, shape [H].
    """
    d = wrap_angle(dihedral_angle(x0, x1, x2, x3) - rest)
    return 0.5 * np.asarray(ke) * d * d


def mesh_hinges(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One hinge per interior edge (shared by exactly two faces) of a triangle mesh, with its rest angle.

    The edge x0 → x1 runs as in the winding of the first face of the pair (trimesh's ``face_adjacency``
    order), x2 is that face's third vertex and x3 the other face's; faces wound consistently (outward
    normals on a closed surface) give θ > 0 at convex edges. The winding of the second face does not
    enter the hinge. Boundary edges (one face) give no hinge.

    Args:
        vertices: vertex positions [m], shape [v, 3].
        faces: vertex indices of each triangle, shape [t, 3].

    Returns:
        ``(hinges, rest_angle)``: vertex indices (x0, x1, x2, x3), int64, shape [H, 4]; rest angles θ0
        [rad], float64, shape [H].

    Raises:
        ValueError: a face repeats a vertex, or an edge is shared by more than two faces (non-manifold).
    """
    import trimesh

    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must be triangles, shape [t, 3], got {faces.shape}")
    repeated = np.flatnonzero(
        (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 2] == faces[:, 0])
    )
    if len(repeated):
        raise ValueError(f"face {int(repeated[0])} {faces[repeated[0]].tolist()} repeats a vertex")
    mesh = trimesh.Trimesh(vertices, faces, process=False, validate=False)
    # trimesh's adjacency silently skips edges of three or more faces: find them first.
    edges, counts = np.unique(mesh.edges_sorted, axis=0, return_counts=True)
    shared = np.flatnonzero(counts > 2)
    if len(shared):
        raise ValueError(
            f"edge {edges[shared[0]].tolist()} is shared by {counts[shared[0]]} faces (non-manifold mesh; "
            f"{len(shared)} such edges): a hinge needs exactly two"
        )
    first = faces[mesh.face_adjacency[:, 0]]
    wings = np.asarray(mesh.face_adjacency_unshared, dtype=np.int64)
    # The first face rotated to start after its wing, (x0, x1, x2) = (f[k+1], f[k+2], f[k]), keeps its winding.
    k = np.argmax(first == wings[:, :1], axis=1)
    rows = np.arange(len(first))
    hinges = np.stack([first[rows, (k + 1) % 3], first[rows, (k + 2) % 3], wings[:, 0], wings[:, 1]], axis=1)
    x = vertices[hinges]
    return hinges, dihedral_angle(x[:, 0], x[:, 1], x[:, 2], x[:, 3])


def hinge_lengths_areas(vertices: np.ndarray, hinges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Edge length and the areas of the two triangles of every hinge.

    Args:
        vertices: vertex positions [m], shape [v, 3].
        hinges: vertex indices (x0, x1, x2, x3), shape [H, 4].

    Returns:
        ``(edge_length, triangle_area)``: |x1 - x0| [m], shape [H]; areas [m²] of the triangles
        (x0, x1, x2) and (x1, x0, x3), shape [H, 2].
    """
    x = np.asarray(vertices, dtype=np.float64)[np.asarray(hinges, dtype=np.int64)]
    e = x[:, 1] - x[:, 0]
    n1 = np.cross(e, x[:, 2] - x[:, 0])
    n2 = np.cross(x[:, 3] - x[:, 0], e)
    area = 0.5 * np.stack([np.linalg.norm(n1, axis=-1), np.linalg.norm(n2, axis=-1)], axis=1)
    return np.linalg.norm(e, axis=-1), area
