"""ASTM D1388 (cantilever) by simulation against the float64 heavy elastica, for the cloth presets and the
cloth of the drape study, at several resolutions (``warpspring.analysis.d1388``).

For each material: its bending length c = (B / ρ_A g)^⅓, the elastica's overhang Λ* c (Λ* = 2.0003 at 41.5°)
and, at each number of cells over the overhang, the simulated overhang at which the chord from the platform's
edge to the tip falls 41.5°, its error, and the static steps of the last solve. ``--hinges triangles`` is not
offered: the triangles' hinges are measured in tests/test_d1388.py's docstring (-13 % at 8 cells).

    python bench/d1388.py --device cpu --cells 4 8 16 32
    python bench/d1388.py --device cuda:0 --cells 4 8 16 32 64

Writes its table into bench/results/cloth_materials.md (the section between its markers).
"""

from __future__ import annotations

import argparse
import datetime
import pathlib
import time

import warp as wp

import warpspring as ws
from warpspring.analysis import d1388, elastica
from warpspring.core import material as wm

RESULTS = pathlib.Path(__file__).parent / "results" / "cloth_materials.md"
#: The cloth of the drape study (issue: drape moved with resolution) and the presets.
MATERIALS = {"study": ws.ClothMaterial(stretch=300.0, shear=10.0, bending=5.0e-6, density=0.13), **wm.PRESETS}


def write_section(key: str, text: str, path: pathlib.Path = RESULTS) -> None:
    """Replace (or append) the section of ``path`` between ``<!-- key -->`` and ``<!-- /key -->``."""
    start, end = f"<!-- {key} -->", f"<!-- /{key} -->"
    old = path.read_text() if path.exists() else "# Cloth materials: measured\n"
    if start in old and end in old:
        head, rest = old.split(start, 1)
        new = head + start + "\n" + text + "\n" + end + rest.split(end, 1)[1]
    else:
        new = old.rstrip("\n") + "\n\n" + start + "\n" + text + "\n" + end + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(new)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--cells", type=int, nargs="+", default=[4, 8, 16, 32])
    parser.add_argument("--materials", nargs="+", default=list(MATERIALS), choices=list(MATERIALS))
    args = parser.parse_args()
    wp.init()
    device = wp.get_device(args.device)
    rows = []
    for name in args.materials:
        material = MATERIALS[name]
        c = elastica.bending_length(material.bending, material.density)
        for cells in args.cells:
            start = time.perf_counter()
            result = d1388.simulate(material, cells=cells, device=device)
            rows.append(f"| {name} | {c * 1e3:.2f} | {result.reference * 1e3:.3f} | {cells} | "
                        f"{result.overhang * 1e3:.3f} | {result.error:+.2%} | {result.cantilever.steps} | "
                        f"{time.perf_counter() - start:.1f} |")
            print(rows[-1], flush=True)
    command = "python bench/d1388.py --device " + args.device + " --cells " + " ".join(map(str, args.cells))
    if args.materials != list(MATERIALS):
        command += " --materials " + " ".join(args.materials)
    text = "\n".join([
        "## ASTM D1388 by simulation against the heavy elastica",
        "",
        f"`{command}` — {device.name} ({device.alias}), Warp {wp.config.version}, {datetime.date.today()}",
        "",
        "| material | c [mm] | elastica L [mm] | cells over L | simulated L [mm] | error | static steps | wall [s] |",
        "|---|---|---|---|---|---|---|---|",
        *rows,
    ])
    print(text)
    write_section("d1388-" + device.alias.replace(":", ""), text)


if __name__ == "__main__":
    main()
