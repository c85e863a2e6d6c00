"""rayleigh-separable-v0's channel (Vignon et al. 2023's case) uncontrolled, in float64:
its Nusselt number against the authors', and the grid's convergence.

    .venv/bin/python validation/rayleigh_channel.py [--out DIR] [--page FILE]

For each resolution (24, 32 and 40 cells per unit length; the env's is 32) the flow is
developed from rest as the env's start is (400 time units, no control) and measured:

- the Nusselt number of the whole flow (the env's diagnostic, ``column_nusselt``) and
  the one of the bottom wall's temperature gradient;
- Vignon et al.'s own estimate, which their code computes from an 8 x 32 probe grid and
  subtracts from the reward (2.6726): the temperature and vertical velocity read at
  their probes (every 8th of 64 Chebyshev-Gauss points across the channel, in numpy's
  order, top first; every 3rd of 96 Fourier points along it), bilinearly interpolated
  from our cells, then (<v T> - kappa <dT/dj>) / (kappa dT / H) with the probes'
  vertical gradient taken per row index (numpy's ``gradient``), as their code does;
- the number of convection cells (sign changes of the vertical velocity at mid-height).

Records a dated ``channel_validation-DATE.json`` in ``validation/results/rayleigh-separable/``
and writes the table of the newest record on the env's page.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "validation" / "results" / "rayleigh-separable"
BEGIN, END = "<!-- validation: validation/rayleigh_channel.py -->", "<!-- end of the validation -->"
VIGNON_NUSSELT = 2.6726  # the uncontrolled value the authors' reward subtracts
RESOLUTIONS = (24, 32, 40)


def probe_nusselt(theta: np.ndarray, v: np.ndarray, L: float, H: float, kappa: float) -> float:
    """Vignon et al.'s probe estimate on our cell fields ``theta``, ``v`` (cell centres,
    ``[nx, ny]``; their temperature is ours plus 1.5)."""
    from scipy.interpolate import RegularGridInterpolator

    nx, ny = theta.shape
    dx, dy = L / nx, H / ny
    x = np.concatenate(([-0.5 * dx], (np.arange(nx) + 0.5) * dx, [L + 0.5 * dx]))
    y = np.concatenate(([-1.0], (np.arange(ny) + 0.5) * dy - 1.0, [1.0]))

    def field(f, bottom, top):
        f = np.concatenate((f[-1:], f, f[:1]))  # periodic in x
        walls = lambda value: np.full((nx + 2, 1), value)
        return RegularGridInterpolator((x, y), np.concatenate((walls(bottom), f, walls(top)), 1))

    temperature, velocity = field(theta + 1.5, 2.0, 1.0), field(v, 0.0, 0.0)
    rows = np.cos(np.pi * (2 * np.arange(64) + 1) / 128)[::8]  # numpy's chebgauss order
    columns = (2 * np.pi * np.arange(96) / 96)[::3] * L / (2 * np.pi)
    points = np.stack(np.meshgrid(columns, rows, indexing="ij"), -1).reshape(-1, 2)
    t = temperature(points).reshape(len(columns), len(rows)).T  # [rows, columns]
    w = velocity(points).reshape(len(columns), len(rows)).T
    gradient = np.mean(np.gradient(np.mean(t, axis=1), axis=0))
    return float((np.mean(w * t) - kappa * gradient) / (kappa * 1.0 / H))


def measure(resolution: int) -> dict:
    from beacon_torch.envs.rayleigh import VIGNON, RayleighSeparableParams, developed_convection

    p = RayleighSeparableParams(**VIGNON, resolution=resolution)
    start = time.perf_counter()
    flow = developed_convection(p)
    seconds = time.perf_counter() - start
    return {"resolution": resolution, "seconds": seconds, **nusselts(flow, VIGNON)}


def nusselts(flow, case: dict) -> dict:
    L, H, kappa = case["L"], case["H"], 1.0 / (case["pr"] * 1e4) ** 0.5
    theta = flow.theta[1:-1, 1:-1].numpy()
    v = 0.5 * (flow.v[1:-1, 1:-1] + flow.v[1:-1, 2:]).numpy()
    nx, ny = theta.shape
    bottom = 0.5 * (flow.theta[1:-1, 0] + flow.theta[1:-1, 1]).numpy()
    top = 0.5 * (flow.theta[1:-1, -1] + flow.theta[1:-1, -2]).numpy()
    whole = float(np.mean(H / kappa * (v * theta).mean(1) + bottom - top))
    wall = float(np.mean((0.5 - theta[:, 0]) / (0.5 * H / ny) * H))
    mid = v[:, ny // 2]
    cells = int(((mid * np.roll(mid, 1)) < 0).sum())
    probes = probe_nusselt(theta, v, L, H, kappa)
    return {
        "nx": nx,
        "ny": ny,
        "nusselt": whole,
        "wall_nusselt": wall,
        "probe_nusselt": probes,
        "probe_error": probes / VIGNON_NUSSELT - 1.0,
        "cells": cells,
    }


def table(rows: list[dict]) -> str:
    lines = [
        "| cells per unit | grid | Nusselt (whole flow) | Nusselt (bottom wall) | Vignon's probe estimate | "
        "against their 2.6726 | convection cells |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['resolution']} | {r['nx']} x {r['ny']} | {r['nusselt']:.3f} | {r['wall_nusselt']:.3f} | "
            f"{r['probe_nusselt']:.4f} | {100 * r['probe_error']:+.1f} % | {r['cells']} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=RECORDS)
    parser.add_argument("--page", type=Path, default=ROOT / "docs" / "envs" / "rayleigh-separable.md")
    parser.add_argument("--page-only", action="store_true", help="write the newest record's table, compute nothing")
    args = parser.parse_args()
    from beacon_torch import received
    from beacon_torch.files import save_rows
    from beacon_torch.training.report import write_block

    torch.set_num_threads(1)
    if not args.page_only:
        rows = [measure(r) for r in RESOLUTIONS]
        print("recorded:", save_rows(rows, args.out, "channel_validation"))
    newest = sorted(args.out.glob("channel_validation-*.json"))[-1]
    rows = received.json_file(newest, "a channel validation record")["rows"]
    print(table(rows))
    print(write_block(args.page, BEGIN, END, table(rows)))


if __name__ == "__main__":
    main()
