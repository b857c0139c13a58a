"""warpspring: mass-spring cloth and soft bodies on NVIDIA Warp, on CUDA and CPU, exported to USD.

Typical use::

    import warpspring as ws

    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=32, ny=32, spacing=0.05, mass=0.5, origin=(0, 0, 2),
                           rotation=ws.quat_from_axis_angle((1, 0, 0), 1.5708), pin=["top-left", "top-right"])
    model = builder.finalize("cpu")
    sim = ws.Simulator(model, fps=60, substeps=16)
    sim.step_frame()
"""

from .builder import ModelBuilder, SpringMaterial
from .errors import ConfigError, SimulationError, WarpspringError
from .forces import apply_contacts, eval_forces
from .integrators import (
    INTEGRATORS,
    RK4,
    DormandPrince,
    ExplicitEuler,
    ImplicitEuler,
    Integrator,
    Midpoint,
    SymplecticEuler,
    VelocityVerlet,
    make_integrator,
)
from .guards import GuardLimits
from .model import Control, MeshGroup, Model, ShapeInfo, Stabilizers, State
from .simulation import Simulator
from .stability import Advice, advise
from .transforms import quat_from_axis_angle

__version__ = "0.1.0"

__all__ = [
    "INTEGRATORS",
    "Advice",
    "advise",
    "RK4",
    "DormandPrince",
    "ExplicitEuler",
    "ImplicitEuler",
    "Midpoint",
    "VelocityVerlet",
    "ConfigError",
    "Control",
    "Integrator",
    "MeshGroup",
    "Model",
    "ModelBuilder",
    "ShapeInfo",
    "SimulationError",
    "Simulator",
    "Stabilizers",
    "GuardLimits",
    "SpringMaterial",
    "State",
    "SymplecticEuler",
    "WarpspringError",
    "apply_contacts",
    "eval_forces",
    "make_integrator",
    "quat_from_axis_angle",
]
