"""Shipped policies' episodes from the env's own start, side by side, stretch by stretch:
the summed reward of each stretch of actions and the mean size of the actions there, so
that where one policy gains on another in an episode can be read, not guessed.

    .venv/bin/python experiments/policy_trace.py --env sloshing-v0 --algos ppo grad

Each policy is the one a user loads (``beacon_torch.pretrained.load``), played
deterministically on one member of the env (float32, its default parameters). Writes a
new ``trace-ENV-DATE-TIME.json`` to ``--out`` and prints the table.
"""

from __future__ import annotations

import argparse
from pathlib import Path

HERE = Path(__file__).resolve()


def episode(env_id: str, algo: str):
    """The rewards and the actions of one deterministic episode of the shipped
    ``algo`` policy from the env's own start: ``[actions]`` and ``[actions, dims]``."""
    import torch

    from beacon_torch import make, pretrained

    policy = pretrained.load(algo, env_id)
    env = make(env_id, 1)
    td = env.reset()
    rewards, actions = [], []
    with torch.no_grad():
        for _ in range(env.episode_length):
            td = policy(td)
            actions.append(td["action"][0].clone())
            td = env.step(td)
            rewards.append(float(td["next", "reward"].sum()))
            td = td["next"]
    return torch.tensor(rewards, dtype=torch.float64), torch.stack(actions).double()


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", required=True)
    parser.add_argument("--algos", nargs="+", default=["ppo", "grad"])
    parser.add_argument("--stretch", type=int, default=20, help="actions a row of the table")
    parser.add_argument("--out", type=Path, default=HERE.parent / "results" / "policy_trace")
    args = parser.parse_args(argv)
    from beacon_torch.files import save_rows

    traces = {algo: episode(args.env, algo) for algo in args.algos}
    length = min(len(rewards) for rewards, _ in traces.values())
    rows = []
    for first in range(0, length, args.stretch):
        part = slice(first, min(first + args.stretch, length))
        row = {"env": args.env, "first_action": first, "actions": part.stop - first}
        for algo, (rewards, actions) in traces.items():
            row[f"{algo}_reward"] = float(rewards[part].sum())
            row[f"{algo}_action_size"] = float(actions[part].abs().mean())
        rows.append(row)
    totals = {algo: float(rewards.sum()) for algo, (rewards, _) in traces.items()}
    rows.append({"env": args.env, "totals": totals})
    print(f"episode totals: {', '.join(f'{a} {t:.4f}' for a, t in totals.items())}")
    print("| actions | " + " | ".join(f"{a}: reward | {a}: mean action size" for a in args.algos) + " |")
    print("|---|" + "---|---|" * len(args.algos))
    for row in rows[:-1]:
        cells = " | ".join(f"{row[f'{a}_reward']:.4f} | {row[f'{a}_action_size']:.4f}" for a in args.algos)
        print(f"| {row['first_action']} to {row['first_action'] + row['actions'] - 1} | {cells} |")
    written = save_rows(rows, args.out, f"trace-{args.env}")
    print(f"written to {written}")
    return written


if __name__ == "__main__":
    main()
