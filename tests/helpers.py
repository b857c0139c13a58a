"""What several test modules share (no test module imports another): small scenes and drivers, the CLI's
test scene, the advisor battery's cloth, and flat meshes with the elastic moduli of a spring network on them.
"""

from __future__ import annotations

import contextlib
import gc
import pathlib
import signal

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import warp as wp
from scipy.spatial import Delaunay

import warpspring as ws
from warpspring.analysis import load_battery
from warpspring.core import material as wm

#: Whether a CUDA device is present (the ``device`` fixture then runs ``cuda:0`` too).
CUDA = wp.is_cuda_available()
ZERO_GRAVITY = (0.0, 0.0, 0.0)


def hanging_cloth(device, *, n=12, precision="float32", sphere=False, ground=False, drag=0.0, **grid):
    """A horizontal n × n cloth at z = 1 pinned at its two top corners (the ANCHORS cloth layout), with
    air drag ``drag`` [N·s/m]."""
    builder = ws.ModelBuilder(drag=drag)
    options = dict(
        nx=n,
        ny=n,
        spacing=0.1,
        origin=(-0.05 * (n - 1), -0.05 * (n - 1), 1.0),
        particle_mass=0.1,
        structural=ws.SpringMaterial(1.0e3, 10.0),
        shear=ws.SpringMaterial(1.0e3, 10.0),
        bend=ws.SpringMaterial(1.0e3, 10.0),
        pin=["top-left", "top-right"],
    )
    options.update(grid)
    ids = builder.add_cloth_grid(**options)
    if sphere:
        builder.add_collider_sphere(center=(0.0, 0.0, 0.5), radius=0.3, friction=0.5)
    if ground:
        builder.add_ground_plane(friction=0.5)
    return builder.finalize(device, precision=precision), ids


def damped_gathered_cloth(device) -> ws.Model:
    """An 8 × 8 cloth of 0.1 kg particles 0.1 m apart hanging from its top corners, structural, shear and bend springs
    of ke = 1 kN/m, kd = 10 N·s/m, gathered (the guard's unstable-dampers cases: raised past the step's damping
    limit)."""
    builder = ws.ModelBuilder()
    spring = ws.SpringMaterial(ke=1.0e3, kd=10.0)
    builder.add_cloth_grid(nx=8, ny=8, spacing=0.1, origin=(-0.35, -0.35, 1.0), particle_mass=0.1,
                           structural=spring, shear=spring, bend=spring, pin=["top-left", "top-right"])
    return builder.finalize(device, spring_evaluation="gather")


def trajectory(model, integrator, dt, steps, *, control=None, every=1):
    """Positions [steps // every + 1, particle_count, 3] (float64) of ``steps`` steps of ``dt``."""
    a, b = model.state(), model.state()
    out = [a.particle_q.numpy().astype(np.float64)]
    for k in range(1, steps + 1):
        integrator.step(a, b, control, dt)
        a, b = b, a
        if k % every == 0:
            out.append(a.particle_q.numpy().astype(np.float64))
    return np.stack(out)


def run_frames(sim: ws.Simulator, frames: int) -> np.ndarray:
    """Advance ``frames`` frames and return the final positions (float64)."""
    for _ in range(frames):
        sim.step_frame()
    wp.synchronize_device(sim.model.device)
    return sim.state.particle_q.numpy().astype(np.float64)


def loaded_modules() -> int:
    """Kernel modules loaded so far in this process, over all devices (each (module, device, block size)
    load counts once): a new compile-time constant would load a new one."""
    try:
        from warp._src.context import user_modules
    except ImportError:  # older Warp layouts
        from warp.context import user_modules
    return sum(len(module.execs) for module in list(user_modules.values()))


def driven_cloth(device, *, n: int = 32) -> ws.Model:
    """The soak's cloth (a copy of ``bench/soak.py``'s scene): n × n particles 0.1 m apart, 0.1 kg each, the grid
    turned upright about x from z = 4 m, structural + shear + bend springs (ke = 1e3 N/m, kd = 10 N·s/m), air
    drag 0.01, the two corners of its last row a pin group swung ±0.2 m along x and back every 2 s (smooth,
    cycled)."""
    builder = ws.ModelBuilder(drag=0.01)
    spring = ws.SpringMaterial(ke=1.0e3, kd=10.0)
    ids = builder.add_cloth_grid(nx=n, ny=n, spacing=0.1, particle_mass=0.1, origin=(0.0, 0.0, 4.0),
                                 structural=spring, shear=spring, bend=spring,
                                 rotation=ws.quat_from_axis_angle((1.0, 0.0, 0.0), np.pi / 2))
    swing = ws.Track([0.0, 0.5, 1.0, 1.5, 2.0], [[0, 0, 0], [0.2, 0, 0], [0, 0, 0], [-0.2, 0, 0], [0, 0, 0]],
                     interpolation="smooth", extrapolation="cycle")
    builder.add_pin_group([ids[-1, 0], ids[-1, -1]], translation=swing, name="handle")
    return builder.finalize(device)


