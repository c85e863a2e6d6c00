"""The steady pinball at Re 30 against HydroGym's recorded forces.

    .venv/bin/python -m beacon_torch.envs.pinball.steady [--cells 10 20 30] [--setups ...] [--out DIR]

HydroGym's pinball test solves the steady flow at Re 30 on its fine mesh by Newton's
method and records each cylinder's drag and lift coefficients (front, top, bottom):
C_D = (1.451, 1.566, 1.566), C_L = (0, 0.521, -0.521). Its mesh puts the front
cylinder at the origin of the box [-6, 20] x [-6, 6] (so the inflow is 6 D ahead of
it, 4.7 D in Deng et al.'s box, where the origin lies between the rear cylinders), and
the mesh file of that test's time puts the rear cylinders 1.5 x 1.866 R behind the
front one, not the triangle's 1.5 x 1.732 R. Each set-up here starts from the free
stream and runs in float64 at Re 30 without control until the drag changes by less
than 1e-6 over a time unit (or ``--time`` units):

- ``hydrogym-mesh``: HydroGym's box and its mesh's cylinders (the reference's set-up);
- ``hydrogym-box``: HydroGym's box with the equilateral triangle;
- ``pinball-v0``: the env's own box and triangle (Deng et al.'s).

Prints each set-up's coefficients beside the reference and writes them to a new dated
``pinball_steady-DATE-TIME.json`` in ``--out``. Each run is its own process.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import math
import os

RE = 30.0
# HydroGym's test_steady (fine mesh): front, top, bottom
HYDROGYM = {"drag": (1.451, 1.566, 1.566), "lift": (0.0, 0.521, -0.521)}
SETUPS = ("hydrogym-mesh", "hydrogym-box", "pinball-v0")


def geometry(setup: str):
    """The cylinders and the box's x range of a set-up, in the env's coordinates."""
    from beacon_torch.envs.pinball.flow import CYLINDERS, RADIUS, X_RANGE
    from beacon_torch.numerics.bodies import Circle

    if setup == "pinball-v0":
        return CYLINDERS, X_RANGE
    rear = 1.5 * (1.866 if setup == "hydrogym-mesh" else math.sqrt(3.0)) * RADIUS
    cylinders = (Circle(-rear, 0.0, RADIUS), *CYLINDERS[1:])
    # HydroGym's box is [-6, 20] from the front cylinder's centre
    return cylinders, (-6.0 - rear, 20.0 - rear)


def time_step(cells: int) -> float:
    """The env's dt where it is stable at Re 30, else a smaller one with the same margin."""
    from beacon_torch.envs.pinball.flow import DT

    h = 1.0 / cells
    return min(DT, 0.5 * h * h * RE / 8.0)


def measure(setup: str, cells: int, time: float) -> dict:
    import numpy as np
    import torch

    from beacon_torch.envs.pinball.flow import Box, coefficient, rest, run

    torch.set_num_threads(1)
    cylinders, x_range = geometry(setup)
    box = Box(cells, cylinders=cylinders, x_range=x_range, dtype=torch.float64, device="cpu")
    dt = time_step(cells)
    flow = rest(1, box, torch.float64, "cpu")
    still = torch.zeros(1, 3, dtype=torch.float64)
    per_unit = int(round(1.0 / dt))
    history, change = [], float("inf")
    with torch.no_grad():
        for k in range(int(time)):
            flow, loads = run(flow, per_unit, still, box, 1.0 / RE, dt)
            drag, lift = coefficient(loads[0, 0]).numpy(), coefficient(loads[0, 1]).numpy()
            if history:
                change = float(np.abs(drag - history[-1]["drag"]).max())
            history.append({"time": k + 1.0, "drag": drag.tolist(), "lift": lift.tolist()})
            if change < 1e-6:
                break
    last = history[-1]
    return {
        "setup": setup,
        "cells_per_diameter": cells,
        "dt": dt,
        "cells": box.nx * box.ny,
        "time": last["time"],
        "last_change": change,
        "drag": last["drag"],
        "lift": last["lift"],
        "history": history,
    }


def table(rows: list[dict]) -> str:
    """The rows against HydroGym's forces, as markdown."""
    ref_d, ref_l = HYDROGYM["drag"], HYDROGYM["lift"]
    lines = [
        "| set-up | cells per D | dt | C_D front | C_D top | C_D bottom | C_L top | C_L bottom |",
        "|---|---|---|---|---|---|---|---|",
        f"| HydroGym (fine mesh, Newton) | | | {ref_d[0]} | {ref_d[1]} | {ref_d[2]} | {ref_l[1]} | {ref_l[2]} |",
    ]
    order = {s: i for i, s in enumerate(SETUPS)}
    for r in sorted(rows, key=lambda r: (order[r["setup"]], r["cells_per_diameter"])):
        pct = lambda v, ref: f"{v:.4f} ({100 * (v / ref - 1):+.1f} %)"
        drag = [pct(v, ref) for v, ref in zip(r["drag"], ref_d, strict=True)]
        lift = [pct(v, ref) for v, ref in zip(r["lift"][1:], ref_l[1:], strict=True)]
        lines.append(f"| {r['setup']} | {r['cells_per_diameter']} | {r['dt']:g} | " + " | ".join(drag + lift) + " |")
    return "\n".join(lines)


def main() -> None:
    from beacon_torch.files import save_rows

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cells", type=int, nargs="+", default=[10, 20], help="cells across a diameter")
    parser.add_argument("--setups", nargs="+", default=list(SETUPS), choices=SETUPS)
    parser.add_argument("--time", type=float, default=80.0, help="the most time units from the free stream")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--out", default="runs/pinball_steady")
    args = parser.parse_args()
    runs = [(s, c) for s in args.setups for c in args.cells]
    with concurrent.futures.ProcessPoolExecutor(min(args.workers, len(runs))) as pool:
        rows = list(pool.map(measure, *zip(*runs, strict=True), [args.time] * len(runs)))
    print(table(rows))
    print("results:", save_rows(rows, args.out, "pinball_steady"))


if __name__ == "__main__":
    main()
