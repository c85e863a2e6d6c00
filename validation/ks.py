"""ks-v0's solver against the published facts of the L = 22 Kuramoto-Sivashinsky flow
(Cvitanovic, Davidchack & Siminos 2010), in float64, and the scheme's convergence.

    .venv/bin/python validation/ks.py [--out DIR] [--page docs/envs/ks.md] [--quick]

Records, as a new dated ``ks_validation-DATE.json`` in ``validation/results/ks/``:

- the equilibria E1, E2, E3 that the env finds by Newton's method: their energy and
  leading stability eigenvalues (of the discrete equations' Jacobian) beside the
  published ones;
- the leading Lyapunov exponent of the uncontrolled flow at the env's time step: a
  tangent vector carried by finite differences (1e-7) and renormalised every step, along
  256 trajectories from the env's start bank, 100 time units dropped, then averaged over
  1,000 (``--quick``: 64 trajectories, 200);
- the time step's order: the field after 2 time units from 8 starts, at dt = 0.1 down to
  0.00625, against dt = 0.05 / 128;
- the grid's convergence: the equilibria's energies with 20 to 128 points (at 16, Newton from the E3 guess finds E2).

Then writes the table of the newest record on the env's page.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "validation" / "results" / "ks"
BEGIN, END = "<!-- validation: validation/ks.py -->", "<!-- end of the validation -->"
L = 22.0
N = 64


def equilibria() -> list[dict]:
    from beacon_torch.envs.ks import PUBLISHED_EIGENVALUES, PUBLISHED_ENERGY, TARGETS, equilibrium, jacobian

    rows = []
    for target in TARGETS:
        u = equilibrium(target, L, N)
        values = np.linalg.eigvals(jacobian(u, L))
        values = values[np.argsort(-values.real)]
        found = []
        for published in PUBLISHED_EIGENVALUES[target]:
            nearest = values[np.argmin(np.abs(values - published))]
            found.append([nearest.real, abs(nearest.imag), published.real, abs(published.imag)])
        rows.append(
            dict(
                kind="equilibrium",
                target=target,
                energy=0.5 * float((u * u).mean()),
                published_energy=PUBLISHED_ENERGY[target],
                eigenvalues=found,  # [re, |im|, published re, published |im|] per published value
                leading=[[float(v.real), float(v.imag)] for v in values[:6]],
            )
        )
    return rows


def lyapunov(members: int, horizon: float, transient: float = 100.0, eps: float = 1e-7) -> dict:
    from beacon_torch.envs.ks import DT, PUBLISHED_LYAPUNOV, attractor_bank, ks_step, stage_matrices

    weights = torch.as_tensor(stage_matrices(L, N, 0.4))
    bank = attractor_bank(L, N, 0.4).u
    u = bank[:: len(bank) // members][:members].clone()
    v = torch.randn(u.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    v = v - v.mean(-1, keepdim=True)  # the mean is conserved: no growth there
    v = v / v.norm(dim=-1, keepdim=True)
    zero = torch.zeros(len(u), 4, dtype=torch.float64)
    growth = torch.zeros(len(u), dtype=torch.float64)
    dropped, steps = round(transient / DT), round(horizon / DT)
    for i in range(dropped + steps):
        u, ahead = ks_step(u, zero, weights), ks_step(u + eps * v, zero, weights)
        d = (ahead - u) / eps
        norm = d.norm(dim=-1)
        v = d / norm[:, None]
        if i >= dropped:
            growth += torch.log(norm)
    exponents = growth / (steps * DT)
    return dict(
        kind="lyapunov",
        dt=DT,
        members=len(u),
        time=horizon,
        exponent=float(exponents.mean()),
        stderr=float(exponents.std() / len(u) ** 0.5),
        published=PUBLISHED_LYAPUNOV,
    )


def order(horizon: float = 2.0) -> dict:
    from beacon_torch.envs.ks import DT, attractor_bank, ks_step, stage_matrices

    start = attractor_bank(L, N, 0.4).u[::128][:8]
    zero = torch.zeros(len(start), 4, dtype=torch.float64)

    def run(dt):
        weights = torch.as_tensor(stage_matrices(L, N, 0.4, dt))
        u = start
        for _ in range(round(horizon / dt)):
            u = ks_step(u, zero, weights)
        return u

    reference = run(DT / 128)
    steps = [0.1, 0.05, 0.025, 0.0125, 0.00625]
    errors = [float((run(dt) - reference).abs().max()) for dt in steps]
    orders = [float(np.log2(a / b)) for a, b in zip(errors[:-1], errors[1:], strict=True)]
    return dict(kind="order", time=horizon, dt=steps, errors=errors, orders=orders)


def resolution() -> dict:
    from beacon_torch.envs.ks import TARGETS, equilibrium

    points = [20, 24, 32, 48, 64, 128]
    energies = {t: [0.5 * float((u * u).mean()) for u in (equilibrium(t, L, n) for n in points)] for t in TARGETS}
    return dict(kind="resolution", points=points, energies=energies)


def table(rows: list[dict]) -> str:
    def rel(a, b):
        return f"{100 * (a - b) / abs(b):+.2f} %"

    lines = [
        "| quantity | ks-v0 (float64) | published | difference |",
        "|---|---|---|---|",
    ]
    for r in rows:
        if r["kind"] == "equilibrium":
            t, energy, published = r["target"], r["energy"], r["published_energy"]
            lines.append(f"| {t} energy | {energy:.5f} | {published} | {rel(energy, published)} |")
            for re, im, pre, pim in r["eigenvalues"]:
                ours = f"{re:.5f} ± {im:.5f} i" if pim else f"{re:.5f}"
                theirs = f"{pre} ± {pim} i" if pim else f"{pre}"
                diff = f"{rel(re, pre)} (real), {rel(im, pim)} (imaginary)" if pim else rel(re, pre)
                lines.append(f"| {t} eigenvalue | {ours} | {theirs} | {diff} |")
        elif r["kind"] == "lyapunov":
            lines.append(
                f"| leading Lyapunov exponent ({r['members']} trajectories x {r['time']:g} time units, dt = {r['dt']}) "
                f"| {r['exponent']:.4f} ± {r['stderr']:.4f} | {r['published']} | {rel(r['exponent'], r['published'])} |"
            )
    by_kind = {r["kind"]: r for r in rows}
    o, g = by_kind["order"], by_kind["resolution"]
    lines += [
        "",
        f"The time step's convergence (largest error of the field after {o['time']:g} time units from 8 "
        "starts on the attractor, against dt = 0.05 / 128):",
        "",
        "| dt | " + " | ".join(f"{dt:g}" for dt in o["dt"]) + " |",
        "|---|" + "---|" * len(o["dt"]),
        "| error | " + " | ".join(f"{e:.2e}" for e in o["errors"]) + " |",
        "| order | - | " + " | ".join(f"{x:.2f}" for x in o["orders"]) + " |",
        "",
        f"The grid's convergence (the equilibria's energies, Newton's method on each grid, against "
        f"{g['points'][-1]} points'):",
        "",
        "| points | " + " | ".join(str(n) for n in g["points"]) + " |",
        "|---|" + "---|" * len(g["points"]),
    ]
    for target, energies in g["energies"].items():
        gaps = [f"{abs(e - energies[-1]):.1e}" for e in energies[:-1]]
        lines.append(f"| {target} | " + " | ".join(gaps) + f" | {energies[-1]:.10f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=RECORDS)
    parser.add_argument("--page", type=Path, default=ROOT / "docs" / "envs" / "ks.md")
    parser.add_argument("--quick", action="store_true", help="64 trajectories over 200 time units for the exponent")
    parser.add_argument("--page-only", action="store_true", help="write the newest record's table, compute nothing")
    args = parser.parse_args()
    from beacon_torch import received
    from beacon_torch.files import save_rows
    from beacon_torch.training.report import write_block

    torch.set_num_threads(1)
    if not args.page_only:
        start = time.perf_counter()
        rows = equilibria() + [lyapunov(*((64, 200.0) if args.quick else (256, 1000.0))), order(), resolution()]
        print(f"recorded in {time.perf_counter() - start:.0f} s:", save_rows(rows, args.out, "ks_validation"))
    newest = sorted(args.out.glob("ks_validation-*.json"))[-1]
    rows = received.json_file(newest, "a ks validation record")["rows"]
    print(table(rows))
    print(write_block(args.page, BEGIN, END, table(rows)))


if __name__ == "__main__":
    main()