def battery_cloth(device, stiffness):
    """The advisor battery's hanging cloth (``warpspring/analysis/load_battery.py``): 20 × 20 particles of
    0.1 kg hanging from its top corners, structural springs only (kd = 0.01 N·s/m), one world per stiffness."""
    return load_battery.battery_cloth("hanging", stiffness, device)


# -- the CLI's test scene ---------------------------------------------------------------------------------

#: A 5 × 5 cloth on a ground plane: the hanging-cloth example's feature set (springs, gravity, drag, a
#: ground plane, float32), so every scene written from it shares its compiled kernel.
SCENE = """\
[simulation]
fps = 60
frames = 5
substeps = 4

[world]
drag = 0.002

[cloth]
grid = { nx = 5, ny = 5, spacing = 0.1 }
origin = [0.0, 0.0, 1.0]
mass = 0.25
pin = ["top-left", "top-right"]
structural = { ke = 40.0, kd = 0.01 }
shear = { ke = 10.0, kd = 0.01 }
bend = { ke = 1.0, kd = 0.001 }

[[collider]]
type = "ground"
"""


def write_scene(tmp_path, replace: dict | None = None, extra: str = "", name: str = "scene.toml") -> pathlib.Path:
    """SCENE with each ``old: new`` of ``replace`` applied (each ``old`` must occur) and ``extra`` appended."""
    text = SCENE
    for old, new in (replace or {}).items():
        assert old in text, old
        text = text.replace(old, new)
    path = tmp_path / name
    path.write_text(text + extra)
    return path


def points_samples(path, prim: str = "/World/cloth") -> tuple[list[np.ndarray], list[float], float]:
    """The cloth's point samples in ``path`` in time order, their time codes, and the stage's time codes per second."""
    from pxr import Usd  # usd-core: loaded only by the tests that read a stage

    stage = Usd.Stage.Open(str(path))
    attr = stage.GetPrimAtPath(prim).GetAttribute("points")
    return [np.array(attr.Get(t)) for t in attr.GetTimeSamples()], attr.GetTimeSamples(), stage.GetTimeCodesPerSecond()


#: An OBJ whose vertex 2 carries two UVs (a seam).
SEAM_OBJ = """v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 2 0 0
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vt 0.5 0.5
vt 0.2 0.2
f 1/1 2/2 3/3
f 1/1 3/3 4/4
f 2/5 5/6 3/3
"""


# -- flat meshes and the elastic moduli of spring networks on them (cloth material tests) -----------------

#: Strain magnitude of the probes below.
STRAIN_EPS = 1.0e-6
#: Strain states (ε_xx, ε_yy, γ_xy) probed to measure C: their energies give C11, C22, C66, C12 and C16.
STRAIN_PROBES = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, 0, 1]], dtype=float) * STRAIN_EPS


def delaunay_square(n: int, side: float = 1.0, seed: int = 0):
    """Delaunay mesh of the square [0, side]² on an n × n grid of points jittered by up to ±0.3 spacing
    (boundary points stay on the boundary): vertices [n², 3], faces, and a mask of the boundary vertices."""
    a = side / (n - 1)
    rows, cols = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    p = np.stack([cols, rows], -1).reshape(-1, 2) * a
    boundary = np.any((p < 0.5 * a) | (p > side - 0.5 * a), axis=1)
    p[~boundary] += np.random.default_rng(seed).uniform(-0.3 * a, 0.3 * a, ((~boundary).sum(), 2))
    return np.c_[p, np.zeros(len(p))], Delaunay(p).simplices, boundary


def mesh_edges(faces):
    return np.unique(np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)


