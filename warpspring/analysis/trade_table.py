"""The measured trade table that ``substeps = "auto"`` reads (:mod:`warpspring.analysis.step_choice`).

It ships with the package as ``trade_table.json`` beside this module, so that an installed warpspring reads it, and
is written from a study's files by ``python bench/trade.py --table CSV...`` (:func:`write_table`). It holds, in a
few kilobytes:

* **sources**: each study it was built from: its file, command, device (alias and name), Warp version and date
  (read from the study's Markdown report beside its CSV);
* **the accuracy floor** [m over a frame] that implicit Euler and dopri5 meet on auto, and the rows it comes from:
  on the hanging cloth (problem ``cloth``), the float64 errors of the two explicit integrators the advisor
  recommends, symplectic Euler and velocity Verlet, at the coarsest step each ran stably; the floor is their
  geometric mean, the middle of that band on a log scale. The rows' errors are over the cloth's 1 s run while
  the floor bounds what one frame adds (step doubling): implicit Euler on auto is asked to err, per frame, no
  more than the explicit integrators on their largest steps err over the whole run;
* **the contact problems** measured: per problem and contact option, the signature of the model it was
  measured on (:func:`signature`: what a scene must match for the rows to apply) and every row that ran clean
  (status ok, no crossing), grouped by integrator, precision and tolerance: substeps per frame at the study's frame
  rate (an adaptive integrator's: its output interval) and error (``error_max``, the larger of the trajectory error over the
  horizon and the Hausdorff distance at the end [m], to 4 digits).
"""

from __future__ import annotations

import functools
import json
import math
import os
import pathlib
import re
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..core.model import Model
from ..errors import ConfigError
from .trade_contact import FPS, study_plan
from .trade_report import read_csv

#: The table the package ships (written by ``python bench/trade.py --table``).
TABLE_PATH = pathlib.Path(__file__).with_name("trade_table.json")
#: The file format's version.
FORMAT = 1
#: The floor's problem and integrators (module docstring).
FLOOR_PROBLEM = "cloth"
FLOOR_INTEGRATORS = ("symplectic_euler", "velocity_verlet")
#: Signature values agree within this relative tolerance (float32 and float64 builds of one scene).
SIGNATURE_RTOL = 1e-5


@dataclass(frozen=True)
class TableRow:
    """One measured configuration the table keeps.

    Attributes:
        problem: the study's problem; option: its contact option's label (``None`` off contact scenes).
        integrator, precision: as measured; tolerance: an adaptive integrator's, else ``None``.
        dt: the step [s] (adaptive: the output interval); error: its ``error_max`` [m].
        source: the index of its study in :attr:`TradeTable.sources`.
    """

    problem: str
    option: str | None
    integrator: str
    precision: str
    tolerance: float | None
    dt: float
    error: float
    source: int

    def substeps(self, fps: float) -> int:
        """Substeps per 1/``fps`` frame that take at most this row's step."""
        return max(1, math.ceil(1.0 / (fps * self.dt) - 1e-9))

    def describe(self) -> str:
        """E.g. "drape, particle contacts: symplectic_euler, float32, dt = 0.8333 ms, error 2.5e-03 m"."""
        setting = f"dt = {self.dt * 1e3:.4g} ms" if self.tolerance is None else f"tolerance {self.tolerance:g}"
        where = self.problem if self.option is None else f"{self.problem}, {self.option}"
        return f"{where}: {self.integrator}, {self.precision}, {setting}, error {self.error:.2e} m"


@dataclass(frozen=True)
class TradeTable:
    """The table read back (:func:`load_table`).

    Attributes:
        floor: the accuracy floor [m over a frame]; floor_rows: the rows it comes from.
        problems: per (problem, option): ``(signature, rows)``.
        sources: the studies' provenance (dicts: file, command, device, device_name, warp, date).
        path: the file it was read from.
    """

    floor: float
    floor_rows: tuple[TableRow, ...]
    problems: dict
    sources: tuple[dict, ...]
    path: str = ""

    def provenance(self, row: TableRow) -> str:
        """Where ``row`` was measured: "cpu (AMD EPYC ...), Warp 1.19.0, 2026-11-27"."""
        s = self.sources[row.source]
        return f"{s['device']} ({s['device_name']}), Warp {s['warp']}, {s['date']}"

    def floor_reason(self) -> str:
        """One line: the floor and the rows it comes from."""
        rows = " and ".join(f"{r.integrator} {r.error:.3g} m at dt = {r.dt * 1e3:.4g} ms" for r in self.floor_rows)
        return (f"the accuracy floor of {self.floor:.3g} m, the geometric mean of {rows} on the trade table's "
                f"{FLOOR_PROBLEM} ({self.provenance(self.floor_rows[0])})")

    def match(self, model: Model) -> tuple[str, str] | None:
        """The (problem, option) whose model ``model`` is (:func:`signature`), or ``None``."""
        mine = signature(model)
        for key, (theirs, _) in self.problems.items():
            if signatures_match(mine, theirs):
                return key
        return None


