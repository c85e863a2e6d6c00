"""FluidGym's RBC2D levels uncontrolled, in float64: the Nusselt number of each level
against FluidGym's, on the env's grid and refined ones.

    .venv/bin/python validation/rbc2d.py [--levels easy medium hard] [--cells 8 12 16]
                                         [--average 100] [--out DIR] [--page FILE]

For each level and grid (``heater_cells`` cells along x per heater; the env's is 8,
FluidGym's grid) ten initial domains (``--seeds``; FluidGym develops ten per split)
start from FluidGym's conduction profile with noise of their own seed, side by side as
one batch, and run 283 time units without control (as the env's developed start), then
``--average`` more, the Nusselt number 1 + sqrt(Ra Pr) <v T> read after each time unit
(and the one of the plates' temperature gradients, first order in the plates' rows: in a
steady mean the two agree to the discretisation's error). A refined grid keeps the rows'
ratio (1.02), so its rows near the plates shrink faster than its columns, and takes the
step of :func:`time_step`. Recorded: each seed's mean, their interquartile mean
(FluidGym's table is the IQM over its seeds and test episodes) and mean, the median of
every sample, the largest CFL number met, each seed's convection cells (sign changes of
v at mid-height: a flow may settle into more or fewer rolls, each with its own Nusselt
number), beside FluidGym's 4.841 / 6.856 / 7.854 and the scaling Nu = 0.138 Ra^0.285
(Johnston & Doering 2009, two-dimensional convection between fixed-temperature plates).

Records a dated ``nusselt-DATE.json`` in ``validation/results/rbc2d/`` (each level and
grid as soon as it is done) and writes on the page the newest row of each level and grid over the records.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import torch

from beacon_torch.envs import rbc2d

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "validation" / "results" / "rbc2d"
BEGIN, END = "<!-- validation: validation/rbc2d.py -->", "<!-- end of the validation -->"
GRIDS = (8, 12, 16)
HEATERS, PR = 12, 0.7  # FluidGym's heaters and Prandtl number
FIRST_SEED = 300  # FluidGym's test domains are seeds 300 to 309 (ours: our generator's)


def scaling(ra: float) -> float:
    """Johnston & Doering (2009)'s fit of two-dimensional convection."""
    return 0.138 * ra**0.285


def time_step(level: dict, cells: int) -> float:
    """The level's time step on a grid of ``cells`` columns a heater: shrunk with the
    columns' width (the CFL number of the env's grid kept) and, where the explicit
    diffusion of the finest rows asks for less, to 0.8 of that bound; a whole number
    of steps a time unit. The env's grid keeps the level's step."""

    nx = HEATERS * cells
    ny = round(rbc2d.Y_SCALE * nx / math.pi)
    dx, dy = math.pi / nx, float(rbc2d.wall_refined(ny, rbc2d.BASE).min()) * rbc2d.HEIGHT
    diffusivity = max(math.sqrt(PR / level["ra"]), 1.0 / math.sqrt(PR * level["ra"]))
    bound = 1.0 / (2.0 * diffusivity * (1.0 / dx**2 + 1.0 / dy**2))
    dt = min(level["dt"] * 8 / cells, 0.8 * bound) if cells > 8 else level["dt"]
    return 1.0 / math.ceil(round(1.0 / dt, 9))


