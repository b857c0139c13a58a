"""Where the bytes go: memory traffic of the fused gather step per particle-substep, from its data layout.

The fused symplectic Euler kernel (``kernels/integrators.symplectic_euler_kernel`` over the spring family's
gather, ``kernels/springs.py``) runs one thread per particle of every world. For the ANCHORS cloth
(gravity, no drag, no external force, no contacts) a thread at particle i of world w loads

- its own position and velocity (``particle_q_in``, ``particle_qd_in``) and its flag,
- its mass (gravity) and inverse mass, from row min(w, rows - 1),
- for each of the ``head_slots`` slots k of the incidence head: the spring s = ``head_element[k, i]`` and
  the other particle j = ``head_local[k, i]``; then x_j, v_j, and the spring's rest length, stiffness and
  damping (padding slots point at the particle itself and spring 0),
- the CSR tail's entries the same way, if the table has a tail;
- or, with spring data per group (``Model.spring_slot_groups``: the head laid out group by group), each
  group's spring ``group_spring[g]`` and its rest length, stiffness and damping once, then in a uniform
  group's slot only the other particle j = ``head_local[k, i]`` and x_j, v_j (no spring index), in the slot
  of a group read per spring (-1) the spring index and the spring's three values too,
- or, with the grid layout too (``Model.spring_layout`` "grid": one cloth grid in grid order), the grid's
  size (nx, ny) once, and in a uniform group's slot no topology at all: j = i + dy·nx + dx from the slot's
  compile-time direction (slots of a group read per spring load head_element and head_local as above),

and writes its new position and velocity. Two counts per array:

- **compulsory**: every byte of the array once per substep (its size): what must cross from DRAM when
  nothing survives in cache from one substep to the next. Topology, rest lengths and one-row parameters
  are shared by all worlds, so their bytes per particle-substep fall as 1/world_count.
- **requested**: what the threads load without any reuse (S slot loads of 24 B of neighbour state and
  12 B of spring data each). The difference is what L1 and L2 absorb: each spring is read by both its
  ends, each particle's state by its own thread and its ≤ S neighbours.

Achieved bandwidth = compulsory bytes × particle-substeps/s: it is the DRAM bandwidth the kernel would
draw if caches absorbed exactly the reuse and nothing across substeps. Where the working set fits in L2
(≈ 50 MB on an H100) the substeps re-read it from there and the figure may exceed DRAM's.

    python bench/traffic.py --sizes 256 512 1024 2048          # the table of the layout, no device needed
    python bench/traffic.py --sizes 256 512 1024 2048 --layout groups    # the grouped incidence table
    python bench/traffic.py --sizes 256 512 1024 2048 --layout springs   # spring data per spring
    python bench/traffic.py --device cuda:0 --profile 1024      # one model, a few frames (for Nsight Compute)

``bench/cloth.py --bytes`` prints these counts next to the measured rates and a device copy's bandwidth,
and, where ``ncu`` exists, Nsight Compute's DRAM bytes of one substep's kernel (``ncu_dram_bytes``).
"""

from __future__ import annotations

import argparse
import csv
import io
import os
import shutil
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass

import warp as wp

import warpspring as ws
from cloth_scene import WarpspringRunner, warpspring_model

#: Nsight Compute metrics read for one launch of the fused kernel.
NCU_METRICS = ("dram__bytes_read.sum", "dram__bytes_write.sum", "lts__t_bytes.sum", "gpu__time_duration.sum")
#: Byte and time units Nsight Compute may print, in bytes and seconds.
NCU_UNITS = {
    "byte": 1.0, "kbyte": 1e3, "mbyte": 1e6, "gbyte": 1e9, "tbyte": 1e12,
    "nsecond": 1e-9, "usecond": 1e-6, "msecond": 1e-3, "second": 1.0,
    # `--print-units base` prints durations as "ns" (Nsight Compute on the H100 machine, 2026-11-25)
    "ns": 1e-9, "us": 1e-6, "ms": 1e-3, "s": 1.0,
}


