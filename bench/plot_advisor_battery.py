"""Plot the advisor battery's ratios from its raw tables: per case, what ``--strict`` passes against the 10 s
blow-up and against the case's lowest limit (the blow-up and the two linear limits), by integrator and step.
A table that contradicts the battery's claim (no passed world blew up or grows; every pass within 10 % of the
case's lowest limit) is named row by row on stderr, and the exit status is 1.

    python bench/plot_advisor_battery.py                       # results/advisor_frozen_h100.md → docs/images
    python bench/plot_advisor_battery.py --results FILE.md --out PLOT.png
"""

import argparse
import os
import sys

import numpy as np

from warpspring.analysis.load_battery import EXPLICIT, SCENES
from warpspring.plotting import pyplot

HERE = os.path.dirname(os.path.abspath(__file__))


def read_rows(path: str) -> list[dict]:
    """Every row of the Markdown tables in ``path`` whose header starts with "scene | integrator", as {column:
    cell}; a case measured twice keeps its last row."""
    rows, header = {}, None
    with open(path) as f:
        for line in f:
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if not line.startswith("|"):
                header = None
            elif cells[:2] == ["scene", "integrator"]:
                header = cells
            elif header and not set(cells[0]) <= {"-"} and len(cells) == len(header):
                row = dict(zip(header, cells))
                rows[(row["scene"], row["integrator"], row["dt"])] = row
    return list(rows.values())


def stiffness(cell: str) -> float:
    """A table's "1.2e+04 N/m" as a number [N/m]; NaN for "none in the grids" or "–"."""
    try:
        return float(cell.split()[0])
    except (ValueError, IndexError):
        return float("nan")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--results", default=os.path.join(HERE, "results", "advisor_frozen_h100.md"))
    parser.add_argument("--out", default=os.path.join(HERE, "..", "docs", "images", "advisor_battery.png"))
    args = parser.parse_args()
    plt = pyplot("the battery plot")
    rows = read_rows(args.results)
    steps = sorted({(r["integrator"], r["dt"]) for r in rows},
                   key=lambda key: (EXPLICIT.index(key[0]), float(key[1].split()[0].split("/")[1])))
    fig, ax = plt.subplots(figsize=(10, 4.2))
    colours = dict(zip(SCENES, plt.rcParams["axes.prop_cycle"].by_key()["color"]))
    for x, (integrator, dt) in enumerate(steps):
        for offset, scene in zip(np.linspace(-0.28, 0.28, len(SCENES)), SCENES):
            row = next((r for r in rows if (r["scene"], r["integrator"], r["dt"]) == (scene, integrator, dt)), None)
            if row is None:
                continue
            passed = stiffness(row["advisor passes up to"])
            lowest = float(row.get("ratio to the lowest", row["ratio"]).replace("nan", "NaN"))
            ax.plot(x + offset, lowest, "o", color=colours[scene], label=scene if x == 0 else None)
            ax.plot(x + offset, passed / stiffness(row["blows up from ke"]), "o", mfc="none", color=colours[scene])
    ax.axhspan(0.9, 1.0, color="0.9", zorder=0)
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set_xticks(range(len(steps)), [f"{i.replace('_', ' ')}\n{dt}" for i, dt in steps], fontsize=8)
    ax.set_ylabel("advisor passes / limit")
    ax.set_ylim(0.55, 1.05)
    ax.set_title("Filled: against the lowest of the 10 s blow-up and the linear limits; open: against the 10 s "
                 "blow-up alone.\nGrey: the 10 % target; above 1 would pass a run past its limit.", fontsize=9)
    ax.legend(fontsize=8, ncol=5, loc="lower left")
    fig.tight_layout()
    fig.savefig(args.out, dpi=120)
    print(f"wrote {args.out} ({len(rows)} cases from {args.results})")
    problems = claim_problems(rows)
    for line in problems:
        print(f"warning: {line}", file=sys.stderr)
    return 1 if problems else 0


def claim_problems(rows: list[dict]) -> list[str]:
    """What in ``rows`` contradicts the battery's claim (docs/stability.md, bench/results/advisor.md): the advisor
    passes no world that blew up or whose top mode grows, and passes within 10 % of each case's lowest limit."""
    problems = [f"{r['scene']}, {r['integrator']}, {r['dt']}: passed {r['passed but blew up']} world(s) that blew up "
                f"and {r.get('passed but grows', '0')} whose top mode grows" for r in rows
                if r["passed but blew up"] != "0" or r.get("passed but grows", "0") not in ("0", "–")]
    for r in rows:
        lowest = float(r.get("ratio to the lowest", r["ratio"]))
        if not 0.9 <= lowest <= 1.0:
            problems.append(f"{r['scene']}, {r['integrator']}, {r['dt']}: passes {lowest:.3f} of its lowest limit")
    return problems


if __name__ == "__main__":
    sys.exit(main())
