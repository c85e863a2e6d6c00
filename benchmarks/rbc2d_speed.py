"""FluidGym's RBC2D levels: transitions per second at 1, 16 and 64 members, beside
FluidGym's seconds per environment step on an A100.

    .venv/bin/python benchmarks/rbc2d_speed.py [--batches 1 16 64] [--steps 2] [--repeats 3] [--threads 1]

Each level's single-agent env compiled, float32, ``--threads`` threads (one: a core of
the two), measured as ``beacon-torch bench`` measures (random actions, warmed up until a
step compiles nothing new, the median of ``--repeats`` timings of ``--steps`` actions,
``beacon_torch.bench.measure``): run it with nothing else on the machine. FluidGym's figures are
the A100 seconds per step during training its paper gives (1.27 / 2.23 / 2.26): one
simulation per process, a GPU each. Writes ``speed-DATE.json`` in
``benchmarks/results/rbc2d/`` and prints the table.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "benchmarks" / "results" / "rbc2d"
FLUIDGYM_SECONDS = {"easy": 1.27, "medium": 2.23, "hard": 2.26}  # per step, one A100, during training


def table(rows: list[dict]) -> str:
    lines = [
        "| level | members | transitions/s | s per member-step | FluidGym: A100 s per step | "
        "per step against FluidGym's | recompiles while timed |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        seconds = 1.0 / r["transitions_per_s"]
        lines.append(
            f"| {r['level']} | {r['batch']} | {r['transitions_per_s']:.1f} | {seconds:.4f} | {r['fluidgym']:.2f} | "
            f"{r['fluidgym'] / seconds:.0f} x fewer seconds | {r['recompiles']} |"
        )
    return "\n".join(lines)


def main() -> None:
    from beacon_torch.bench import measure
    from beacon_torch.files import save_rows

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 16, 64])
    parser.add_argument("--steps", type=int, default=2, help="actions a timed repeat")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=RECORDS)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    for batch in args.batches:
        for level, seconds in FLUIDGYM_SECONDS.items():
            m = measure(f"rbc2d-{level}-v0", batch, mode="compiled", steps=args.steps, repeats=args.repeats)
            rows.append(
                {
                    "level": level,
                    "batch": batch,
                    "transitions_per_s": m.transitions_per_s,
                    "step_ms": m.step_ms,
                    "compile_s": m.compile_s,
                    "recompiles": m.recompiles,
                    "threads": args.threads,
                    "fluidgym": seconds,
                }
            )
            print(table(rows[-1:]).splitlines()[-1], flush=True)
    print("recorded:", save_rows(rows, args.out, "speed"))
    print(table(rows))


if __name__ == "__main__":
    main()