@dataclass(frozen=True)
class ArrayTraffic:
    """One array of the fused gather step and its traffic per substep [bytes] over all worlds."""

    name: str
    role: str  # "state", "particle", "topology" or "spring": how its traffic scales
    compulsory: int  # the array's bytes, each once [B]
    requested: int  # the threads' loads or stores without reuse [B]


def gather_traffic(model: ws.Model) -> list[ArrayTraffic]:
    """Per-array traffic of one substep of the fused gather kernel on ``model`` (springs only, float32 or
    float64), from the model's own arrays: their dtypes, row counts and the incidence table's shape.

    Raises:
        ValueError: ``model`` is not stepped by the spring gather alone (other families, scattered springs).
    """
    specs = model.family_specs()
    if not model.spring_gather or len(specs) != 1:
        raise ValueError(
            f"the traffic model covers the spring gather alone; this model has families {specs} and "
            f"spring_gather={model.spring_gather}: build it with springs only and spring_evaluation='gather'"
        )
    n, worlds, springs = model.particle_count, model.world_count, model.spring_count
    threads = n * worlds
    head_slots, tail = model.spring_incidence_shape
    incidence = model.spring_incidence
    tail_entries = incidence.tail_element.shape[0] if tail else 0
    entries = head_slots + tail_entries / n  # loads per thread: every head slot, the tail's mean
    vec = wp.types.type_size_in_bytes(model.particle_q.dtype)
    scalar = wp.types.type_size_in_bytes(model.spring_rest_length.dtype)

    def size(array) -> int:
        return array.size * wp.types.type_size_in_bytes(array.dtype)

    grouped = bool(model.spring_slot_groups)
    grid = model.spring_layout == "grid"
    # Slots whose spring index and values are read per spring: all of them, or a non-uniform group's.
    per_spring_slots = model.spring_slot_groups.count(-1) if grouped else head_slots
    # Slots that load their other particle from the table: all of them, or on the grid a non-uniform group's.
    table_slots = per_spring_slots if grid else head_slots
    rows = [
        ArrayTraffic("particle_q_in", "state", threads * vec, round(threads * (1 + entries) * vec)),
        ArrayTraffic("particle_qd_in", "state", threads * vec, round(threads * (1 + entries) * vec)),
        ArrayTraffic("particle_q_out", "state", threads * vec, threads * vec),
        ArrayTraffic("particle_qd_out", "state", threads * vec, threads * vec),
        ArrayTraffic("particle_flags", "particle", size(model.particle_flags), threads * 4),
        ArrayTraffic("particle_mass", "particle", size(model.particle_mass), threads * scalar),
        ArrayTraffic("particle_inv_mass", "particle", size(model.particle_inv_mass), threads * scalar),
    ]
    if table_slots:
        rows.append(ArrayTraffic("head_local", "topology", size(incidence.head_local) * table_slots // head_slots,
                                 threads * table_slots * 4))
    if per_spring_slots:
        rows.insert(-1, ArrayTraffic("head_element", "topology",
                                     size(incidence.head_element) * per_spring_slots // head_slots,
                                     threads * per_spring_slots * 4))
    if grid:
        rows.append(ArrayTraffic("grid_size", "topology", size(model.spring_grid_size), threads * 8))
    if tail_entries:
        rows += [
            ArrayTraffic("tail_start", "topology", size(incidence.tail_start), threads * 8),
            ArrayTraffic("tail_element", "topology", size(incidence.tail_element), worlds * tail_entries * 4),
            ArrayTraffic("tail_local", "topology", size(incidence.tail_local), worlds * tail_entries * 4),
        ]
    if grouped:
        # One value per group (and stiffness or damping row): the group's spring, then its three values.
        groups = model.spring_group_spring.shape[0]
        stiffness_rows, damping_rows = model.spring_stiffness.shape[0], model.spring_damping.shape[0]
        rows += [
            ArrayTraffic("group_spring", "spring", groups * 4, threads * groups * 4),
            ArrayTraffic("spring_rest_length", "spring", groups * scalar, threads * groups * scalar),
            ArrayTraffic("spring_stiffness", "spring", stiffness_rows * groups * scalar, threads * groups * scalar),
            ArrayTraffic("spring_damping", "spring", damping_rows * groups * scalar, threads * groups * scalar),
        ]
        if per_spring_slots:
            # The springs of the groups read per spring, each value once; every such slot loads three.
            uniform = set(model.spring_slot_groups) - {-1}
            read = sum(len(m) for g, m in enumerate(model.spring_families.values()) if g not in uniform)
            rows.append(ArrayTraffic("spring data read per spring", "spring",
                                     read * scalar * (1 + stiffness_rows + damping_rows),
                                     threads * per_spring_slots * 3 * scalar))
    else:
        rows += [
            ArrayTraffic("spring_rest_length", "spring", springs * scalar, round(threads * entries * scalar)),
            ArrayTraffic("spring_stiffness", "spring", size(model.spring_stiffness),
                         round(threads * entries * scalar)),
            ArrayTraffic("spring_damping", "spring", size(model.spring_damping), round(threads * entries * scalar)),
        ]
    rows += [
        # The live-input table (gravity) and the clocks: a row per world, read by every thread of it.
        ArrayTraffic("inputs, time", "particle", size(model.inputs) + 2 * worlds * 8, threads * 3 * scalar),
    ]
    return rows