def measure(name: str, cells: int, seeds: list[int], average: int, compile: bool = True) -> dict:
    from beacon_torch.params import resolve_params

    level = rbc2d.LEVELS[name]
    given = dict(level, heater_cells=cells, dt=time_step(level, cells))
    f64, n = torch.float64, len(seeds)
    p = resolve_params(rbc2d.Rbc2dParams, given, batch_size=n, device="cpu", dtype=f64, env_id=f"rbc2d-{name}-v0")
    physics = rbc2d.Rbc2dPhysics(p, n, dtype=f64)
    if compile:
        physics.kernels.compile()
    per_unit = int(round(1.0 / p.dt))
    start = time.perf_counter()
    flow = rbc2d.develop(physics, p, seeds)  # the seeds' initial domains side by side
    samples, walls, cfl = [], [], torch.zeros(n, dtype=f64)
    half = 0.5 * physics.axis.widths
    bottom = torch.ones(n, physics.nx, dtype=f64)
    for _ in range(average):
        flow = rbc2d.uncontrolled(physics, p, flow, per_unit)
        state = rbc2d.Rbc2dState(*flow, bottom=bottom)
        samples.append(physics.nusselt(p, state))
        theta = flow.scalar[:, 1:-1, 1:-1]
        plates = (rbc2d.T_HOT - theta[:, :, 0]) / half[0] + (theta[:, :, -1] - rbc2d.T_COLD) / half[-1]
        walls.append(0.5 * plates.mean(-1))
        cfl = torch.maximum(cfl, physics.cfl(p, state))
    seconds = time.perf_counter() - start
    series = torch.stack(samples, 1)  # [seeds, average]
    means = series.mean(1)
    mid = flow.v[:, 1:-1, 1 + physics.ny // 2]
    cells_count = ((mid * mid.roll(1, 1)) < 0).sum(1)
    return {
        "level": name,
        "ra": level["ra"],
        "heater_cells": cells,
        "nx": physics.nx,
        "ny": physics.ny,
        "dt": p.dt,
        "seeds": seeds,
        "average": average,
        "nusselt": float(means.mean()),
        "median": float(series.flatten().median()),
        "seed_nusselt": means.tolist(),
        "seed_spread": series.std(1).tolist(),
        "wall_nusselt": float(torch.stack(walls, 1).mean()),
        "scaling": scaling(level["ra"]),
        "cfl": float(cfl.max()),
        "convection_cells": cells_count.tolist(),
        "seconds": seconds,
    }


def table(rows: list[dict]) -> str:
    lines = [
        "| level | Ra | grid | dt | Nu: IQM of the seeds | their mean | FluidGym | IQM against it | Nu at the plates | "
        "0.138 Ra^0.285 | seeds | each seed's Nu (convection cells) | seeds in two pairs of rolls: their Nu | "
        "largest CFL |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    from beacon_torch.envs.rbc2d import FLUIDGYM_NUSSELT
    from beacon_torch.training.report import iqm

    for r in rows:
        each = ", ".join(f"{nu:.2f} ({c})" for nu, c in zip(r["seed_nusselt"], r["convection_cells"], strict=True))
        theirs = FLUIDGYM_NUSSELT[r["level"]]
        ours = iqm(r["seed_nusselt"])
        # a flow in two pairs of rolls against the same state on another grid
        paired = [nu for nu, c in zip(r["seed_nusselt"], r["convection_cells"], strict=True) if c == 4]
        pairs = f"{sum(paired) / len(paired):.3f} ({len(paired)})" if paired else "none"
        lines.append(
            f"| {r['level']} | {r['ra']:.0e} | {r['nx']} x {r['ny']} | {r['dt']:g} | {ours:.3f} | "
            f"{r['nusselt']:.3f} | {theirs:.3f} | {100 * (ours / theirs - 1.0):+.1f} % | {r['wall_nusselt']:.3f} | "
            f"{r['scaling']:.2f} | {len(r['seed_nusselt'])} | {each} | {pairs} | {r['cfl']:.2f} |"
        )
    return "\n".join(lines)


def latest_rows(records: list[Path], received) -> list[dict]:
    """The newest measurement of each level and grid over ``records`` (oldest first):
    the refined grids are run apart from the env's, each record keeps what it ran."""
    found = {}
    for record in records:
        for row in received.json_file(record, "an RBC2D validation record")["rows"]:
            found[row["level"], row["heater_cells"]] = row
    order = {name: k for k, name in enumerate(rbc2d.LEVELS)}
    return [found[key] for key in sorted(found, key=lambda key: (order[key[0]], key[1]))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--levels", nargs="+", default=list(rbc2d.LEVELS))
    parser.add_argument("--cells", nargs="+", type=int, default=list(GRIDS))
    parser.add_argument("--average", type=int, default=100, help="time units averaged after the development")
    parser.add_argument("--seeds", type=int, default=10, help="initial domains per level (seeds 300, 301, ...)")
    parser.add_argument("--no-compile", action="store_true")
    parser.add_argument("--out", type=Path, default=RECORDS)
    parser.add_argument("--page", type=Path, default=ROOT / "docs" / "envs" / "rbc2d.md")
    parser.add_argument("--page-only", action="store_true", help="write the records' table, compute nothing")
    args = parser.parse_args()
    from beacon_torch import received
    from beacon_torch.files import save_rows
    from beacon_torch.training.report import write_block

    torch.set_num_threads(1)
    if not args.page_only:
        rows, record = [], None
        # every level on the env's grid first, then the refined grids
        for cells in args.cells:
            for name in args.levels:
                seeds = [FIRST_SEED + k for k in range(args.seeds)]
                rows.append(measure(name, cells, seeds, args.average, compile=not args.no_compile))
                print(table(rows[-1:]).splitlines()[-1], f"({rows[-1]['seconds']:.0f} s)", flush=True)
                # a record after each measurement: a run stopped midway keeps what it measured
                previous, record = record, save_rows(rows, args.out, "nusselt")
                if previous is not None:
                    previous.unlink()
        print("recorded:", record)
    rows = latest_rows(sorted(args.out.glob("nusselt-*.json")), received)
    print(table(rows))
    if args.page.exists():
        print(write_block(args.page, BEGIN, END, table(rows)))


if __name__ == "__main__":
    main()
