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

from .core.bending import DihedralMaterial
from .core.builder import ModelBuilder, SpringMaterial
from .core.springs import SPRING_LAWS, SpringPlasticity
from .core.families import ElementFamily
from .errors import ConfigError, OutputError, SimulationError, SolverWarning, StabilityWarning, WarpspringError
from .core.contacts import Contacts, apply_contacts, collide
from .core.contacts import apply_triangle_contacts
from .core.mesh_colliders import MeshCollider
from .core.forces import eval_forces
from .core.integrators import (
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
from .core.guard_records import EnergyBalance, GuardLimits
from .core.aero import AeroFamily
from .core.emitters import Emitter, PoolTooSmallWarning
from .core.handles import HandleFamily
from .core.kinematics import PinGroup
from .core.material import ClothMaterial
from .core.memory import MemoryEstimate, available_memory, estimate_memory
from .core.model import Model
from .core.state import State
from .core.control import Control
from .core.records import MeshGroup, ShapeInfo, Stabilizers
from .core.records import SkinGroup
from .core.softbody import SoftBody
from .core.simulator import FrameHook, Simulator
from .core.stepper import StepHook, Stepper
from .core.tracks import Track
from .analysis.advisor import Advice, advise
from .analysis.step_choice import SubstepChoice, auto_substeps, choose_substeps
from .analysis.under_load import TransientPeak, transient_peak
from .analysis.watch import StabilityWatch
from .core.adjoint import DiffRun, SmoothContact, Target
from .core.adjoint_params import ParameterMap
from .analysis.fit import FitResult, Motion, fit
from .core.transforms import quat_from_axis_angle

from .version import __version__  # noqa: F401  (the package's version, warpspring.__version__)

__all__ = [
    "INTEGRATORS",
    "DiffRun",
    "SmoothContact",
    "Target",
    "ParameterMap",
    "FitResult",
    "Motion",
    "fit",
    "Advice",
    "advise",
    "SubstepChoice",
    "auto_substeps",
    "choose_substeps",
    "TransientPeak",
    "transient_peak",
    "RK4",
    "DormandPrince",
    "ExplicitEuler",
    "ImplicitEuler",
    "Midpoint",
    "VelocityVerlet",
    "AeroFamily",
    "ClothMaterial",
    "Emitter",
    "HandleFamily",
    "PoolTooSmallWarning",
    "ConfigError",
    "Control",
    "DihedralMaterial",
    "ElementFamily",
    "MemoryEstimate",
    "Integrator",
    "MeshGroup",
    "SkinGroup",
    "SoftBody",
    "Model",
    "ModelBuilder",
    "OutputError",
    "PinGroup",
    "ShapeInfo",
    "SimulationError",
    "Simulator",
    "FrameHook",
    "SolverWarning",
    "StabilityWarning",
    "StabilityWatch",
    "Stabilizers",
    "StepHook",
    "Stepper",
    "EnergyBalance",
    "GuardLimits",
    "SpringMaterial",
    "SpringPlasticity",
    "SPRING_LAWS",
    "State",
    "SymplecticEuler",
    "Track",
    "WarpspringError",
    "Contacts",
    "MeshCollider",
    "apply_contacts",
    "apply_triangle_contacts",
    "available_memory",
    "collide",
    "estimate_memory",
    "eval_forces",
    "make_integrator",
    "quat_from_axis_angle",
]
