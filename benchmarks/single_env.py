"""One env at a time: the published code's single-env speed against ours at batch 1.

    .venv/bin/python benchmarks/single_env.py [--envs ...] [--out DIR]

For every env, random actions (fixed seed) through
- ``gymnasium.make("beacon/<id>")``: the lean path (``FlowEnv.step_members``, numpy in
  and out), eager and compiled;
- a batch-of-one TorchRL env's ``step`` (TensorDicts and TorchRL's step wrappers), for
  comparison;
- the step call alone (``FlowEnv._step_core`` from a frozen state: the physics, the
  action's checks and the bookkeeping; compiled, the one compiled call), the floor of
  any wrapper: what the lean step costs beyond it is the adapter's share.

Prints a markdown table and writes a new ``single_env-DATE-TIME.json`` to ``--out``. The numbers in
benchmarks/RESULTS.md come from this script, run on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import statistics
import time

import gymnasium
import numpy as np
import torch
from tensordict import TensorDict

from beacon_torch.bench import machine, save_rows
from beacon_torch.registry import base_envs, env_class

ENVS = base_envs()  # the seven benchmark envs


def rates(steps: dict, seconds: float, repeats: int) -> dict:
    """Median steps per second of each of ``steps`` (name -> function), the repeats of
    the paths alternating so that they are measured side by side, each run about
    ``seconds`` long (at least 2 steps). A warm-up of ``seconds`` per path first: it
    compiles, and lets the compiler's worker processes finish."""
    counts = {}
    for name, step in steps.items():
        start, n = time.perf_counter(), 0
        while n < 3 or time.perf_counter() - start < seconds:
            step()
            n += 1
        start, n = time.perf_counter(), 0
        while n < 2 or time.perf_counter() - start < 0.2 * seconds:
            step()
            n += 1
        counts[name] = max(2, int(seconds * n / (time.perf_counter() - start)))
    measured = {name: [] for name in steps}
    for _ in range(repeats):
        for name, step in steps.items():
            start = time.perf_counter()
            for _ in range(counts[name]):
                step()
            measured[name].append(counts[name] / (time.perf_counter() - start))
    return {name: statistics.median(r) for name, r in measured.items()}


def measure(env_id: str, compiled: bool, seconds: float, repeats: int) -> dict:
    gym_env = gymnasium.make(f"beacon/{env_id}", compile=compiled).unwrapped
    gym_env.reset(seed=0)
    gym_env.action_space.seed(0)
    actions = [gym_env.action_space.sample() for _ in range(64)]
    index = [0]

    def lean():
        _, _, terminated, truncated, _ = gym_env.step(actions[index[0] % 64])
        index[0] += 1
        if terminated or truncated:
            gym_env.reset()

    env = gym_env.env  # the batch-of-one FlowEnv behind it
    batch = [
        TensorDict({env.action_key: torch.as_tensor(np.asarray(a))[None]}, batch_size=env.batch_size)
        for a in actions[:8]
    ]

    def torchrl_step():
        td = env.step(batch[index[0] % 8])
        index[0] += 1
        if bool(td["next", "done"].any()):
            env.reset()

    # the step call alone, from a state of the episode
    frozen = {}

    def physics():
        if not frozen:
            frozen.update(
                state=env.state,
                obs=env.observation,
                action=env.check_action(batch[0][env.action_key]),
                count=env.step_count,
                noise=env.noise(),
            )
        with torch.no_grad():
            env._whole_step(frozen["state"], frozen["obs"], frozen["action"], frozen["count"], frozen["noise"], None)

    measured = rates({"gymnasium": lean, "torchrl": torchrl_step, "physics": physics}, seconds, repeats)
    return {
        "env": env_id,
        "mode": "compiled" if compiled else "eager",
        "published": env_class(env_id).published_speed,
        **measured,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", default=ENVS)
    parser.add_argument("--modes", nargs="+", default=["eager", "compiled"], choices=["eager", "compiled"])
    parser.add_argument(
        "--seconds", type=float, default=2.0, help="length of one timed run (cavities: at least 2 steps)"
    )
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (the published code runs on one core)")
    parser.add_argument("--out", default="runs/single_env")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"# {machine()}")
    print(
        "| env | mode | gymnasium (lean) /s | TorchRL step /s | step call alone /s | published /s | lean vs published |"
    )
    print("|---|---|---|---|---|---|---|")
    rows = []
    for env_id in args.envs:
        for mode in args.modes:
            seconds = args.seconds * (3 if env_class(env_id).family == "cavity" else 1)
            r = measure(env_id, mode == "compiled", seconds, args.repeats)
            rows.append(r)
            print(
                f"| {env_id} | {mode} | {r['gymnasium']:,.1f} | {r['torchrl']:,.1f} | "
                f"{r['physics']:,.1f} | {r['published']:,.1f} | {r['gymnasium'] / r['published']:.2f}x |",
                flush=True,
            )
    print("results:", save_rows(rows, args.out, "single_env"))


if __name__ == "__main__":
    main()
