"""Integrators: error against cost, measured. The same as ``warpspring trade`` (see ``warpspring.analysis.trade``).

Every registered integrator × step × precision on the seed spring (45 kg, 75 N), a stiff lightly
damped spring and the ANCHORS hanging cloth: wall time per simulated second (graph replays, device
synchronised, compilation excluded, median of repeats) and error against the closed form or a
float64 RK4 reference. Writes trade.csv, trade.md, pareto.png, convergence.png and seed.png to --out.
``--problems`` picks problems, the contact scenes among them (``warpspring.analysis.trade_contact``: every
integrator that applies × substeps × precision × contact options against float64 fine-step references;
pareto_contact.png).

    python bench/trade.py --device cpu --quick          # about a minute
    python bench/trade.py --device cuda:0 --out trade   # the full study
    python bench/trade.py --device cpu --problems drape stack tablecloth softball softball-neohookean \\
        --out bench/results/trade_contact_cpu            # the contact scenes: ~9 minutes on one CPU core
    python bench/trade.py --device cuda:0 --quick --problems drape stack tablecloth softball softball-neohookean \\
        --out bench/results/trade_contact_cuda_quick -q   # the quick contact study on a GPU
    python bench/trade.py --device cuda:0 --reduced --problems drape stack tablecloth softball softball-neohookean \\
        --out bench/results/trade_contact_cuda_reduced -q # full-size scenes, every integrator at 20 and 40 substeps
    python bench/trade.py --device cuda:0 --problems drape --out bench/results/trade_contact_cuda/drape -q
        # the full study on a GPU, a problem a process (bench/results/trade_contact_cuda/*: 81-188 s each on an H100)

``--reduced`` keeps the full scenes (their costs compare with the full study's rows) with fewer runs: the reference
option, 20 and 40 substeps, dopri5 at 1e-3, one reference refinement (110 configurations; 179 s and 338 s in two
runs on the shared 2-core CPU; bench/results/trade_contact_cpu_reduced/). Every file names the device: the report's header and plot titles, each CSV row (``device``,
``device_name``), the command's last line.

``--table CSV...`` writes the measured trade table that ``substeps = "auto"`` reads
(``warpspring/analysis/trade_table.json``, shipped with the package; ``warpspring.analysis.trade_table``) from
studies' CSV files, each with its report (``.md``) beside it for the provenance; a later file's problem replaces an
earlier one's:

    python bench/trade.py --table bench/results/trade_cpu.csv bench/results/trade_contact_cpu/trade.csv \\
        bench/results/trade_contact_cpu_tablecloth/trade.csv
"""

import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))  # this checkout's warpspring

from warpspring.analysis.trade_table import load_table, write_table as write  # noqa: E402
from warpspring.app.cli import main  # noqa: E402


def write_table(paths: list[str]) -> int:
    if not paths:
        print("usage: python bench/trade.py --table STUDY.csv [STUDY.csv ...]", file=sys.stderr)
        return 2
    path = write(paths)
    table = load_table(path)
    print(f"wrote {path} ({pathlib.Path(path).stat().st_size} bytes): floor {table.floor:.3g} m over a frame, "
          f"{len(table.problems)} contact problem options from {len(table.sources)} studies")
    return 0


if __name__ == "__main__":
    if sys.argv[1:2] == ["--table"]:
        sys.exit(write_table(sys.argv[2:]))
    sys.exit(main(["trade", *sys.argv[1:]]))
