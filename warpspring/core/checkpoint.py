"""Checkpoints: everything a :class:`~warpspring.core.simulator.Simulator` needs to go on with a run, saved
at full precision to one ``.npz`` file, so that a run restored from it continues bit for bit as the
uninterrupted run would on the same device.

A checkpoint holds NumPy copies of device arrays, in their own dtypes (float32 or float64 bits as they
are), under names grouped by owner:

* ``state/``: the current :class:`~warpspring.core.state.State`: ``particle_q`` [m], ``particle_qd`` [m/s],
  ``particle_f`` [N] (each shape [world_count · particle_count, 3]) and ``time`` [s] (float64, shape
  [world_count]: each world's clock, at which keyframe tracks and driven pins are evaluated);
* ``integrator/``: the integrator's :meth:`~warpspring.core.integrators.Integrator.persistent_arrays`
  (dopri5's step-size controllers, implicit Euler's warm start; none for the others);
* ``model/``: the model's arrays a user may change between frames (:data:`MODEL_ARRAYS`: the live-input
  table, ``world_enabled``, particle flags, masses and radii, rest lengths, stiffness and damping rows),
  and the colliders' current frames when a collider moves;
* ``control/``: the external force and the pin targets of control-driven pin groups, when present;
* ``springs/``: plastic springs' state (each world's rest lengths and plastic strains) and parameters
  (:data:`PLASTIC_ARRAYS`), when the model has plastic springs;
* ``families/<k>/``: the live arrays of the model's ``k``-th element family (``ElementFamily.live_arrays``: the
  tet families' per-tet values, the handles' gains and host-set targets), where it has some;
* ``colliders/<i>/``: each deforming mesh collider's current points, surface velocities, swept box and query
  range (``MeshCollider.snapshot``; ``i`` its index among the colliders), which the host set between frames;
* ``contacts/``: the contact buffer's overflow counters (the contact stage);
* ``hooks/``: the arrays the step hooks (the run-time guard) carry from one frame to the next.

A JSON header (the ``header`` entry) names the format and its version, the package and Warp versions, the
scene's counts and precision, the integrator's name and settings, fps and substeps, the frame counter,
the model's on/off switches (gravity, drag, stabilisers, held worlds), the guard's world failures and the
model's fingerprint (:func:`~.checkpoint_checks.model_fingerprint`: per key of the model as built — topology, materials,
colliders, integrator, dt — a hash and a short readable summary), which a resumed run compares with the
model it built (:meth:`Checkpoint.model_differences`). :meth:`Checkpoint.load` checks every header field's
type and range, and refuses a state that is not finite (but in worlds the guard stopped).

Not saved: the scene itself (topology, colliders and meshes as built, keyframe tracks and pin-group tracks, the element
families' fixed arrays: build the simulator from the same scene, then load), the guard's limits and
``use_graph`` (the simulator's configuration), and scratch arrays every step rewrites before reading them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import uuid
import zipfile
from pathlib import Path

import numpy as np
import warp as wp

from ..errors import ConfigError
from ..version import __version__
from ..kernels.inputs import INPUTS
from .checkpoint_checks import check_finite, check_header, integrator_settings, model_fingerprint, summary
from .guard_records import GuardReport
from .mesh_files import check_regular_file
from .records import Stabilizers

#: The format's name, stored in every header.
FORMAT = "warpspring-checkpoint"
#: The format's version: a reader refuses newer ones. Version 2 added the model's fingerprint (``model``).
FORMAT_VERSION = 2

#: Model arrays a user may change between frames (live values and in-place edits), saved and restored.
MODEL_ARRAYS = (
    "inputs",  # live inputs (gravity, drag, stabiliser thresholds), shape [world_count, INPUT_COUNT]
    "world_enabled",  # int32, shape [world_count]
    "particle_flags",  # int32, shape [world_count · particle_count] (pins released or pinned mid-run)
    "particle_mass",  # [kg], shape [1 or world_count, particle_count]
    "particle_inv_mass",  # [1/kg], same shape
    "particle_radius",  # [m], shape [particle_count]
    "spring_rest_length",  # [m], shape [spring_count]
    "spring_stiffness",  # [N/m], shape [1 or world_count, spring_count]
    "spring_damping",  # [N·s/m], shape [1 or world_count, spring_count]
    "hinge_rest_angle",  # [rad], shape [hinge_count]
    "hinge_stiffness",  # [N·m/rad], shape [1 or world_count, hinge_count]
    "hinge_damping",  # [N·m·s/rad], shape [1 or world_count, hinge_count]
)
#: Plastic springs' arrays (``Model.spring_<name>``), saved and restored when the model has some.
PLASTIC_ARRAYS = (
    "plastic_rest_length",  # [m], shape [world_count · spring_count]: the current rest lengths (state)
    "plastic_strain",  # α [-], shape [world_count · spring_count] (state)
    "yield_strain",  # [-], shape [spring_count]
    "yield_force",  # [N], shape [spring_count]
    "yield_rate",  # [1/s], shape [spring_count]
    "hardening",  # [-], shape [spring_count]
    "break_strain",  # [-], shape [spring_count]
)
#: Of those, the per-world parameters held as one row for every world or one row per world: a checkpoint
#: may hold the other layout than the model it is loaded into (the array is then replaced, not assigned).
PER_WORLD_ROWS = ("particle_mass", "particle_inv_mass", "spring_stiffness", "spring_damping", "hinge_stiffness",
                  "hinge_damping")

#: What must agree between a checkpoint and the simulator it is loaded into: header key, how to name it, and
#: how to fix a difference.
_SCENE_REMEDY = "load it into a simulator built from the scene it was saved from"
_COMPATIBILITY = (
    ("precision", "precision", _SCENE_REMEDY),
    ("worlds", "worlds", _SCENE_REMEDY),
    ("particles", "particles per world", _SCENE_REMEDY),
    ("springs", "springs", _SCENE_REMEDY),
    ("hinges", "hinges", _SCENE_REMEDY),
    ("families", "element families", _SCENE_REMEDY),
    ("colliders", "colliders", _SCENE_REMEDY),
    ("integrator", "integrator", "build the simulator with integrator=make_integrator({saved!r}, model)"),
    ("fps", "fps", "build the simulator with fps={saved!r}"),
    ("substeps", "substeps", "build the simulator with substeps={saved!r}"),
)


class Checkpoint:
    """One simulator's state at the end of a frame, held on the host (see the module docstring for what it
    holds and what it does not).

    Make one with :meth:`capture` (or ``Simulator.save_checkpoint``), write it with :meth:`save`, read it
    back with :meth:`load` and put it into a simulator with :meth:`restore` (or ``Simulator.load_checkpoint``).
    Here and in this module's functions, ``sim`` is a :class:`~warpspring.core.simulator.Simulator` (which
    imports this module, so it is named here rather than imported).

    Args:
        header: the JSON-serialisable description (format, versions, scene, integrator, frame, switches).
        arrays: the saved arrays by name (``"state/particle_q"``, ...), NumPy, in the device arrays' dtypes.
        source: the file it was read from, named in error messages (``None``: made in memory).
    """

    def __init__(self, header: dict, arrays: dict[str, np.ndarray], *, source: str | None = None):
        self.header = header
        self.arrays = arrays
        self.source = source

    @property
    def frame(self) -> int:
        """Frames the saved simulator had completed."""
        return int(self.header["frame"])

    def world_failures(self) -> dict:
        """The saved simulator's ``world_failures``: world → (frame, :class:`~warpspring.core.guard_records.GuardReport`)."""
        return {int(item["world"]): (int(item["frame"]), GuardReport(**item["report"]))
                for item in self.header["world_failures"]}

    # -- capture and restore ----------------------------------------------------------------------------------

    @classmethod
    def capture(cls, sim) -> Checkpoint:
        """Copy everything ``sim`` needs to go on from its current frame (reads the device: synchronises)."""
        model = sim.model
        arrays = {name: array.numpy().copy() for name, array in live_arrays(sim).items()}
        arrays.update(collider_arrays(model))
        header = {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "warpspring_version": __version__,
            "warp_version": wp.config.version,
            "device": str(model.device),
            **_configuration(sim),
            "integrator_settings": integrator_settings(sim.integrator),
            "frame": sim.frame,
            "switches": {
                "gravity": model.gravity_enabled,
                "drag": model.drag_enabled,
                "hold_worlds": model.holds_worlds,
                "stabilizers": dataclasses.asdict(model.stabilizers),
            },
            "world_failures": [{"world": int(w), "frame": int(frame), "report": dataclasses.asdict(report)}
                               for w, (frame, report) in sorted(sim.world_failures.items())],
            "arrays": sorted(arrays),
            "model": model_fingerprint(sim),
        }
        return cls(header, arrays)

    def restore(self, sim) -> None:
        """Put this checkpoint into ``sim``: its state, frame counter and world failures, the integrator's
        persistent arrays and settings, the model's live arrays and switches, the control's inputs, the
        contact overflow counters and the hooks' records.

        Arrays are written into the simulator's existing device arrays (``array.assign``), so a captured
        frame graph, which reads them in place, stays valid. Where the checkpoint needs a structure the
        simulator lacks (gravity or drag switched on, other stabilisers, held worlds, an external force, one
        row per world of a parameter), it is set up through the public setters, which count as structural
        changes: the stepper re-captures at the next frame. Everything is checked before anything is
        written. ``Simulator.load_checkpoint`` calls this and then re-derives the simulator's own caches.

        Raises:
            ConfigError: the checkpoint was saved from another scene, integrator, fps or substeps (the
                message names the difference and the fix), or holds an array this simulator has not.
        """
        self.check_configuration(sim)
        plan = self._plan(sim)
        colliders = self._collider_plan(sim)
        self._restore_structure(sim)
        model = sim.model
        live = live_arrays(sim)
        for key, values in plan:
            owner, name = key.split("/", 1)
            if owner == "model" and name in PER_WORLD_ROWS and live[key].shape != values.shape:
                # One row for all worlds against one per world: a new array (a structural change).
                setattr(model, name, wp.array(values, dtype=model.scalar, device=model.device))
            elif owner == "families":
                k, array_name = name.split("/", 1)
                model.families[int(k)].restore_live_array(model, array_name, values)
            elif values.size:
                live[key].assign(values)
        model.refresh_spring_layout()  # saved per-spring values within a group read per group: per spring now
        for collider, values in colliders:
            collider.restore_snapshot(values)
        sim.frame = self.frame
        sim.world_failures = self.world_failures()

    def model_differences(self, sim) -> list[str]:
        """The keys of :func:`model_fingerprint` in which the model this checkpoint was saved from differs from
        ``sim``'s (as built: call this before :meth:`restore`, which writes the saved live values over
        it), each as ``"key (saved: summary; now: summary)"``; empty when they agree, and for a checkpoint of
        format 1, which recorded no fingerprint."""
        saved = self.header.get("model")
        if saved is None:
            return []
        mine = model_fingerprint(sim)
        return [f"{key} (saved: {summary(saved.get(key))}; now: {summary(mine.get(key))})"
                for key in sorted(set(saved) | set(mine))
                if (saved.get(key) or {}).get("hash") != (mine.get(key) or {}).get("hash")]

    def check_configuration(self, sim) -> None:
        """Raise a one-line ConfigError naming the first of the counts, precision, integrator, fps and substeps
        that differ between this checkpoint and ``sim``, and how to fix it."""
        mine = _configuration(sim)
        saved = self.header
        for key, label, remedy in _COMPATIBILITY:
            if saved.get(key) != mine[key]:
                raise ConfigError(f"{self._name()} was saved with {label} {_show(saved.get(key))}, but this "
                                  f"simulator has {_show(mine[key])}: {remedy.format(saved=saved.get(key))}")

    def _plan(self, sim) -> list[tuple[str, np.ndarray]]:
        """The saved arrays to write, in order, each checked against the simulator's array of that name."""
        live = live_arrays(sim)
        # An external force the simulator's control has not allocated yet is allocated by the restore.
        if "control/particle_force" not in live:
            live["control/particle_force"] = sim.state.particle_q
        # Checkpoints from before the families' live arrays were saved leave them as the scene built them.
        optional = ("hooks/", "control/particle_force", "families/")
        missing = sorted(key for key in live if key not in self.arrays and not key.startswith(optional))
        if missing:
            raise ConfigError(f"{self._name()} lacks {missing[0]}, which this simulator has: {_SCENE_REMEDY}")
        plan = []
        for key in sorted(self.arrays):
            values = self.arrays[key]
            if key.startswith("colliders/"):
                continue  # host-side: _collider_plan
            if key not in live:
                if key.startswith("hooks/"):
                    continue  # the simulator runs without that hook (e.g. no guard): nothing to carry
                raise ConfigError(f"{self._name()} holds {key}, which this simulator has not: "
                                  f"{_SCENE_REMEDY}")
            shape, dtype = _layout(live[key])
            owner, name = key.split("/", 1)
            if owner == "hooks" and values.ndim == len(shape) and values.shape[:-1] == shape[:-1] and \
                    values.shape[-1] < shape[-1]:
                # A hook's record from a version with fewer slots per entry (the guard's running sums gained the
                # working families' work, zero at every frame's end): the new slots start at zero.
                values = np.concatenate([values, np.zeros(values.shape[:-1] + (shape[-1] - values.shape[-1],),
                                                          dtype=values.dtype)], axis=-1)
            rows_differ = (owner == "families" or (owner == "model" and name in PER_WORLD_ROWS)) and \
                values.shape[1:] == shape[1:] and values.shape[0] in (1, sim.model.world_count)
            if values.dtype != dtype or (values.shape != shape and not rows_differ):
                raise ConfigError(f"{self._name()} holds {key} of shape {values.shape} ({values.dtype}), but this "
                                  f"simulator's is {shape} ({dtype}): {_SCENE_REMEDY}")
            plan.append((key, values))
        return plan

    def _collider_plan(self, sim) -> list:
        """(collider, snapshot) of each deforming mesh collider the checkpoint holds, each checked against the
        simulator's (checkpoints from before colliders were saved hold none: the points stay as they are)."""
        saved: dict[int, dict] = {}
        for key, values in self.arrays.items():
            if key.startswith("colliders/"):
                _, index, name = key.split("/", 2)
                saved.setdefault(int(index), {})[name] = values
        deforming = {c.index: c for c in sim.model.mesh_colliders if c.info.deforming}
        plan = []
        for index, values in sorted(saved.items()):
            collider = deforming.get(index)
            shape = None if collider is None else collider.points().shape
            if collider is None or values.get("points", np.empty(0)).shape != shape or \
                    set(values) != set(collider.SNAPSHOT):
                raise ConfigError(f"{self._name()} holds the points of a deforming mesh collider {index} that this "
                                  f"simulator has not (or of another vertex count): {_SCENE_REMEDY}")
            plan.append((collider, values))
        return plan

    def _restore_structure(self, sim) -> None:
        """Set up, through the public setters, the switches and inputs the saved run had and ``sim`` lacks."""
        model, control, switches = sim.model, sim.control, self.header["switches"]
        if "control/particle_force" in self.arrays and control.particle_force is None:
            control.set_particle_force(np.zeros(3))  # allocates it; the saved values follow
        elif "control/particle_force" not in self.arrays and control.particle_force is not None:
            control.particle_force = None
        stabilizers = Stabilizers(**switches["stabilizers"])
        if stabilizers != model.stabilizers:
            model.stabilizers = stabilizers
        inputs = self.arrays["model/inputs"]
        for name, enabled in (("gravity", model.gravity_enabled), ("drag", model.drag_enabled)):
            slot, width = INPUTS[name]
            values = inputs[:, slot: slot + width].astype(np.float64)
            if switches[name] and not enabled and values.any():
                model.set_world_values(name, values)  # switches the term on; the saved bits follow
        if switches["hold_worlds"]:
            model.hold_worlds()
        for name, value in self.header["integrator_settings"].items():
            if getattr(sim.integrator, name) != value:
                setattr(sim.integrator, name, value)

    def _name(self) -> str:
        return f"checkpoint {self.source}" if self.source is not None else "the checkpoint"

    # -- files ----------------------------------------------------------------------------------------------

    def save(self, path: str | os.PathLike) -> Path:
        """Write the checkpoint to ``path`` (used as given: add ``.npz`` yourself) as one ``.npz`` file.

        The file is written under a temporary name in the same directory, flushed to disk, and then renamed
        over ``path`` (``os.replace``), so an interrupted save never leaves a partial file under ``path``: a
        checkpoint already there stays intact.

        Returns:
            The path written.

        Raises:
            ConfigError: the directory does not exist or cannot be written.
        """
        path = Path(path)
        temporary = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
        try:
            file = open(temporary, "xb")
        except OSError as exc:
            raise ConfigError(f"cannot write checkpoint {path}: {exc.strerror} ({path.parent})") from None
        try:
            with file:
                np.savez(file, header=np.array(json.dumps(self.header)), **self.arrays)
                file.flush()
                os.fsync(file.fileno())
            os.replace(temporary, path)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(temporary)
            raise
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> Checkpoint:
        """Read a checkpoint written by :meth:`save` (every array is read and checked here).

        Raises:
            ConfigError: the file does not exist, is not a warpspring checkpoint, is truncated or damaged, or
                was written by a newer format version.
        """
        path = Path(path)
        name = f"checkpoint {path}"
        if not path.exists():
            raise ConfigError(f"{name} does not exist (or is not a file)")
        check_regular_file(path, "checkpoint")  # a named pipe would block the reader
        try:
            data = np.load(path, allow_pickle=False)
            if not isinstance(data, np.lib.npyio.NpzFile):
                raise ValueError("a single array, not an .npz archive")
            with data:
                arrays = {key: data[key] for key in data.files}
        except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as exc:
            raise ConfigError(f"{name} cannot be read ({_reason(exc)}): it is truncated, damaged or not a "
                              "warpspring checkpoint; save it again") from None
        try:
            header = json.loads(str(arrays.pop("header")))
            if not isinstance(header, dict) or header.get("format") != FORMAT:
                raise ValueError
        except (KeyError, ValueError):
            raise ConfigError(f"{name} is not a warpspring checkpoint (no {FORMAT} header): save one with "
                              "Simulator.save_checkpoint") from None
        version = header.get("format_version")
        if not isinstance(version, int) or version > FORMAT_VERSION:
            raise ConfigError(f"{name} has format version {version!r}, newer than this warpspring "
                              f"({header.get('warpspring_version')!r} wrote it; this one reads version "
                              f"{FORMAT_VERSION}): upgrade warpspring")
        check_header(header, name)
        missing = sorted(set(header["arrays"]) - set(arrays))
        if missing:
            raise ConfigError(f"{name} lacks {len(missing)} of its arrays (first: {missing[0]}): it is damaged; "
                              "save it again")
        check_finite(header, arrays, name)
        return cls(header, arrays, source=str(path))


