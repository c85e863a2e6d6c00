"""How bad can a completed episode get, and what does a blow-up score?

    .venv/bin/python validation/blowups.py [ENV_ID ...] [--batch 256] [--seed 0]

Runs whole episodes (float32, the env's defaults) of a batch split evenly among
policies that push hardest on the physics: uniformly random actions, bang-bang (a random
corner of the box each step), the extreme constants and square waves of several periods
(resonant forcing). Prints, per policy, how many members completed their episode and the
worst completed score, how many left the physical bounds and the best score among those.
An env's blow-up penalty must lie below every completed score (docs/envs).
"""

from __future__ import annotations

import argparse
import time

import torch

import beacon_torch
from beacon_torch import episodes

PERIODS = (4, 8, 16, 32, 64)  # square waves, in actions


def policies(env, seed: int):
    g = torch.Generator(device=env.device).manual_seed(seed)
    shape = (env.num_envs, *env.action_shape)
    ones = torch.ones(shape, dtype=env.dtype, device=env.device)
    out = {
        "random": lambda step: env.random_action(g),
        "bang-bang": lambda step: torch.where(torch.rand(shape, generator=g, device=env.device) < 0.5, -ones, ones),
        "constant +1": lambda step: ones,
        "constant -1": lambda step: -ones,
    }
    for period in PERIODS:
        out[f"square {period}"] = lambda step, period=period: ones * (1.0 if (step // (period // 2)) % 2 == 0 else -1.0)
    return out


def measure(env_id: str, batch: int, seed: int) -> list[str]:
    env = beacon_torch.make(env_id, batch, seed=seed)
    if env.discrete:
        raise SystemExit(f"{env_id}: a discrete env has no box to push against")
    named = policies(env, seed)
    groups = torch.arange(batch) % len(named)  # member m follows policy m mod n

    def policy(td):
        step = int(env.step_count.max())
        actions = torch.stack([fn(step) for fn in named.values()])  # [policies, batch, ...]
        td.set(env.action_key, actions[groups, torch.arange(batch)])
        return td

    start = time.perf_counter()
    rollout = episodes.episode(env, policy)
    scores = episodes.scores(rollout)
    done = rollout["next", "done"][..., 0]
    terminated = (rollout["next", "terminated"][..., 0] & (done.cumsum(-1) == done.to(torch.int64))).any(-1)
    lines = [
        f"{env_id} (batch {batch}, seed {seed}, blow-up reward {env.physics.blowup_reward}, "
        f"{time.perf_counter() - start:.0f} s)"
    ]
    for k, name in enumerate(named):
        mine = groups == k
        completed, blown = scores[mine & ~terminated], scores[mine & terminated]
        worst = f"{completed.min().item():.3f}" if completed.numel() else "-"
        best = f"{blown.max().item():.3f}" if blown.numel() else "-"
        lines.append(
            f"  {name:12s} completed {completed.numel():3d} (worst {worst:>9s}), blown up "
            f"{blown.numel():3d} (best {best:>9s})"
        )
    completed = scores[~terminated]
    lines.append(f"  all          worst completed {completed.min().item():.3f}, blow-ups {int(terminated.sum())}")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("env_ids", nargs="*", default=["sloshing-v0", "shkadov-v0"])
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    for env_id in args.env_ids:
        print("\n".join(measure(env_id, args.batch, args.seed)), flush=True)


if __name__ == "__main__":
    main()
