"""Transitions per second through Stable-Baselines3's vector-env interface: the
batched :class:`beacon_torch.sb3.BeaconVecEnv` against SB3's ``DummyVecEnv`` over the
same number of single gymnasium envs.

    .venv/bin/python benchmarks/sb3_throughput.py [--envs ...] [--copies 16 64]

Random actions (fixed seed) through ``VecEnv.step`` with its auto-resets, as SB3's
algorithms call it. Prints a markdown table and writes a new ``sb3_throughput-DATE-TIME.json`` to
``--out``; the numbers in benchmarks/RESULTS.md come from this script, run on an
otherwise idle machine.
"""

from __future__ import annotations

import argparse
import time

import gymnasium
import numpy as np
import torch
from stable_baselines3.common.vec_env import DummyVecEnv

import beacon_torch  # noqa: F401  (registers the gymnasium ids)
from beacon_torch.files import machine, save_rows
from beacon_torch.registry import base_envs, env_spec
from beacon_torch.sb3 import BeaconVecEnv

ENVS = base_envs()  # the seven benchmark envs


def rate(venv, seconds: float) -> float:
    """Transitions per second of ``venv`` over about ``seconds`` (after two warm-up
    steps), at least two steps."""
    venv.reset()
    venv.action_space.seed(0)
    actions = [np.stack([venv.action_space.sample() for _ in range(venv.num_envs)]) for _ in range(8)]
    for i in range(2):
        venv.step(actions[i])
    start, n = time.perf_counter(), 0
    while n < 2 or time.perf_counter() - start < seconds:
        venv.step(actions[n % 8])
        n += 1
    return n * venv.num_envs / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", default=ENVS)
    parser.add_argument("--copies", nargs="+", type=int, default=[16, 64])
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default="runs/sb3_throughput")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"# {machine()}")
    print("| env | copies | BeaconVecEnv /s | DummyVecEnv /s | ratio |")
    print("|---|---|---|---|---|")
    rows = []
    for env_id in args.envs:
        seconds = args.seconds * (4 if env_spec(env_id).card.costly else 1)
        for copies in args.copies:
            batched = rate(BeaconVecEnv(env_id, copies, seed=0), seconds)
            dummy = rate(
                DummyVecEnv([lambda name=env_id: gymnasium.make(f"beacon/{name}") for _ in range(copies)]), seconds
            )
            rows.append({"env": env_id, "copies": copies, "batched": batched, "dummy": dummy, "ratio": batched / dummy})
            print(f"| {env_id} | {copies} | {batched:,.1f} | {dummy:,.1f} | {batched / dummy:.1f}x |", flush=True)
    print("results:", save_rows(rows, args.out, "sb3_throughput"))


if __name__ == "__main__":
    main()