def live_arrays(sim) -> dict[str, wp.array]:
    """Every device array of ``sim`` a checkpoint holds, by checkpoint name (see the module docstring)."""
    model, control = sim.model, sim.control
    state = sim.state
    arrays = {f"state/{name}": getattr(state, name) for name in ("particle_q", "particle_qd", "particle_f", "time")}
    arrays.update({f"integrator/{name}": array for name, array in sim.integrator.persistent_arrays().items()})
    arrays.update({f"model/{name}": getattr(model, name) for name in MODEL_ARRAYS})
    if model.spring_plastic_count:
        # Plastic springs' state (each world's rest lengths, plastic strains) and their live parameters.
        arrays.update({f"springs/{name}": getattr(model, f"spring_{name}") for name in PLASTIC_ARRAYS})
    if model.shape_moving:
        arrays["model/shape_transform_start"] = model.shape_arrays.transform_start
        arrays["model/shape_transform_end"] = model.shape_arrays.transform_end
    if control.particle_force is not None:
        arrays["control/particle_force"] = control.particle_force
    if control.pin_targets is not None:
        arrays["control/pin_target_position"] = control.pin_targets.position
        arrays["control/pin_target_time"] = control.pin_targets.time
    for k, family in enumerate(model.families):
        arrays.update({f"families/{k}/{name}": array for name, array in family.live_arrays().items()})
    if sim.contacts is not None:
        arrays["contacts/overflow"] = sim.contacts.arrays.overflow
    for k, hook in enumerate(sim.stepper.hooks):
        arrays.update({f"hooks/{k}/{j}": array for j, array in enumerate(hook.history())})
    return arrays


