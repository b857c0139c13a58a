"""Run a scene to a USD file: build, simulate frame by frame, stream frames out, report."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from .. import checks
from ..errors import ConfigError, SimulationError
from ..core.integrators import make_integrator
from ..io.scene import Scene
from ..io.scene_checks import check_run_settings
from ..io.usd import UsdWriter
from ..core.checkpoint import Checkpoint
from ..core.records import STABILIZER_INPUTS
from ..io.output_lock import OutputLock
from ..io.usd_stream import check_output_path
from ..core.mesh_colliders import mesh_cache_counts
from ..core.simulator import Simulator
from ..core.guard_records import describe_suspects, remedy_substeps
from ..core.builder.colliders import model_triangle_contacts
from ..analysis.advisor import advise, diagnose
from ..analysis.step_choice import choose_substeps
from ..analysis.under_load import PROBE_HORIZON
from ..analysis.watch import WATCH_EVERY, WATCH_STOP, StabilityWatch
from ..kernels.inputs import INPUTS
from ..version import __version__


@dataclass
class RunSummary:
    """What a run did.

    Attributes:
        output: the USD file written.
        frames: frames simulated (the file holds frames + 1 samples: the initial state is frame 0).
        simulated_time: simulated seconds [s].
        wall_time: wall time [s] of frames 2..frames (simulation and USD writing).
        setup_time: wall time [s] to build the model, compile the kernels and run the first frame.
        substeps: integrator steps per frame; dt = 1 / (fps · substeps).
        device: the Warp device used.
        model: one-line model description.
        integrator: integrator name.
        advice: the stability advisor's verdict before the run.
        worlds: worlds simulated (``[worlds] count``).
        exported_world: the one world written, or ``None`` (every world).
        world_failures: one line per world the guard stopped (``[guard] stop = "world"``), in world order,
            naming the world, the frame and what failed; the file holds that world's frames before it.
        contact_overflow: contacts dropped in the run because a particle touched more colliders than its
            contact slots, all worlds together (0 without the contact stage).
        peak_contacts: the most particle-collider contacts held at the end of a frame, all worlds together, and
            the buffer's capacity, (count, capacity); None without the contact stage.
        resumed_from: the checkpoint's frame a resumed run went on from (0: a run from the start).
        recycled: per emitter whose pool was too small, the particles recycled before their life span ended
            (all worlds together) and the pool's size: {name: (count, capacity)}.
        self_contact: with self-collision, (pairs pushed apart, vertices capped, pairs dropped for a full pair list,
            pair-steps beyond the cap, pair-steps pressed below τ/2) summed over the run's steps and worlds; ``None``
            without it.
        mesh_cache_overflow: full mesh queries made because a particle's candidate cache overflowed (all worlds;
            the results are the same, the work is not: raise the mesh's ``cache_candidates``).
        choices: what the scene switched on or chose by itself and why, one line each (``substeps = "auto"``,
            triangle contacts by the rule of ``core/builder/colliders.py``).
        balance: what the guard's energy balance counted, left out or why it was off (``BalanceTerms.describe``);
            empty without a guard.
        balance_created: the energy the integration created by the balance's count at the run's end, as a share of
            its budget, E - (E_ref + W - D) over the peak of E_ref + W [-] (the largest over worlds; ``None`` where
            the balance was off or there is no guard): within the guard's tolerance for a run it did not stop.
    """

    output: str
    frames: int
    simulated_time: float
    wall_time: float
    setup_time: float
    substeps: int
    dt: float
    device: str
    model: str
    integrator: str
    advice: str
    worlds: int = 1
    exported_world: int | None = None
    world_failures: list = field(default_factory=list)
    contact_overflow: int = 0
    resumed_from: int = 0
    recycled: dict = field(default_factory=dict)
    peak_contacts: tuple | None = None
    self_contact: tuple | None = None
    mesh_cache_overflow: int = 0
    choices: tuple = ()
    balance: str = ""
    balance_created: float | None = None

    def line(self) -> str:
        """The closing summary line of the CLI."""
        timed = self.frames - self.resumed_from - 1
        if timed > 0 and self.wall_time > 0:
            rate = timed / self.wall_time
            speed = f"{rate:.1f} frames/s, {rate * self.substeps:.0f} substeps/s"
        else:  # one frame: all of it is setup, there is no rate to report
            speed = "no timed frames"
        worlds = ""
        if self.worlds > 1:  # the model's description counts the worlds
            written = "every world" if self.exported_world is None else f"world {self.exported_world}"
            worlds = f"; {written} written"
            if self.world_failures:
                stopped = len(self.world_failures)
                worlds += f"; {stopped} world{'s' if stopped > 1 else ''} stopped by the guard"
        if self.contact_overflow:
            worlds += (f"; {self.contact_overflow} contacts dropped for want of contact slots (raise "
                       "[contacts] slots)")
        for name, (count, capacity) in self.recycled.items():
            worlds += (f"; emitter {name!r}: {count} particles recycled before their life span ended (its pool of "
                       f"{capacity} is too small: raise capacity)")
        if self.mesh_cache_overflow:
            worlds += (f"; {self.mesh_cache_overflow} full mesh queries for overflowing candidate caches (raise "
                       "the mesh's cache_candidates)")
        if self.self_contact is not None:
            pushed, capped, dropped, outrun, squeezed = self.self_contact
            worlds += f"; self-collision: {pushed} pairs pushed apart, {capped} vertex steps capped"
            if dropped:
                worlds += f", {dropped} pairs dropped for a full pair list (their worlds held their free vertices)"
            if outrun:
                worlds += (f", {outrun} pair-steps beyond the cap where pins closed in faster than the cloth could give "
                           "way, or on other pins (the surface may cross there: substeps = \"auto\" keeps pins within "
                           "a quarter of the cap's reach a step; pins driven into pins cross by their own motion)")
            if squeezed:
                worlds += (f", {squeezed} pair-steps pressed below τ/2 (pins pressing layers held by other pins: no "
                           "room to give way; not crossed)")
        resumed = f", frames {self.resumed_from + 1}..{self.frames} after resuming" if self.resumed_from else ""
        contacts = ""
        if self.peak_contacts is not None:
            count, capacity = self.peak_contacts
            contacts = f"; at most {count} of {capacity} contact slots held at a frame's end"
        return (
            f"wrote {self.frames + 1} frames{resumed} ({self.simulated_time:.3g} s simulated) to {self.output} in "
            f"{self.wall_time:.2f} s + {self.setup_time:.2f} s setup: {speed}; {self.integrator}, "
            f"dt = {self.dt * 1e3:.4g} ms; {self.model}{contacts}{worlds}"
        ) + "".join(f"; {choice}" for choice in self.choices) + (f"; {self.balance}" if self.balance else "")


def checkpoint_path(output: str) -> str:
    """Where ``run_scene(checkpoint_every=...)`` saves the checkpoints of a run writing ``output``: beside it,
    ``out.usdc`` → ``out.checkpoint.npz``."""
    return os.path.splitext(output)[0] + ".checkpoint.npz"


def scene_output_path(scene: Scene) -> str | None:
    """The output a scene names itself (``[output] path``), as a path to write, or ``None`` when it names none.

    A scene file may come from anyone, so its output stays home: a relative path is taken in the scene file's
    folder (not the working directory), and a path that leaves that folder is refused: an absolute path
    elsewhere, a ``..`` that climbs out, a symbolic link (a folder or the file) that leads out. Only the
    command line (``-o``) writes elsewhere.

    Raises:
        ConfigError: the path leaves the scene's folder (one line naming the scene, the path and the remedy).
    """
    path = scene.output
    if not path:
        return None
    path = os.fspath(path)
    scene_file = getattr(scene, "path", None)
    home = os.path.dirname(os.path.abspath(scene_file)) if scene_file and os.path.isfile(scene_file) else os.getcwd()
    where = f"{os.path.basename(scene_file) if scene_file else 'the scene'}: [output] path = {path!r}"
    remedy = "a scene writes only inside its own folder; pass -o to write elsewhere"
    real_home = os.path.realpath(home)
    joined = os.path.join(home, path)  # an absolute path stays as it is; realpath follows links as the OS will
    def inside(where_to: str) -> bool:
        return os.path.commonpath([real_home, os.path.realpath(where_to)]) == real_home

    if not inside(joined):
        if os.path.isabs(path) and not inside(os.path.dirname(path)):
            how = "is an absolute path outside"
        elif os.pardir in path.replace("\\", "/").split("/"):
            how = "climbs out of"
        else:
            how = "leads (through a symbolic link) out of"
        raise ConfigError(f"{where} {how} the scene's folder {home}: {remedy}")
    return os.path.join(os.path.realpath(os.path.dirname(joined)), os.path.basename(joined))


def run_scene(
    scene: Scene,
    *,
    output: str | None = None,
    device: str | None = None,
    frames: int | None = None,
    fps: float | None = None,
    substeps: int | str | None = None,
    progress: bool = True,
    strict: bool = False,
    warn=None,
    world: int | None = None,
    world_spacing: float | None = None,
    world_columns: int | None = None,
    watch: int | None = None,
    checkpoint_every: int = 0,
    resume: str | None = None,
    on_start=None,
    note=None,
) -> RunSummary:
    """Simulate ``scene`` and write it to USD. Arguments other than ``scene`` override the file's values
    (``world``, ``world_spacing`` and ``world_columns`` those of its ``[output]``: see
    :class:`~warpspring.io.usd.UsdWriter`).

    Before the run the stability advisor checks the step (:func:`preflight`): with ``strict`` an unstable
    step is refused, otherwise its message goes to ``warn`` (a callable taking one string), if given.
    During the run it re-checks the step at the state reached every ``watch`` frames (default
    ``WATCH_EVERY``; 0 off: :class:`~warpspring.analysis.watch.StabilityWatch`), its warnings to ``warn``; a
    state past ``WATCH_STOP`` times its step's stable limit stops the run (the guard's balance may be off or
    one-sided, and a position correction may hold the growth below the tear limit).

    Every ``checkpoint_every`` frames (0: never) the whole simulation is saved to
    :func:`checkpoint_path` of the output (atomically replaced); ``resume`` continues a stopped run from such
    a checkpoint: the output's frames up to the checkpoint's are kept and the run goes on from there to
    ``frames``, bit for bit as the uninterrupted run on the same device.

    ``output`` (the command line's ``-o``) is used as given. Without it the scene's ``[output] path`` is used,
    which must stay in the scene file's folder (:func:`scene_output_path`). The run owns its output from
    before the model is built until the file is packed (:class:`~warpspring.io.output_lock.OutputLock`): a run
    on an output another run is writing is refused at once.

    With ``[guard] stop = "world"`` a world that fails a guard check is held and the others go on: the
    world gets no samples from the failing frame on, its failure goes to ``warn`` at once and is listed in
    :attr:`RunSummary.world_failures`. The run fails only when every world has failed.

    ``on_start(sim, advice)``, if given, is called once the simulator is made and the advisor has judged
    the step, before the first frame (the live viewer attaches itself there).

    ``substeps = "auto"`` (the scene's default: :func:`~warpspring.analysis.step_choice.choose_substeps`) is chosen
    once the model is built, before the run; what the run chose by itself (the substeps, triangle contacts)
    goes to ``note`` (a callable taking one string), if given, and into :attr:`RunSummary.choices`.

    Raises:
        ConfigError: bad scene or options, a scene's output path that leaves its folder, an output another run
            is writing (naming its process), or (``strict``) an unstable step; nothing is written.
        SimulationError: the state became non-finite (in every world, with ``stop = "world"``); the file
            holds every frame before that one.
    """
    frames = scene.frames if frames is None else frames
    fps = scene.fps if fps is None else fps
    substeps = scene.substeps if substeps is None else substeps
    check_run_settings(fps=fps, frames=frames, substeps=substeps)
    output = output or scene_output_path(scene)
    if not output:
        raise ConfigError("no output file: pass -o out.usdc or set [output] path in the scene")
    output = check_output_path(output)  # fail before the model is built and the kernels compiled
    lock = OutputLock(output)  # this run owns the output: another run writing it is refused now, not later
    try:
        return _run(scene, output=output, lock=lock, device=device, frames=frames, fps=fps, substeps=substeps,
                    progress=progress, strict=strict, warn=warn, world=world, world_spacing=world_spacing,
                    world_columns=world_columns, watch=watch, checkpoint_every=checkpoint_every, resume=resume,
                    on_start=on_start, note=note)
    finally:
        lock.release()


def _run(scene: Scene, *, output: str, lock: OutputLock, device, frames: int, fps: float, substeps, progress,
         strict, warn, world, world_spacing, world_columns, watch, checkpoint_every, resume, on_start,
         note=None) -> RunSummary:
    """:func:`run_scene` once its output is checked and owned (``lock`` held)."""
    world = scene.export_world if world is None else world
    if world is not None and world >= scene.world_count:
        raise ConfigError(f"cannot write world {world}: the scene has {scene.world_count} world(s), "
                          f"0..{scene.world_count - 1}")
    export = dict(
        world=world,
        world_spacing=scene.world_spacing if world_spacing is None else world_spacing,
        world_columns=scene.world_columns if world_columns is None else world_columns,
    )

    t0 = time.perf_counter()
    dev = checks.device(device or scene.device)
    model = scene.finalize(dev)
    try:
        integrator = make_integrator(scene.integrator, model, **scene.integrator_options)
    except ConfigError as exc:
        raise ConfigError(f"{os.path.basename(scene.path)}: [simulation] {exc}") from None
    watch = WATCH_EVERY if watch is None else checks.count("watch", watch, minimum=0)
    checkpoint_every = checks.count("checkpoint_every", checkpoint_every, minimum=0)
    control, choices, chosen = model.control(), [], None
    if substeps == "auto":
        chosen = choose_substeps(model, integrator, fps=fps, control=control, horizon=frames / fps)
        substeps = chosen.substeps
        choices.append(f"substeps auto: {chosen.reason}")
    if scene.contact_triangles is None:  # switched on by the rule, not by the scene's key
        rule = model_triangle_contacts(model)
        if rule.needed:
            choices.append(rule.reason + " ([contacts] triangles = false switches them off)")
    for line in choices:
        if note is not None:
            note(line)
    sim = Simulator(model, integrator=integrator, fps=fps, substeps=substeps, control=control, guard=scene.guard)
    start = 0
    if resume is not None:
        _check_resume(Checkpoint.load(resume), sim, warn)
        scene_inputs = model.inputs.numpy().copy()  # the scene's live inputs: they may differ from the saved run's
        sim.load_checkpoint(resume)
        _keep_scene_inputs(model, scene_inputs)
        start = sim.frame
        if start >= frames:
            raise ConfigError(f"the checkpoint {resume!r} is at frame {start}, at or past the run's end (frame "
                              f"{frames}): nothing to resume; pass more --frames")
    if chosen is not None and chosen.advice is not None and chosen.advice.dt == sim.dt:
        advice = chosen.advice  # the verdict at the chosen step, made just now
    else:
        advice = preflight(model, integrator.name, sim.dt, fps=fps, strict=strict, control=sim.control,
                           horizon=frames / fps, note=note)
    if model.self_contact is not None:
        model.self_contact.reset()  # the advisor's dry run stepped the model: count the run's steps only
    # Its limits from the verdict just made, not a second analysis.
    stability_watch = StabilityWatch.attach(sim, every=watch, advice=advice, stop=WATCH_STOP) if watch else None
    last_good = model.state()  # the last frame the guard passed: where a stop is diagnosed
    if not advice.stable and warn is not None:
        warn(advice.message)
    if on_start is not None:
        on_start(sim, advice)

    saved_at = os.path.abspath(checkpoint_path(output))
    with UsdWriter(output, model, fps=fps, particles=scene.export_particles, springs=scene.export_springs,
                   keep_frames=start + 1 if resume is not None else 0, lock=lock, **scene.export_options,
                   **export) as usd:
        if resume is None:
            usd.write_frame(sim.state)
        failures = sorted(sim.world_failures)
        if failures:
            usd.stop_worlds(failures)  # worlds the guard held before the checkpoint get no new samples
        bar = _progress(frames, enabled=progress, initial=start)
        if stability_watch is not None and warn is not None:
            def notify(message: str) -> None:
                with bar.external_write_mode():  # a line of its own, not through the progress bar
                    warn(message)

            stability_watch.notify = notify
        t1 = None
        peak_contacts = 0
        try:
            for _ in range(start, frames):
                sim.step_frame()
                if sim.contacts is not None:  # the contact stage: how full its buffer gets
                    peak_contacts = max(peak_contacts, int(sim.contacts.counts().sum()))
                for w in sorted(set(sim.world_failures) - set(failures)):  # stopped by the guard this frame
                    failures.append(w)
                    usd.stop_worlds(w)  # its last sample stays the frame before the failure
                    if warn is not None:
                        with bar.external_write_mode():  # a line of its own, not through the progress bar
                            warn(sim.describe_failure(w))
                usd.write_frame(sim.state)
                if checkpoint_every and sim.frame % checkpoint_every == 0:
                    sim.save_checkpoint(saved_at)
                if sim.guard is not None:
                    wp.copy(last_good.particle_q, sim.state.particle_q)
                bar.update(1)
                if t1 is None:  # the first frame compiled the kernels and captured the graph: setup time
                    t1 = time.perf_counter()
            if stability_watch is not None:
                stability_watch.collect()  # the last frame's re-check, where it is read a frame later (CUDA)
        except SimulationError as exc:
            # A guard names its frame and substep; the writer's last-line check knows only the frame.
            frame = exc.frame if exc.frame is not None else sim.frame
            where = "" if exc.frame is not None else f"frame {frame} (t = {frame * sim.frame_dt:.4g} s): "
            remedy = _remedy(advice, substeps, model, sim.control, integrator.name, sim.dt)
            reason = getattr(exc, "reason", None)
            if reason is not None:
                remedy = diagnose(model, integrator.name, sim.dt, fps=fps, reason=reason, state=last_good,
                                  control=sim.control, omega_estimate=_omega_estimate(model),
                                  substeps_floor=advice.substeps or 0).remedy
            resumable = ""
            if checkpoint_every and os.path.exists(saved_at):
                resumable = f"; continue from the last checkpoint with --resume {checkpoint_path(output)}"
            raise SimulationError(
                f"{where}{exc} (dt = {sim.dt * 1e3:.4g} ms). {remedy[0].upper()}{remedy[1:]}; "
                f"{output} holds frames 0..{frame - 1}{resumable}",
                frame=frame,
                substep=exc.substep,
            ) from None
        finally:
            bar.close()
        wall = time.perf_counter() - t1
    return RunSummary(
        output=output,
        frames=frames,
        simulated_time=frames / fps,
        wall_time=wall,
        setup_time=t1 - t0,
        substeps=substeps,
        dt=sim.dt,
        device=str(dev),
        model=model.describe(),
        integrator=integrator.name,
        advice=advice.message,
        worlds=model.world_count,
        exported_world=world,
        world_failures=[sim.describe_failure(w) for w in sorted(failures)],
        contact_overflow=int(sim.contact_overflow().sum()),
        resumed_from=start,
        recycled={e.name: (int(e.recycled().sum()), e.capacity) for e in model.emitters if e.recycled().any()},
        peak_contacts=None if sim.contacts is None else (peak_contacts, sim.contacts.capacity),
        self_contact=None if model.self_contact is None else tuple(
            int(v.sum()) for v in model.self_contact.counts().values()),  # pairs, capped, overflow, outrun, squeezed
        mesh_cache_overflow=int(mesh_cache_counts(model)["overflow"].sum()) if model.mesh_colliders else 0,
        choices=tuple(choices),
        balance=sim.guard.balance_terms().describe() if sim.guard is not None else "",
        balance_created=_created_share(sim),
    )


def _created_share(sim) -> float | None:
    """``RunSummary.balance_created`` of ``sim`` (reads the device)."""
    if sim.guard is None or not sim.guard.balance_terms().on:
        return None
    balance = sim.guard.energy_balance()
    return float(np.max(balance.created / np.maximum(balance.peak, 1.0e-300)))


def _check_resume(checkpoint: Checkpoint, sim: Simulator, warn) -> None:
    """Refuse to resume from ``checkpoint`` into ``sim`` (built from the scene, not yet restored) when the model
    differs in any key of its fingerprint (the message names the keys); the end time, the output and the live
    inputs may differ. A checkpoint from another warpspring version is resumed with a warning."""
    name = f"checkpoint {checkpoint.source}"
    checkpoint.check_configuration(sim)  # counts, integrator, fps, substeps: named with their fix
    differences = checkpoint.model_differences(sim)
    if differences:
        shown = "; ".join(differences[:4]) + (f"; and {len(differences) - 4} more" if len(differences) > 4 else "")
        raise ConfigError(f"{name} was saved from another model than this scene builds: {shown}; "
                          "resume with the scene (and options) it was saved from, or start the run over "
                          "(the end time, the output and live inputs such as gravity and drag may change)")
    saved = checkpoint.header.get("warpspring_version")
    if saved != __version__ and warn is not None:
        warn(f"{name} was saved by warpspring {saved}, this is {__version__}: the resumed run may "
             "not continue the saved one bit for bit")
    if "model" not in checkpoint.header and warn is not None:
        warn(f"{name} predates checkpoints that record their model: it cannot be checked against "
             "this scene")


def _keep_scene_inputs(model, scene_inputs) -> None:
    """After a checkpoint restored the saved run's live inputs, write back those the scene gives other values
    (gravity, drag, stabiliser limits, wind: a resumed run may change them, as between frames), except those a
    keyframe track animates (the track sets them at every step) and the limits of a stabiliser that is off."""
    saved = model.inputs.numpy()
    for name, (slot, width) in INPUTS.items():
        columns = slice(slot, slot + width)
        if np.array_equal(saved[:, columns], scene_inputs[:, columns]):
            continue
        if any(model.track(name, world=w) is not None for w in range(model.world_count)):
            continue
        if name in STABILIZER_INPUTS and not model.stabilizers.enabled(name):
            continue
        values = scene_inputs[:, columns].astype(np.float64)
        model.set_world_values(name, values if width == 3 else values[:, 0])


def preflight(model, integrator: str, dt: float, *, fps: float, strict: bool = False, control=None,
              horizon: float | None = None, note=None):
    """The stability advisor's verdict on a run (:func:`warpspring.analysis.advisor.advise`): ω_max at the
    static equilibrium under the run's loads (gravity, ``control``'s external force) when any act, and at
    its peak over a dry run of the scene up to ``horizon`` [s] (the run's duration; default
    ``PROBE_HORIZON``) when the model moves by itself.

    Biphasic springs are judged by their stiffer branch. ω_max comes from power iteration on GPUs and
    on CPUs for models up to ``POWER_ITERATION_CPU_LIMIT`` particles, else from the (conservative, also
    under load) Gershgorin bound. The static equilibrium is up to ``RELAX_MAX_STEPS`` implicit steps: a
    stiff cloth settles in a few, a soft one hung from two corners does not (a denim cloth at 32², 200
    steps and 20 s on a 2-core CPU; at 64² 79 s), which is most of the check's time on a CPU. With ``strict``, a
    step past the one the theory passes but within ``TRIAL_CEILING`` × the linear limit is decided by two trial runs of
    the scene over ``horizon`` (``advise``'s ``trial``), announced to ``note`` (a callable taking one string), if given.

    Raises:
        ConfigError: with ``strict``, when ``dt`` is outside the integrator's stability limit.
    """
    return advise(model, integrator, dt, fps=fps, strict=strict, control=control,
                  horizon=PROBE_HORIZON if horizon is None else horizon, omega_estimate=_omega_estimate(model),
                  notify=note)


def _omega_estimate(model) -> str:
    """How the runner's advisor finds ω_max: power iteration, but Gershgorin for a large model on a CPU."""
    cheap = not model.device.is_cuda and model.particle_count > POWER_ITERATION_CPU_LIMIT
    return "gershgorin" if cheap else "power_iteration"


#: Largest model (particles) whose pre-run ω_max is found by power iteration on a CPU.
POWER_ITERATION_CPU_LIMIT = 20_000


def _remedy(advice, substeps: int, model, control, integrator: str, dt: float) -> str:
    """What to change after a run went bad: the advisor's verdict; or, where it saw no spring instability, what else
    the scene holds (its contacts and loads, as the guard names them: ``describe_suspects``) and the substeps the
    guard's bound asks for (``remedy_substeps``): never implicit_euler, whose balance is off (a remedy that only
    silences the guard)."""
    if advice.stable:
        more = remedy_substeps(model, integrator=integrator, substeps=substeps, dt=dt)
        return (f"the advisor found the step stable for the springs ({advice.message}); the scene's other suspects: "
                f"{describe_suspects(model, control=control)}; run with more substeps (e.g. --substeps {more})")
    hint = f" (e.g. --substeps {advice.substeps})" if advice.substeps else ""
    return f"{advice.message}{hint}"


#: Seconds of wall time between the progress lines of a run whose stderr is not a terminal (a log file, CI).
PROGRESS_EVERY = 5.0


def _progress(total: int, *, enabled: bool, initial: int = 0):
    """The run's progress on stderr: a tqdm bar on a terminal; elsewhere (a pipe, a log file) a line every
    :data:`PROGRESS_EVERY` seconds (:class:`ProgressLines`), so a long run shows that it is alive."""
    import sys

    if enabled and sys.stderr.isatty():
        from tqdm import tqdm

        return tqdm(total=total, initial=initial, unit="frame", dynamic_ncols=True, leave=False)
    return ProgressLines(total, initial=initial, enabled=enabled)


class ProgressLines:
    """Progress as plain lines, for output that is not a terminal: every :data:`PROGRESS_EVERY` seconds of wall
    time, ``frame 120 of 600 (20 %), 35.2 frames/s, 14 s left``. The rate is taken over the frames since the
    first one (which compiles the kernels and captures the graph), so the time left is the run's steady pace.
    The interface is the part of tqdm's that the runner uses (``update``, ``external_write_mode``, ``close``).

    Args:
        total: the run's last frame.
        initial: the frame it starts from (a resumed run's checkpoint).
        enabled: ``False`` prints nothing.
        clock: wall-clock seconds (``time.perf_counter``; a test passes its own).
    """

    def __init__(self, total: int, *, initial: int = 0, enabled: bool = True, clock=time.perf_counter):
        self.total, self.frame, self.enabled, self.clock = total, initial, enabled, clock
        self._base = None  # (frame, time) after the first frame: where the rate is measured from
        self._last = clock()

    def update(self, frames: int = 1) -> None:
        """Count ``frames`` more frames done; print a line when the interval has passed since the last one."""
        import sys

        self.frame += frames
        now = self.clock()
        if self._base is None:
            self._base = (self.frame, now)
        if not self.enabled or now - self._last < PROGRESS_EVERY or self.frame <= self._base[0]:
            return
        self._last = now
        rate = (self.frame - self._base[0]) / max(now - self._base[1], 1e-9)
        left = (self.total - self.frame) / rate
        share = 100.0 * self.frame / max(self.total, 1)
        print(f"frame {self.frame} of {self.total} ({share:.0f} %), {rate:.3g} frames/s, {left:.0f} s left",
              file=sys.stderr, flush=True)

    def external_write_mode(self):
        """Another line may be written at any time: lines do not share the terminal with a bar."""
        import contextlib

        return contextlib.nullcontext()

    def close(self) -> None:
        """Nothing to clear: every line printed stays."""
