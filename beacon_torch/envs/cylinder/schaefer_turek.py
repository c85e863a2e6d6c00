"""The uncontrolled cylinder wake against the Schaefer-Turek benchmark 2D-2.

    .venv/bin/python -m beacon_torch.envs.cylinder.schaefer_turek [--cells 20 40 ...] [--dt ...] [--time 8] [--out DIR]
    .venv/bin/python -m beacon_torch.envs.cylinder.schaefer_turek --plot RECORD.json FIGURE.png

For each resolution (cells across the diameter), the channel starts at rest with its
inflow on and runs ``--time`` time units in float64 without control
(``beacon_torch.envs.cylinder.developed_shedding``); over the last two time units it
measures the largest drag and lift coefficients, the mean drag coefficient and the
Strouhal number (from the lift's upward zero crossings), and prints them beside the
benchmark's intervals with the relative distance to the nearer end. Writes a new dated
``cylinder_validation-DATE-TIME.json`` (rows and the coefficient histories of the
window) to ``--out``. Each resolution runs in its own process (one core each).
``--plot`` draws a record's drag and lift histories, one line per resolution, into a
new figure (the page's, docs/img/cylinder-validation.png). The records on the page are
in ``validation/results/cylinder/``.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import os

WINDOW = 2.0  # time units at the end of a run that are measured


def off_by(value: float, interval: tuple[float, float]) -> float:
    """The relative distance of ``value`` to the nearer end of ``interval`` (0 inside)."""
    low, high = interval
    if value != value:  # a run that blew up
        return value
    if value < low:
        return (value - low) / low
    if value > high:
        return (value - high) / high
    return 0.0


def measure(cells: int, time: float, dt: float) -> dict:
    import torch

    from beacon_torch.envs.cylinder import developed_shedding, shedding_figures

    torch.set_num_threads(1)
    _, history = developed_shedding(cells, time=time, dt=dt)
    figures = shedding_figures(history["time"], history["drag"], history["lift"], WINDOW)
    row = {"cells_per_diameter": cells, "time": time, "dt": dt, **figures}
    last = history["time"] > history["time"][-1] - WINDOW
    row["history"] = {k: v[last][::10].tolist() for k, v in history.items()}
    return row


def table(rows: list[dict]) -> str:
    from beacon_torch.envs.cylinder import SCHAEFER_TUREK

    lines = [
        "| cells per D | dt | C_D,max | C_L,max | mean C_D | St |",
        "|---|---|---|---|---|---|",
        "| Schaefer-Turek 2D-2 | | 3.22-3.24 | 0.99-1.01 | | 0.295-0.305 |",
    ]
    for r in sorted(rows, key=lambda r: r["cells_per_diameter"]):
        cells = [f"{r[k]:.3f} ({100 * off_by(r[k], SCHAEFER_TUREK[k]):+.1f} %)" for k in ("cd_max", "cl_max")]
        strouhal = f"{r['strouhal']:.4f} ({100 * off_by(r['strouhal'], SCHAEFER_TUREK['strouhal']):+.1f} %)"
        row = [str(r["cells_per_diameter"]), f"{r['dt']:g}", *cells, f"{r['cd_mean']:.3f}", strouhal]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def plot(record: str, figure: str) -> None:

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from beacon_torch import received
    from beacon_torch.envs.cylinder import SCHAEFER_TUREK
    from beacon_torch.files import create_file

    rows = received.json_file(record, "a validation record")["rows"]
    fig, (drag, lift) = plt.subplots(2, 1, figsize=(7.0, 4.6), sharex=True)
    for r in sorted(rows, key=lambda r: r["cells_per_diameter"]):
        t = [x - r["history"]["time"][0] for x in r["history"]["time"]]
        label = f"{r['cells_per_diameter']} cells per D, dt {r['dt']:g}"
        drag.plot(t, r["history"]["drag"], lw=0.9, label=label)
        lift.plot(t, r["history"]["lift"], lw=0.9, label=label)
    for ax, key, name in ((drag, "cd_max", "C_D"), (lift, "cl_max", "C_L")):
        ax.axhspan(*SCHAEFER_TUREK[key], color="0.8", label="Schaefer-Turek max")
        ax.set_ylabel(name)
    lift.set_xlabel("time over the measured window")
    drag.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    print("figure:", create_file(figure, lambda tmp: fig.savefig(tmp, dpi=110, format="png")))


def main() -> None:
    from beacon_torch.files import save_rows

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cells", type=int, nargs="+", default=[10, 20], help="cells across the diameter")
    parser.add_argument("--time", type=float, default=8.0, help="time units from rest")
    parser.add_argument(
        "--dt", type=float, nargs="+", default=None, help="time step per resolution (default: the env's, 5e-4)"
    )
    parser.add_argument("--out", default="runs/cylinder_validation")
    parser.add_argument("--plot", nargs=2, metavar=("RECORD", "FIGURE"), help="draw a record's histories")
    args = parser.parse_args()
    if args.plot:
        return plot(*args.plot)
    workers = min(len(args.cells), os.cpu_count() or 1)
    with concurrent.futures.ProcessPoolExecutor(workers) as pool:
        dts = args.dt or [5e-4] * len(args.cells)
        if len(dts) != len(args.cells):
            parser.error(f"--dt gives {len(dts)} time steps for {len(args.cells)} resolutions")
        rows = list(pool.map(measure, args.cells, [args.time] * len(args.cells), dts))
    print(table(rows))
    print("results:", save_rows(rows, args.out, "cylinder_validation"))


if __name__ == "__main__":
    main()