def per_particle(rows: list[ArrayTraffic], model: ws.Model) -> dict[str, float]:
    """Bytes per particle-substep: compulsory and requested in all, and compulsory by role."""
    threads = model.particle_count * model.world_count
    out = {
        "compulsory": sum(r.compulsory for r in rows) / threads,
        "requested": sum(r.requested for r in rows) / threads,
    }
    for role in ("state", "particle", "topology", "spring"):
        out[role] = sum(r.compulsory for r in rows if r.role == role) / threads
    return out


def copy_bandwidth(device, *, megabytes: int = 512, repeats: int = 10) -> float:
    """Bandwidth [B/s] of ``wp.copy`` between two float32 arrays of ``megabytes`` MB on ``device`` (read +
    write counted, median of ``repeats`` copies, device synchronised around each): the memory roofline the
    kernel is compared against, measured in the same process."""
    count = megabytes * (1 << 20) // 4
    src = wp.ones(count, dtype=wp.float32, device=device)
    dst = wp.empty_like(src)
    wp.copy(dst, src)  # first touch
    times = []
    for _ in range(repeats):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        wp.copy(dst, src)
        wp.synchronize_device(device)
        times.append(time.perf_counter() - t0)
    return 2 * count * 4 / statistics.median(times)


#: finalize's options of each spring layout of the gather (``Model.spring_layout``) on a cloth grid.
LAYOUTS = {"grid": {}, "groups": {"spring_grid": False}, "springs": {"spring_groups": False}}


