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

import importlib.util as _importlib_util
import pathlib as _pathlib
import sys as _sys


def _bind_kernels() -> None:
    """Make ``warpspring.kernels`` the ``kernels/`` of this very copy of the package.

    An installed wheel carries it as ``warpspring/kernels/``; a source checkout keeps it beside the
    package (``<checkout>/kernels``), which an editable install maps by name. That mapping names one
    checkout, so a second checkout run from its own directory would silently load the first one's
    kernels: bind the sibling folder explicitly before anything imports it.
    """
    here = _pathlib.Path(__file__).resolve().parent
    if (here / "kernels" / "__init__.py").is_file():
        return  # an installed wheel (or a link to the sibling): the ordinary import finds it
    sibling = here.parent / "kernels"
    init = sibling / "__init__.py"
    if not init.is_file():
        raise ImportError(
            f"warpspring's kernels are missing: neither {here / 'kernels'} nor {sibling} exists; "
            "reinstall with `python -m pip install -e .` from the checkout"
        )
    spec = _importlib_util.spec_from_file_location(__name__ + ".kernels", init, submodule_search_locations=[str(sibling)])
    module = _importlib_util.module_from_spec(spec)
    _sys.modules[spec.name] = module
    spec.loader.exec_module(module)


_bind_kernels()

from .core.bending import DihedralMaterial
from .core.builder import ModelBuilder, SpringMaterial
from .core.springs import SPRING_LAWS, SpringPlasticity
from .core.families import ElementFamily
from .errors import ConfigError, OutputError, SimulationError, StabilityWarning, WarpspringError
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
from .core.guards import EnergyBalance, GuardLimits
from .core.aero import AeroFamily
from .core.emitters import Emitter, PoolTooSmallWarning
from .core.handles import HandleFamily
from .core.kinematics import PinGroup
from .core.material import ClothMaterial
from .core.memory import MemoryEstimate, available_memory, estimate_memory
from .core.model import Control, MeshGroup, Model, ShapeInfo, Stabilizers, State
from .core.model import SkinGroup
from .core.softbody import SoftBody
from .core.simulator import Simulator
from .core.stepper import StepHook, Stepper
from .core.tracks import Track
from .analysis.stability import Advice, TransientPeak, advise, transient_peak
from .analysis.watch import StabilityWatch
from .core.transforms import quat_from_axis_angle

__version__ = "0.1.0"

__all__ = [
    "INTEGRATORS",
    "Advice",
    "advise",
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
