"""Replay the published code's recorded rollouts through our envs, whole episodes.

    .venv/bin/python validation/reference_rollouts.py [ENV_ID ...] [--out FILE]

For each env with a recorded rollout (beacon_torch/data/reference-rollouts.json: seeded
open-loop actions, float64, the published start states), steps our env through the same
actions (batch 1, float64) and prints the largest relative difference of the running
return, the first and last observations' largest differences and the wall time; the
cavities run with both pressure solvers (the default direct solve and the published
Jacobi iterations). The tests replay 30-action prefixes; this runs everything (about
15 minutes on one core, most of it mixing with the Jacobi solve). ``--out`` writes the
markdown table.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import fields

import torch

from beacon_torch import reference
from beacon_torch.files import create_file, refuse_existing
from beacon_torch.registry import env_spec


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("env_ids", nargs="*", default=reference.env_ids(), choices=reference.env_ids())
    parser.add_argument("--out", help="write the markdown table here")
    args = parser.parse_args()
    if args.out:
        refuse_existing([args.out], "give another --out")  # before the rollouts, not after
    torch.set_num_threads(1)
    rows = [
        "| env | solver | actions | return | published | running return, largest rel. difference | "
        "first obs. | last obs. | wall time |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for env_id in args.env_ids:
        # the envs with a choice of Poisson solver replay with each
        solvers = (
            ("direct", "jacobi") if "solver" in {f.name for f in fields(env_spec(env_id).physics.Params)} else (None,)
        )
        for solver in solvers:
            start = time.perf_counter()
            agreement = reference.replay(env_id, **({"solver": solver} if solver else {}))
            wall = time.perf_counter() - start
            print(f"{agreement.summary()} [{solver or '-'}; {wall:.0f} s]", flush=True)
            last = agreement.last_observation_error
            rows.append(
                f"| {env_id} | {solver or '-'} | {agreement.steps} | {agreement.rewards.sum():.10g} | "
                f"{agreement.published.sum():.10g} | {agreement.running_error.max():.1e} | "
                f"{agreement.first_observation_error:.1e} | {last:.1e} | {wall:.0f} s |"
            )
    table = "\n".join(rows) + "\n"
    print(table)
    if args.out:
        create_file(args.out, lambda tmp: tmp.write_text(table), "give another --out")


if __name__ == "__main__":
    main()