def collider_arrays(model) -> dict[str, np.ndarray]:
    """The deforming mesh colliders' snapshots (host copies), by checkpoint name (see the module docstring)."""
    return {f"colliders/{c.index}/{name}": values for c in model.mesh_colliders if c.info.deforming
            for name, values in c.snapshot().items()}


def _configuration(sim) -> dict:
    """What a checkpoint must agree on with the simulator it is loaded into (see ``_COMPATIBILITY``)."""
    model = sim.model
    return {
        "precision": model.precision,
        "worlds": model.world_count,
        "particles": model.particle_count,
        "springs": model.spring_count,
        "hinges": model.hinge_count,
        "families": [family.name for family in model.families],
        "colliders": model.shape_count,
        "integrator": sim.integrator.name,
        "fps": sim.fps,
        "substeps": sim.substeps,
    }


def _layout(array: wp.array) -> tuple[tuple, np.dtype]:
    """The shape and dtype of ``array.numpy()``, without reading the device."""
    dtype = array.dtype
    scalar = getattr(dtype, "_wp_scalar_type_", dtype)
    return (*array.shape, *getattr(dtype, "_shape_", ())), np.dtype(wp.dtype_to_numpy(scalar))


def _show(value) -> str:
    if isinstance(value, list):
        return "[" + ", ".join(map(str, value)) + "]"
    return str(value)


def _reason(exc: Exception) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__
