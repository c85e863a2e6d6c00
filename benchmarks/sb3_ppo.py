"""Stable-Baselines3's PPO on burgers-v0: the batched vector env against SB3's own
DummyVecEnv of single gymnasium envs, the same training on each.

    .venv/bin/python benchmarks/sb3_ppo.py --vec batched --out runs/sb3/batched
    .venv/bin/python benchmarks/sb3_ppo.py --vec dummy --out runs/sb3/dummy

Both train SB3's PPO, unmodified, with the paper's PPO settings where SB3 has them
(4000 transitions per rollout over 16 copies, 2 minibatches, 32 epochs, learning rate
5e-4, gamma 0.99, GAE 0.99, clip 0.2, entropy 0.01, 64-wide tanh networks) and
observation normalisation (``VecNormalize``, rewards left raw) for the paper's
500 k transitions. Writes ``curve.csv`` (transitions, mean return of the episodes that
ended since the last line, wall seconds) and ``summary.json`` (the mean of the last
tenth's training episodes, the paper's quantity, and the wall time) to ``--out``. The
numbers in benchmarks/RESULTS.md come from this script.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import gymnasium
import numpy as np
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor, VecNormalize

import beacon_torch  # noqa: F401  (registers the gymnasium ids)
from beacon_torch.files import create_file, refuse_existing
from beacon_torch.sb3 import BeaconVecEnv


class Curve(BaseCallback):
    """Every ended episode's return and length, with the transitions and wall time."""

    def __init__(self) -> None:
        super().__init__()
        self.rows: list[tuple[int, float, float]] = []
        self.start = time.perf_counter()

    def _on_step(self) -> bool:
        for info in self.locals["infos"]:
            if "episode" in info:
                self.rows.append((self.num_timesteps, float(info["episode"]["r"]), time.perf_counter() - self.start))
        return True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--vec", choices=["batched", "dummy"], required=True)
    parser.add_argument("--env", default="burgers-v0")
    parser.add_argument("--copies", type=int, default=16)
    parser.add_argument("--frames", type=int, default=500_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    out = Path(args.out)
    refuse_existing([out / "curve.csv", out / "summary.json"], "give a new --out")  # before training
    torch.set_num_threads(args.threads)
    if args.vec == "batched":
        venv = BeaconVecEnv(args.env, args.copies, seed=args.seed)
    else:
        venv = DummyVecEnv([lambda: gymnasium.make(f"beacon/{args.env}") for _ in range(args.copies)])
        venv.seed(args.seed)
    venv = VecNormalize(VecMonitor(venv), norm_reward=False)
    rollout = 4000 // args.copies
    model = PPO(
        "MlpPolicy",
        venv,
        n_steps=rollout,
        batch_size=rollout * args.copies // 2,
        n_epochs=32,
        learning_rate=5e-4,
        gamma=0.99,
        gae_lambda=0.99,
        clip_range=0.2,
        ent_coef=0.01,
        policy_kwargs=dict(net_arch=dict(pi=[64, 64], vf=[64, 64])),
        seed=args.seed,
        device="cpu",
    )
    curve = Curve()
    start = time.perf_counter()
    model.learn(args.frames, callback=curve)
    wall = time.perf_counter() - start
    out.mkdir(parents=True, exist_ok=True)
    lines = ["transitions,return,wall_s\n", *(f"{t},{r},{w:.1f}\n" for t, r, w in curve.rows)]
    create_file(out / "curve.csv", lambda tmp: tmp.write_text("".join(lines)))
    returns = np.array([r for _, r, _ in curve.rows])
    tail = returns[-max(1, len(returns) // 10) :]
    summary = {
        "env": args.env,
        "vec": args.vec,
        "copies": args.copies,
        "transitions": int(model.num_timesteps),
        "episodes": len(returns),
        "last_tenth_mean": float(tail.mean()),
        "wall_s": wall,
        "threads": args.threads,
        "seed": args.seed,
    }
    create_file(out / "summary.json", lambda tmp: tmp.write_text(json.dumps(summary, indent=1)))
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
