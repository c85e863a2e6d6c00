"""One env at a time: the published code's single-env speed against ours at batch 1.

    .venv/bin/python benchmarks/single_env.py [--envs ...] [--out DIR]

For every env, random actions (fixed seed) through
- ``gymnasium.make("beacon/<id>")``: the lean path (``FlowEnv.step_members``, numpy in
  and out), eager and compiled;
- a batch-of-one TorchRL env's ``step`` (TensorDicts and TorchRL's step wrappers), for
  comparison;
- the step call alone (``beacon_torch.core.step.step`` from a frozen state: the physics, the
  action's checks and the bookkeeping; compiled, the one compiled call), the floor of
  any wrapper: what the lean step costs beyond it is the adapter's share.

Each path is timed by ``torch.utils.benchmark`` after a warm-up that steps until a step
compiles nothing new; graphs compiled while timing are reported (``recompiles``).
Prints a markdown table and writes a new ``single_env-DATE-TIME.json`` to ``--out``. The numbers in
benchmarks/RESULTS.md come from this script, run on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import statistics

import gymnasium
import numpy as np
import torch
import torch.utils.benchmark as benchmark
from tensordict import TensorDict

from beacon_torch.bench import compiled_graphs, warm_up
from beacon_torch.files import machine, save_rows
from beacon_torch.registry import base_envs, env_spec

ENVS = base_envs()  # the seven benchmark envs


def rates(steps: dict, seconds: float, repeats: int) -> tuple[dict, int]:
    """Median steps per second of each of ``steps`` (name -> function), timed by
    ``torch.utils.benchmark`` with the repeats of the paths alternating, so that they are
    measured side by side, each run about ``seconds`` long (at least 2 steps). Each path
    is first warmed up until a step compiles nothing new; the graphs compiled while
    timing are returned beside the rates (0 when the compiled code was stable)."""
    timers = {}
    counts = {}
    for name, step in steps.items():
        warm_up(step)
        timers[name] = benchmark.Timer(stmt="step()", globals={"step": step}, num_threads=torch.get_num_threads())
        counts[name] = max(2, int(seconds / timers[name].timeit(3).median))
    graphs = compiled_graphs()
    measured = {name: [] for name in steps}
    for _ in range(repeats):
        for name, timer in timers.items():
            measured[name].append(1.0 / timer.timeit(counts[name]).median)
    return {name: statistics.median(r) for name, r in measured.items()}, compiled_graphs() - graphs


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
                noise=env.physics.noise(env.params, env.rng),
            )
        with torch.no_grad():
            inputs = frozen["state"], frozen["action"], frozen["noise"], frozen["count"], frozen["obs"]
            env._whole_step(env.physics, env.params, *inputs)

    measured, recompiles = rates({"gymnasium": lean, "torchrl": torchrl_step, "physics": physics}, seconds, repeats)
    return {
        "env": env_id,
        "mode": "compiled" if compiled else "eager",
        "published": env_spec(env_id).card.published_speed,
        **measured,
        "recompiles": recompiles,
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
        "| env | mode | gymnasium (lean) /s | TorchRL step /s | step call alone /s | published /s | lean vs published "
        "| recompiles |"
    )
    print("|---|---|---|---|---|---|---|---|")
    rows = []
    for env_id in args.envs:
        for mode in args.modes:
            seconds = args.seconds * (3 if env_spec(env_id).card.costly else 1)
            r = measure(env_id, mode == "compiled", seconds, args.repeats)
            rows.append(r)
            print(
                f"| {env_id} | {mode} | {r['gymnasium']:,.1f} | {r['torchrl']:,.1f} | "
                f"{r['physics']:,.1f} | {r['published']:,.1f} | {r['gymnasium'] / r['published']:.2f}x | "
                f"{r['recompiles']} |",
                flush=True,
            )
    print("results:", save_rows(rows, args.out, "single_env"))


if __name__ == "__main__":
    main()
