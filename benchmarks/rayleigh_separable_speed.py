"""rayleigh-separable-v0 against rayleigh-v0 on the same channel (Vignon et al.'s case),
side by side in one run: does the multi-agent layout cost anything per member-step?

    .venv/bin/python benchmarks/rayleigh_separable_speed.py [--batches 1 16 32] [--steps 4] [--rounds 5]

Both envs compiled, float32, 2 threads, the same grid (200 x 64, 150 substeps an
action); the two are timed in alternation, ``--rounds`` times, each time over
``--steps`` actions after a warm-up; wall time and the process's CPU time per
member-step, the median over the rounds. Writes ``speed-DATE.json`` in
``benchmarks/results/rayleigh-separable/`` and prints the table.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "benchmarks" / "results" / "rayleigh-separable"


def timed(env, steps: int) -> tuple[float, float]:
    """Wall and CPU seconds per member-step over ``steps`` actions of zero."""
    td = env.reset()
    action = env.full_action_spec.zero()
    members = env.batch_size.numel()
    wall, cpu = time.perf_counter(), time.process_time()
    for _ in range(steps):
        td = env.step(td.update(action))
        td = td["next"]
    return (time.perf_counter() - wall) / (steps * members), (time.process_time() - cpu) / (steps * members)


def main() -> None:
    import beacon_torch
    from beacon_torch.envs.rayleigh import VIGNON
    from beacon_torch.files import save_rows

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 16, 32])
    parser.add_argument("--steps", type=int, default=4)
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(2)
    rows = []
    for batch in args.batches:
        envs = {
            "rayleigh-separable-v0": beacon_torch.make("rayleigh-separable-v0", batch, compile=True),
            "rayleigh-v0": beacon_torch.make("rayleigh-v0", batch, compile=True, **VIGNON, resolution=32),
        }
        for env in envs.values():
            timed(env, 2)  # compiles
        samples = {name: [] for name in envs}
        for _ in range(args.rounds):
            for name, env in envs.items():
                samples[name].append(timed(env, args.steps))
        for name, got in samples.items():
            wall = statistics.median(w for w, _ in got)
            cpu = statistics.median(c for _, c in got)
            cells = envs[name].physics.nx * envs[name].physics.ny * envs[name].physics.substeps
            rows.append({"env": name, "batch": batch, "wall_s": wall, "cpu_s": cpu, "cell_substeps": cells})
            print(f"{name} batch {batch}: {wall * 1e3:.1f} ms wall, {cpu * 1e3:.1f} ms CPU per member-step", flush=True)
    print(save_rows(rows, RECORDS, "speed"))


if __name__ == "__main__":
    main()
