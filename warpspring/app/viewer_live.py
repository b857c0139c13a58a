"""``warpspring run SCENE --view``: a running simulation in the browser, with its live inputs in the page.

:class:`LiveView` is a :class:`~warpspring.core.simulator.FrameHook`. After a frame it applies what the page
changed since the last one (gravity, drag, wind velocity, the spring stiffness scale, the enabled stabilisers'
limits, the targets of PD handles dragged in the view: values in the model's device arrays, which the next
frame's replay reads with no recompile and no re-capture; pause, step and reset), then hands the frame to the
page through a slot of depth one: if the page has not taken the previous frame yet, or the page's frame rate is
reached, the frame is dropped from the view. The run and its USD file never wait for the page: a server thread
draws, the simulation thread only copies the positions to the host when the slot is free; layers the page
hides are neither built nor sent. Only "pause" holds the run, because the page asked for it.

The stiffness scale multiplies every spring's stiffness as the scene built it. Its range stops where the
advisor's verdict at the run's step stops holding: the top frequency of a spring network grows as √scale
(for scale ≥ 1, ω²(s) = λ_max(M⁻¹(s K_springs + K_other)) ≤ s ω²(1)), so the step dt stays within the
stable step dt_stable found at scale 1 while scale ≤ (dt_stable / dt)²; an integrator stable at any step
gets the slider's own range, a run already past its limit none above 1. Values sent from outside the
range are clamped on the server, not only by the slider.
"""

from __future__ import annotations

import dataclasses
import threading
import time

import numpy as np

from ..core.records import STABILIZER_INPUTS
from ..core.simulator import FrameHook, Simulator
from ..core.transforms import quat_to_matrix
from ..io.usd import world_offsets
from ..kernels.kinematics import PARTICLE_KINEMATIC
from .viewer import Picture, Surface, Viewer

#: The stiffness scale's range where no step limit binds it (implicit integrators).
STIFFNESS_RANGE = (0.05, 10.0)


def _rows(particles: np.ndarray):
    """The particle indices of a surface as a slice where they are one ascending run (a view, no copy)."""
    p = np.asarray(particles)
    if len(p) and p[-1] - p[0] + 1 == len(p) and np.all(np.diff(p) == 1):
        return slice(int(p[0]), int(p[-1]) + 1)
    return p


def stiffness_limit(dt: float, dt_stable: float) -> float:
    """The largest spring stiffness scale that keeps the step ``dt`` [s] within a stable step ``dt_stable`` [s]
    found at scale 1 (see the module's docstring), capped at the slider's range."""
    if not dt_stable < float("inf"):
        return STIFFNESS_RANGE[1]
    if dt_stable < dt:  # already past the limit: no stiffer
        return 1.0
    return float(min((dt_stable / dt) ** 2, STIFFNESS_RANGE[1]))