def ncu_dram_bytes(n: int, device, *, kernel_cache: str | None = None, timeout: float = 120.0,
                   layout: str = "grid") -> dict | str:
    """Nsight Compute's counters for one launch of the fused step on the n × n cloth (the 21st, after warm-up
    and capture; caches flushed before it, as ncu does by default; clocks left as they run, as in §7 of
    RESULTS.md): {metric: value in bytes or seconds}, or a one-line reason when ``ncu`` is missing or fails."""
    ncu = shutil.which("ncu")
    if ncu is None:
        return "ncu not found on PATH: no Nsight Compute counters"
    command = [
        ncu, "--csv", "--print-units", "base", "--clock-control", "none", "--metrics", ",".join(NCU_METRICS),
        "-k", "regex:symplectic_euler",
        "--launch-skip", "20", "--launch-count", "1",
        sys.executable, os.path.abspath(__file__), "--device", str(device), "--profile", str(n),
        "--layout", layout,
    ]
    env = dict(os.environ, **({"WARP_CACHE_PATH": kernel_cache} if kernel_cache else {}))
    try:
        run = subprocess.run(command, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return f"ncu ran past {timeout:.0f} s at {n}²"
    values = parse_ncu_csv(run.stdout)
    if not values:
        last = (run.stderr.strip() or run.stdout.strip() or "no output").splitlines()[-1]
        return f"ncu gave no counters at {n}² (exit {run.returncode}): {last}"
    return values


def parse_ncu_csv(text: str) -> dict[str, float]:
    """{metric name: value in bytes or seconds} from ``ncu --csv`` output (other lines ignored)."""
    lines = [line for line in text.splitlines() if line.startswith('"')]
    values = {}
    for row in csv.DictReader(io.StringIO("\n".join(lines))):
        name, unit, value = row.get("Metric Name"), row.get("Metric Unit", ""), row.get("Metric Value")
        if name in NCU_METRICS and value:
            scale = NCU_UNITS.get(unit.strip().lower(), 1.0)
            values[name] = float(value.replace(",", "")) * scale
    return values


def profile(n: int, device, frames: int = 3, *, layout: str = "grid") -> None:
    """The target of ``ncu_dram_bytes``: the n × n ANCHORS cloth, gather in ``layout``, a few graph-replayed
    frames."""

    runner = WarpspringRunner(warpspring_model(n, device, "gather", **LAYOUTS[layout]))
    for _ in range(frames):
        runner.frame()
    wp.synchronize_device(device)


def layout_table(sizes: list[int], worlds: list[int], device, *, layout: str = "grid") -> list[str]:
    """Markdown rows of the traffic model for n × n cloths (one world) and ``worlds`` × 32² cloths in the spring
    ``layout`` (``LAYOUTS``; "grid", these cloths' default)."""

    lines = [
        "| scene | head slots | state | particle | topology | spring data | compulsory | requested | "
        "working set [MB] |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    cases = [(n, 1) for n in sizes] + [(32, w) for w in worlds]
    for n, w in cases:
        model = warpspring_model(n, device, "gather", worlds=w, **LAYOUTS[layout])
        assert model.spring_layout == layout, (model.spring_layout, layout)
        rows = gather_traffic(model)
        b = per_particle(rows, model)
        working_set = sum(r.compulsory for r in rows) / 1e6  # both state buffers and the model's arrays
        scene = f"{n}²" if w == 1 else f"{w:,} × 32²"
        lines.append(
            f"| {scene} | {model.spring_incidence_shape.head_slots} | {b['state']:.0f} B | {b['particle']:.1f} B | "
            f"{b['topology']:.1f} B | {b['spring']:.1f} B | **{b['compulsory']:.0f} B** | {b['requested']:.0f} B | "
            f"{working_set:,.1f} |"
        )
    return lines


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", help="Warp device the models are built on")
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024, 2048])
    parser.add_argument("--worlds", type=int, nargs="*", default=[4096], help="also W worlds of a 32² cloth")
    parser.add_argument("--profile", type=int, metavar="N", help="run the N × N cloth a few frames and exit")
    parser.add_argument("--layout", choices=list(LAYOUTS), default="grid",
                        help="the gather's spring layout: grid (neighbours from row and column, the default), groups "
                             "(finalize(spring_grid=False): the incidence table, values per group) or springs "
                             "(finalize(spring_groups=False): values per spring)")
    parser.add_argument("--per-spring", action="store_true", help="the same as --layout springs")
    args = parser.parse_args()
    layout = "springs" if args.per_spring else args.layout
    wp.config.log_level = wp.LOG_WARNING
    device = wp.get_device(args.device)
    if args.profile:
        profile(args.profile, device, layout=layout)
        return
    print(f"Bytes per particle-substep of the fused gather step (symplectic Euler, float32, spring layout {layout!r}), "
          "from the data layout:")
    print("\n".join(layout_table(args.sizes, args.worlds, device, layout=layout)))


if __name__ == "__main__":
    main()
