"""The scaling plot: particle-substeps/s against particle count, from the CSV of ``bench/scaling.py``.

One line per engine and scene family (one world of N², W worlds of 32²), log-log axes, the CSV's first line
(machine, Warp and Newton versions, date, copy bandwidth) as the title, and the bandwidth ceiling of the
gather's compulsory traffic (copy bandwidth / the gather's bytes per particle-substep, both in the CSV's first
line) as a dotted line.

    python bench/scaling_plot.py bench/results/scaling_h100.csv bench/results/scaling_h100.png
"""

from __future__ import annotations

import argparse
import csv
import re


def read(path: str) -> tuple[str, list[dict]]:
    """The CSV's header line (without '# ') and its rows."""
    with open(path) as f:
        header = f.readline().lstrip("# ").strip()
        return header, list(csv.DictReader(f))


def plot(csv_path: str, png_path: str) -> None:
    """Draw ``csv_path`` into ``png_path``."""
    from warpspring.plotting import pyplot

    plt = pyplot("scaling plots")
    header, rows = read(csv_path)
    fig, ax = plt.subplots(figsize=(8, 5))
    series = sorted({(r["engine"], r["scene"]) for r in rows})
    for engine, scene in series:
        points = sorted((int(r["particles"]), float(r["particle_substeps_per_s"])) for r in rows
                        if r["engine"] == engine and r["scene"] == scene)
        x, y = zip(*points)
        label = f"{engine}, {'N² cloth' if scene == 'one world' else 'W × 32² cloths'}"
        ax.plot(x, y, "-o" if scene == "one world" else "--s", label=label,
                color="C0" if engine.startswith("warpspring") else "C1", markersize=4)
    ax.set_xscale("log")
    ax.set_yscale("log")
    copy = re.search(r"wp\.copy ([0-9.]+) GB/s", header)
    gather = re.search(r"gather ([0-9.]+) B/particle-substep", header)
    if copy and gather:
        ceiling = float(copy.group(1)) * 1e9 / float(gather.group(1))
        ax.axhline(ceiling, color="gray", linestyle=":", linewidth=1)
        ax.annotate(f"copy bandwidth / {float(gather.group(1)):.0f} B (the gather's bytes)", (0.01, ceiling),
                    xycoords=("axes fraction", "data"), fontsize=8, color="gray", va="bottom")
    ax.set_xlabel("particles in the model (all worlds)")
    ax.set_ylabel("particle-substeps / s")
    # The header is "machine; versions; date; copy; gather": two lines, so a long machine name is not cut off.
    parts = [part.strip() for part in header.split(";")]
    middle = (len(parts) + 1) // 2
    header = "; ".join(parts[:middle]) + "\n" + "; ".join(parts[middle:])
    ax.set_title(f"Hanging cloth, symplectic Euler, 16 substeps per frame\n{header}", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png_path, dpi=120)
    plt.close(fig)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("csv", help="the CSV written by bench/scaling.py")
    parser.add_argument("png", help="the plot to write")
    args = parser.parse_args()
    plot(args.csv, args.png)


if __name__ == "__main__":
    main()