class LiveView(FrameHook):
    """The page of a running simulation.

    Args:
        host, port: where the page listens (see :class:`~warpspring.app.viewer.Viewer`).
        rate: most frames per second sent to the page [1/s]; the others are dropped from the view.
    """

    def __init__(self, *, host: str = "127.0.0.1", port: int = 0, rate: float = 30.0, title: str = "warpspring"):
        self.host, self.port, self.rate, self.title = host, port, rate, title
        self.viewer: Viewer | None = None
        self.sim: Simulator | None = None
        self.sent = 0  # frames handed to the page
        self.dropped = 0  # frames the page did not get
        self._pending: dict = {}
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._slot = None  # the frame waiting for the page: (frame, time, q, qd)
        self._last_sent = 0.0
        self._closed = False
        self._paused = False
        self._steps = 0

    @property
    def url(self) -> str:
        return self.viewer.url

    def attach(self, sim: Simulator, advice=None) -> LiveView:
        """Serve the page of ``sim`` and run after its frames; ``advice`` (the run's
        :class:`~warpspring.analysis.advisor.Advice`) bounds the stiffness scale."""
        self.sim = sim
        model = sim.model
        self.viewer = Viewer(host=self.host, port=self.port, up_axis=model.up_axis, title=self.title)
        self._offsets = (world_offsets(model) if model.world_count > 1 else np.zeros((1, 3))).astype(np.float32)
        self._mesh_rows = [_rows(g.particles) for g in model.meshes]  # a slice where contiguous: no gather
        self._base_stiffness = model.spring_stiffness.numpy().astype(np.float64) if model.spring_count else None
        dt_stable = advice.dt_stable if advice is not None else float("inf")
        self.stiffness_max = stiffness_limit(sim.dt, dt_stable)
        self._springs = model.spring_indices.numpy().astype(np.int64) if model.spring_count else None
        x0 = model.particle_q.numpy()[: model.particle_count].astype(np.float64)
        self._collider_meshes = [self._colliders(x0, offset) for offset in self._offsets]  # at rest: drawn once
        self._build_controls(model)
        sim.add_frame_hook(self)
        self._thread = threading.Thread(target=self._serve, name="warpspring-view-live", daemon=True)
        self._thread.start()
        self._offer(sim, force=True)
        return self

    # -- the page's controls ----------------------------------------------------------------------------------

    def _build_controls(self, model) -> None:
        gui = self.viewer.server.gui
        with gui.add_folder("Run", order=-1):
            self.frame_text = gui.add_markdown("frame 0")
            self.pause = gui.add_checkbox("pause", False)
            self.step = gui.add_button("step one frame")
            self.reset = gui.add_button("reset")
        self.pause.on_update(lambda _: self._set("pause", bool(self.pause.value)))
        self.step.on_click(lambda _: self._set("step", True))
        self.reset.on_click(lambda _: self._set("reset", True))
        with gui.add_folder("Live inputs", order=-0.5):
            g = model.gravity
            self.gravity = gui.add_vector3("gravity [m/s²]", g, min=(-50.0,) * 3, max=(50.0,) * 3, step=0.1)
            self.drag = gui.add_number("drag [N·s/m]", float(model.drag), min=0.0, max=100.0, step=0.001)
            self.wind = gui.add_vector3("wind [m/s]", tuple(model.world_values("wind")[0]), min=(-100.0,) * 3,
                                        max=(100.0,) * 3, step=0.1)
            self.stiffness = None
            if self._base_stiffness is not None:
                self.stiffness = gui.add_slider(
                    "spring stiffness ×", STIFFNESS_RANGE[0], self.stiffness_max, 0.01, 1.0,
                    hint=f"up to {self.stiffness_max:.3g}: the advisor's stable range at this step")
                self.stiffness.on_update(lambda _: self._set("stiffness", float(self.stiffness.value)))
            self.stabilizers = {}
            for name in STABILIZER_INPUTS:
                value = getattr(model.stabilizers, name)
                if model.stabilizers.enabled(name) and value is not None:
                    handle = gui.add_number(name, float(value), min=0.0, step=float(value) / 100 or 0.01)
                    handle.on_update(lambda _, n=name, h=handle: self._set(n, float(h.value)))
                    self.stabilizers[name] = handle
        self.handles = {}
        family = model.handles
        for k, handle in enumerate(family.handles if family is not None else ()):
            if handle.translation is not None:  # follows a track: not the page's to move
                continue
            gizmo = self.viewer.server.scene.add_transform_controls(
                f"/handles/{handle.name}", scale=0.25, disable_rotations=True,
                position=tuple(np.asarray(handle.pivot, dtype=np.float64) + self._offsets[0]))
            gizmo.on_update(lambda _, k=k, g=gizmo, h=handle: self._set(
                ("handle", k), tuple(np.asarray(g.position, dtype=np.float64) - self._offsets[0] - h.pivot)))
            self.handles[handle.name] = gizmo
        self.gravity.on_update(lambda _: self._set("gravity", tuple(self.gravity.value)))
        self.drag.on_update(lambda _: self._set("drag", float(self.drag.value)))
        self.wind.on_update(lambda _: self._set("wind", tuple(self.wind.value)))

    def _set(self, name: str, value) -> None:
        with self._wake:
            if name == "step":
                self._steps += 1
            elif name == "pause":
                self._paused = value
            else:
                self._pending[name] = value
            self._wake.notify_all()

    def apply(self, sim: Simulator, changes: dict) -> None:
        """Write the page's changes into the model (between frames, on the simulation's thread)."""
        model = sim.model
        if "reset" in changes:
            sim.reset()
        if "gravity" in changes:
            model.gravity = changes["gravity"]
        if "drag" in changes:
            model.drag = max(0.0, changes["drag"])
        if "wind" in changes:
            model.set_world_values("wind", np.asarray(changes["wind"], dtype=np.float64))
        if "stiffness" in changes and self._base_stiffness is not None:
            scale = float(np.clip(changes["stiffness"], STIFFNESS_RANGE[0], self.stiffness_max))
            self.stiffness_scale = scale
            model.set_world_values("spring_stiffness", self._base_stiffness * scale)
        for name, value in changes.items():
            if isinstance(name, tuple) and name[0] == "handle":  # a handle's target dragged in the page
                model.handles.set_target(name[1], value)
        limits = {n: max(0.0, v) for n, v in changes.items() if n in STABILIZER_INPUTS}
        if limits:
            model.stabilizers = dataclasses.replace(model.stabilizers, **limits)

    # -- after every frame (the simulation's thread) ----------------------------------------------------------

    def after_frame(self, sim: Simulator, frame: int) -> None:
        with self._wake:
            changes, self._pending = self._pending, {}
        if changes:
            self.apply(sim, changes)
        self._offer(sim)
        with self._wake:
            while self._paused and not self._steps and not self._closed:
                self._wake.wait(0.1)
                if self._pending:
                    changes, self._pending = self._pending, {}
                    self._wake.release()
                    try:
                        self.apply(sim, changes)
                        self._offer(sim, force=True)
                    finally:
                        self._wake.acquire()
            if self._steps:
                self._steps -= 1

    def _offer(self, sim: Simulator, *, force: bool = False) -> None:
        """Hand the current state to the page if its slot is free and the rate allows; else drop it."""
        now = time.monotonic()
        with self._wake:
            free = self._slot is None and (force or now - self._last_sent >= 1.0 / self.rate)
        if not free:
            self.dropped += 1
            return
        state = sim.state
        q = state.particle_q.numpy()
        qd = state.particle_qd.numpy() if self.viewer.color_by.value == "speed" else None  # only what is drawn
        flags = sim.model.particle_flags.numpy() if self.viewer.show_pins.value else None
        with self._wake:
            self._slot = (sim.frame, sim.time, q, qd, flags)
            self._last_sent = now
            self.sent += 1
            self._wake.notify_all()

    # -- the page's thread --------------------------------------------------------------------------------------

    def _serve(self) -> None:
        while True:
            with self._wake:
                while self._slot is None and not self._closed:
                    self._wake.wait()
                if self._closed:
                    return
                frame, t, q, qd, flags = self._slot
            self.viewer.show(self.picture(q, qd, flags, t))
            self.frame_text.content = f"frame {frame} (t = {t:.3f} s)"
            with self._wake:
                self._slot = None

    def picture(self, q: np.ndarray, qd: np.ndarray | None, flags: np.ndarray | None, t: float = 0.0) -> Picture:
        """A state's positions [m] and velocities [m/s] (every world, world-major; float32 as the page draws
        them) as a :class:`Picture`: the worlds laid out on the export grid, colliders at rest. Layers the page
        hides are left out; ``qd`` is needed only to colour by speed, ``flags`` only to show the pins."""
        model, viewer = self.sim.model, self.viewer
        n = model.particle_count
        picture = Picture(time=t)
        q = np.asarray(q, dtype=np.float32).reshape(model.world_count, n, 3)
        speed_shown = viewer.color_by.value == "speed" and qd is not None
        if speed_shown:
            qd = np.asarray(qd, dtype=np.float32).reshape(model.world_count, n, 3)
        pinned = (flags.reshape(model.world_count, n) & PARTICLE_KINEMATIC) != 0 if flags is not None else None
        for w in range(model.world_count):
            key = f"world_{w:04d}" if model.world_count > 1 else ""
            x = q[w] + self._offsets[w] if model.world_count > 1 else q[w]
            speed = np.linalg.norm(qd[w], axis=1) if speed_shown else None
            surfaces = []
            for g, rows in zip(model.meshes, self._mesh_rows):
                surfaces.append(Surface(g.name, x[rows], g.faces, {"speed": speed[rows]} if speed_shown else {}))
            for skin in model.skins:
                values = {"speed": np.linalg.norm(skin.points(qd[w]), axis=1)} if speed_shown else {}
                surfaces.append(Surface(skin.name, skin.points(x), skin.faces, values))
            picture.surfaces[key] = surfaces
            if viewer.show_particles.value:
                picture.particles[key] = x
            if viewer.show_pins.value and pinned is not None:
                picture.pins[key] = x[pinned[w]]
            if viewer.show_springs.value and self._springs is not None:
                picture.springs[key] = np.stack([x[self._springs[:, 0]], x[self._springs[:, 1]]], axis=1)
            if viewer.show_colliders.value:
                picture.colliders[key] = self._collider_meshes[w if len(self._collider_meshes) > 1 else 0]
        return picture

    def _colliders(self, x: np.ndarray, offset: np.ndarray) -> list:
        import trimesh  # optional: trimesh (primitive meshes of the collider shapes)

        out = []
        for shape in self.sim.model.shapes:
            if shape.kind == "sphere":
                mesh = trimesh.creation.icosphere(subdivisions=3, radius=shape.size[0])
            elif shape.kind == "box":
                mesh = trimesh.creation.box(extents=2.0 * np.asarray(shape.size))
            elif shape.kind == "capsule":
                mesh = trimesh.creation.capsule(height=2.0 * shape.size[1], radius=shape.size[0])
            elif shape.kind == "plane":
                half = shape.size[0] or max(1.0, float(np.ptp(x, axis=0).max()))
                mesh = trimesh.creation.box(extents=(2 * half, 2 * half, 1e-3))
            elif shape.mesh is not None:
                mesh = trimesh.Trimesh(shape.mesh.vertices, shape.mesh.faces, process=False)
            else:
                continue
            rotation = quat_to_matrix(np.asarray(shape.rotation, dtype=np.float64))
            points = np.asarray(mesh.vertices) @ rotation.T + np.asarray(shape.position) + offset
            out.append(Surface(shape.name, points, np.asarray(mesh.faces, dtype=np.int32)))
        return out

    def close(self) -> None:
        """Stop serving (a paused run goes on)."""
        with self._wake:
            if self._closed:
                return
            self._closed = True
            self._wake.notify_all()
        if self.viewer is not None:
            self.viewer.close()
