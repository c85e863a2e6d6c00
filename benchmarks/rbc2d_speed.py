"""FluidGym's RBC2D levels: transitions per second at 1, 16 and 64 members, beside
FluidGym's seconds per environment step on an A100.

    .venv/bin/python benchmarks/rbc2d_speed.py [--batches 1 16 64] [--steps 2] [--rounds 3] [--threads 1]

Each level's single-agent env compiled, float32, ``--threads`` threads (one: a core of
the two), the levels timed in alternation ``--rounds`` times, each time over
``--steps`` actions of zero after the compilation settled; the process's CPU time per
member-step, the median over the rounds (and its wall time). FluidGym's figures are
the A100 seconds per step during training its paper gives (1.27 / 2.23 / 2.26): one
simulation per process, a GPU each. Writes ``speed-DATE.json`` in
``benchmarks/results/rbc2d/`` and prints the table.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "benchmarks" / "results" / "rbc2d"
FLUIDGYM_SECONDS = {"easy": 1.27, "medium": 2.23, "hard": 2.26}  # per step, one A100, during training


def timed(env, steps: int) -> tuple[float, float]:
    """Wall and CPU seconds per member-step over ``steps`` actions of zero."""
    td = env.reset()
    action = env.full_action_spec.zero()
    members = env.batch_size.numel()
    wall, cpu = time.perf_counter(), time.process_time()
    for _ in range(steps):
        td = env.step(td.update(action))["next"]
    return (time.perf_counter() - wall) / (steps * members), (time.process_time() - cpu) / (steps * members)


def table(rows: list[dict]) -> str:
    lines = [
        "| level | members | CPU s per member-step | transitions/s of a core | FluidGym: A100 s per step | "
        "per step against FluidGym's |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['level']} | {r['batch']} | {r['cpu']:.4f} | {1.0 / r['cpu']:.1f} | {r['fluidgym']:.2f} | "
            f"{r['fluidgym'] / r['cpu']:.0f} x fewer seconds |"
        )
    return "\n".join(lines)


def main() -> None:
    import beacon_torch
    from beacon_torch.files import save_rows

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 16, 64])
    parser.add_argument("--steps", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=RECORDS)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    for batch in args.batches:
        envs = {level: beacon_torch.make(f"rbc2d-{level}-v0", batch, compile=True) for level in FLUIDGYM_SECONDS}
        for env in envs.values():
            timed(env, 2)  # compiles
        samples = {level: [] for level in envs}
        for _ in range(args.rounds):
            for level, env in envs.items():
                samples[level].append(timed(env, args.steps))
        for level, values in samples.items():
            rows.append(
                {
                    "level": level,
                    "batch": batch,
                    "wall": statistics.median(w for w, _ in values),
                    "cpu": statistics.median(c for _, c in values),
                    "threads": args.threads,
                    "fluidgym": FLUIDGYM_SECONDS[level],
                }
            )
            print(table(rows[-1:]).splitlines()[-1], flush=True)
    print("recorded:", save_rows(rows, args.out, "speed"))
    print(table(rows))


if __name__ == "__main__":
    main()