# -- reading ------------------------------------------------------------------------------------------------


def load_table(path: str | os.PathLike | None = None) -> TradeTable:
    """The table at ``path`` (default: the package's, :data:`TABLE_PATH`).

    Raises:
        ConfigError: a missing or malformed file.
    """
    return _load(str(TABLE_PATH if path is None else path))


@functools.cache
def _load(path: str) -> TradeTable:
    if not os.path.isfile(path):
        raise ConfigError(f"trade table not found: {path} (write it with 'python bench/trade.py --table ...')")
    try:
        with open(path) as f:
            data = json.load(f)
        if data.get("format") != FORMAT:
            raise ValueError(f"format {data.get('format')!r}, expected {FORMAT}")
        floor_rows = tuple(_row(r) for r in data["floor"]["rows"])
        problems = {}
        for entry in data["problems"]:
            fps = float(entry["fps"])
            rows = tuple(TableRow(entry["problem"], entry["option"], group["integrator"], group["precision"],
                                  group["tolerance"], 1.0 / (fps * substeps), error, entry["source"])
                         for group in entry["runs"] for substeps, error in group["rows"])
            problems[(entry["problem"], entry["option"])] = (entry["signature"], rows)
        return TradeTable(float(data["floor"]["value"]), floor_rows, problems, tuple(data["sources"]), path)
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"{path} is not a warpspring trade table ({exc})") from None


def _row(d: dict) -> TableRow:
    return TableRow(d["problem"], d.get("option"), d["integrator"], d["precision"], d.get("tolerance"), d["dt"],
                    d["error"], d["source"])


# -- signatures ---------------------------------------------------------------------------------------------


def signature(model: Model) -> dict:
    """What a scene must share with a measured problem for its rows to apply: counts (worlds, particles, springs,
    triangles, hinges, families' elements), the colliders (kinds, frames, sizes, friction, a mesh's points and
    inside test), the contact options (slots, triangle contacts, self-collision thickness, strain limit), and sums
    and sums of squares of the start positions, masses, spring stiffness, damping and rest lengths, contact radii,
    gravity and drag (every world). JSON-ready."""
    def moments(values) -> list[float]:
        a = np.asarray(values, dtype=np.float64).ravel()
        return [float(a.sum()), float((a * a).sum())]

    shapes = []
    for s in model.shapes:
        mesh = getattr(s, "mesh", None)
        values = [*s.position, *s.rotation, *s.size, s.friction, s.restitution, s.thickness]
        if mesh is not None:
            values += moments(mesh.vertices)
        shapes.append({"kind": s.kind, "values": [float(v) for v in values],
                       "winding_number": bool(getattr(mesh, "winding_number", False))})
    values = {
        "q": moments(model.particle_q.numpy()),
        "mass": moments(model.world_values("particle_mass")),
        "radius": moments(model.particle_radius.numpy()),
        "gravity": moments(model.world_values("gravity")),
        "drag": moments(model.world_values("drag")),
    }
    if model.spring_count:
        values.update(stiffness=moments(model.world_values("spring_stiffness")),
                      damping=moments(model.world_values("spring_damping")), rest=moments(model.spring_rest_lengths()))
    strain = model.stabilizers.max_strain
    return {
        "worlds": model.world_count, "particles": model.particle_count, "springs": model.spring_count,
        "triangles": model.tri_count, "hinges": model.hinge_count,
        "families": sorted([f.name, int(f.element_count)] for f in model.extra_families),
        "shapes": shapes, "contact_slots": int(model.contact_slots), "contact_triangles": bool(model.contact_triangles),
        "self_thickness": None if model.self_contact is None else model.self_contact.thickness,
        "max_strain": None if strain is None else float(strain),
        "values": values,
    }