def mesh_hinges(faces):
    """[h, 4] hinges (shared edge, wing of one face, wing of the other) of the interior edges."""
    sides = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    wing = faces[:, [2, 0, 1]].ravel()
    key = np.sort(sides, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    pair = np.all(key[order[1:]] == key[order[:-1]], axis=1)
    first, second = order[:-1][pair], order[1:][pair]
    return np.c_[sides[first], wing[first], wing[second]]


def strained(x, v):
    """x under the affine in-plane strain v = (ε_xx, ε_yy, γ_xy)."""
    eps = np.array([[v[0], 0.5 * v[2], 0.0], [0.5 * v[2], v[1], 0.0], [0.0, 0.0, 0.0]])
    return x + x @ eps.T


def spring_energy(x0, x, pairs, k):
    """Σ ½ k (|d| - L)² per spring, shape [s]."""
    rest = np.linalg.norm(x0[pairs[:, 1]] - x0[pairs[:, 0]], axis=1)
    length = np.linalg.norm(x[pairs[:, 1]] - x[pairs[:, 0]], axis=1)
    return 0.5 * k * (length - rest) ** 2


def moduli(energy_density) -> np.ndarray:
    """The 3 × 3 matrix C [N/m] of W = ½ vᵀ C v, measured from W at the STRAIN_PROBES strains."""
    w = 2.0 * np.array([energy_density(v) for v in STRAIN_PROBES]) / STRAIN_EPS**2
    c11, c22, c66 = w[:3]
    c12, c16 = 0.5 * (w[3] - c11 - c22), 0.5 * (w[4] - c11 - c66)
    return np.array([[c11, c12, c16], [c12, c22, 0.0], [c16, 0.0, c66]])


def engineering(c):
    """(E_x, E_y, G, ν_xy) of an orthotropic C: the uniaxial-stress moduli and Poisson's ratio."""
    return c[0, 0] - c[0, 1] ** 2 / c[1, 1], c[1, 1] - c[0, 1] ** 2 / c[0, 0], c[2, 2], c[0, 1] / c[1, 1]


def network_moduli(x, faces, boundary, ke):
    """C of an edge-spring network on a flat mesh, (affine, relaxed): the energy per area of the affine
    strain, and of the linear equilibrium with the boundary vertices held on the affine field."""
    edges = mesh_edges(faces)
    area = wm.lumped_masses(wm.ClothMaterial(stretch=1, shear=1, bending=1, density=1), x, faces).sum()
    affine = moduli(lambda v: spring_energy(x, strained(x, v), edges, ke).sum() / area)

    d = x[edges[:, 1], :2] - x[edges[:, 0], :2]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    block = ke[:, None, None] * d[:, :, None] * d[:, None, :]  # [e, 2, 2] linearised spring stiffness
    rows, cols, vals = [], [], []
    for p, q, sign in [(0, 0, 1.0), (1, 1, 1.0), (0, 1, -1.0), (1, 0, -1.0)]:
        for i in range(2):
            for j in range(2):
                rows.append(2 * edges[:, p] + i)
                cols.append(2 * edges[:, q] + j)
                vals.append(sign * block[:, i, j])
    stiffness = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                              shape=(2 * len(x), 2 * len(x)))
    held = np.repeat(boundary, 2)
    solve = spla.factorized(stiffness[~held][:, ~held].tocsc())

    def relaxed_energy(v):
        u = (strained(x, v) - x)[:, :2].ravel()
        u[~held] = solve(-(stiffness[~held][:, held] @ u[held]))
        return 0.5 * u @ (stiffness @ u) / area

    return affine, moduli(relaxed_energy)


@contextlib.contextmanager
def deadline(seconds: float, error: type[BaseException] = TimeoutError):
    """Raise ``error`` in this (the main) thread after ``seconds`` of wall time (SIGALRM): a hang fails the test
    instead of stalling the suite."""
    def expire(signum, frame):
        raise error(f"took more than {seconds:g} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


@contextlib.contextmanager
def warp_allocations(device):
    """Bytes Warp allocates on ``device`` inside the block, its native memory (BVHs, meshes) included: yields a dict
    that holds on exit ``live`` (still allocated) and, on the CPU, ``peak`` (the high-water mark above the start) [B].
    The CPU is measured by Warp's allocation tracker; a CUDA device by its memory pool's counters (``peak`` None:
    the pool's high-water mark cannot be reset)."""
    from warp._src.context import runtime  # Warp's tracker counters have no public getter

    device = wp.get_device(device)
    # Free what earlier objects left to the cycle collector first: a collection inside the block would count their
    # frees against the block's allocations.
    gc.collect()
    wp.synchronize_device(device)
    found: dict = {}
    if device.is_cuda:
        start = wp.get_mempool_used_mem_current(device)
        yield found
        wp.synchronize_device(device)
        found.update(live=wp.get_mempool_used_mem_current(device) - start, peak=None)
        return
    with wp.ScopedMemoryTracker("test", print=False):
        runtime.core.wp_alloc_tracker_reset()
        yield found
        found.update(live=runtime.core.wp_alloc_tracker_get_current_bytes(),
                     peak=runtime.core.wp_alloc_tracker_get_peak_bytes())