def signatures_match(a, b) -> bool:
    """Whether two signatures agree: everything but floats exactly, floats within :data:`SIGNATURE_RTOL`."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(signatures_match(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(signatures_match(x, y) for x, y in zip(a, b))
    if isinstance(a, float) or isinstance(b, float):
        if isinstance(a, bool) or isinstance(b, bool) or a is None or b is None:
            return False
        return math.isclose(float(a), float(b), rel_tol=SIGNATURE_RTOL, abs_tol=1e-9)
    return a == b


# -- writing ------------------------------------------------------------------------------------------------

_DEVICE_LINE = re.compile(r"^Device: (\S+) \((.*)\); Warp ([^;]+); (\d{4}-\d{2}-\d{2});")


def read_provenance(csv_path: str) -> dict:
    """The provenance of the study whose CSV is ``csv_path``, from its Markdown report beside it (the same name
    ending ``.md``): its command (empty where the report names none), device, device name, Warp version, date.

    Raises:
        ConfigError: no report, or one without its device line.
    """
    report = os.path.splitext(csv_path)[0] + ".md"
    if not os.path.isfile(report):
        raise ConfigError(f"{csv_path}: its report {report} is missing (the table needs the study's provenance)")
    command, found = "", None
    with open(report) as f:
        for line in f:
            if line.startswith("Command: `"):
                command = line.strip()[len("Command: `"):-1]
            found = found or _DEVICE_LINE.match(line)
            if found:
                break
    if found is None:
        raise ConfigError(f"{report}: no 'Device: ...; Warp ...; date;' line")
    device, name, warp_version, date = found.groups()
    return dict(file=csv_path, command=command, device=device, device_name=name, warp=warp_version, date=date)


def table_from_studies(csv_paths) -> dict:
    """The table (a JSON-ready dict) of the studies ``csv_paths`` (``trade.csv`` files, each with its report beside
    it); a later study's rows of a problem replace an earlier one's. The contact problems' models are rebuilt on the
    CPU (full or quick plan, as the study's command says) for their signatures.

    Raises:
        ConfigError: no floor rows (the studies lack the hanging cloth or its stable float64 runs), or a contact
            study whose report names no command.
    """
    sources, by_problem = [], {}
    for path in csv_paths:
        sources.append(read_provenance(str(path)))
        rows = [r for r in read_csv(str(path)) if r.status == "ok" and r.error_max is not None and not r.crossings]
        for problem in dict.fromkeys(r.problem for r in read_csv(str(path))):
            by_problem[problem] = (len(sources) - 1, [r for r in rows if r.problem == problem])
    if FLOOR_PROBLEM not in by_problem:
        raise ConfigError(f"the studies hold no '{FLOOR_PROBLEM}' problem: the floor comes from it")
    source, rows = by_problem.pop(FLOOR_PROBLEM)
    floor_rows = []
    for name in FLOOR_INTEGRATORS:
        stable = [r for r in rows if r.integrator == name and r.precision == "float64" and r.tolerance is None]
        if not stable:
            raise ConfigError(f"the '{FLOOR_PROBLEM}' study has no stable float64 {name} row for the floor")
        coarsest = max(stable, key=lambda r: r.dt)
        floor_rows.append(dict(problem=FLOOR_PROBLEM, option=None, integrator=name, precision="float64",
                               tolerance=None, dt=coarsest.dt, error=coarsest.error_max, source=source))
    floor = float(np.exp(np.mean(np.log([r["error"] for r in floor_rows]))))
    problems = []
    for problem, (source, rows) in by_problem.items():
        contact = [r for r in rows if r.option is not None]
        if not contact:
            continue
        command = sources[source]["command"]
        if not command:
            raise ConfigError(f"{sources[source]['file']}: its report names no command: the plan of its contact "
                              "problems is unknown")
        words = command.split()
        plan = study_plan([problem], quick="--quick" in words, reduced="--reduced" in words)
        spec = plan.problems[0]
        for option in dict.fromkeys(r.option for r in contact):
            model = spec.build(wp.get_device("cpu"), "float64", spec.scene.option(option))
            mine = [r for r in contact if r.option == option]
            runs = [dict(integrator=i, precision=p, tolerance=t,
                         rows=[[round(1.0 / (FPS * r.dt)), _short(r.error_max, 4)] for r in mine
                               if (r.integrator, r.precision, r.tolerance) == (i, p, t)])
                    for i, p, t in dict.fromkeys((r.integrator, r.precision, r.tolerance) for r in mine)]
            problems.append(dict(problem=problem, option=option, source=source, fps=FPS, signature=signature(model),
                                 runs=runs))
    return dict(format=FORMAT, sources=sources,
                floor=dict(value=floor, unit="m over a frame", rule=f"geometric mean of {', '.join(FLOOR_INTEGRATORS)} "
                           f"at their coarsest stable float64 step on '{FLOOR_PROBLEM}'", rows=floor_rows),
                problems=problems)


def _short(value: float, digits: int) -> float:
    """``value`` to ``digits`` significant digits."""
    return float(f"{value:.{digits}g}")


def write_table(csv_paths, path: str | os.PathLike = TABLE_PATH) -> str:
    """Write :func:`table_from_studies` of ``csv_paths`` to ``path`` (default: the package's table)."""
    table = table_from_studies(csv_paths)
    with open(path, "w") as f:
        json.dump(table, f, separators=(",", ":"))
        f.write("\n")
    _load.cache_clear()
    return str(path)
