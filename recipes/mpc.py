"""Gradient model-predictive control: no learned policy. Before each action, the next
``horizon`` actions of every member are improved by ``iterations`` steps of gradient
ascent (Adam, projected on the action box) on their predicted return, differentiated
through copies of the env's current state stepped by the physics itself
(``beacon_torch.step``); the first action is taken and the rest, shifted, with the last
one repeated, start the next plan. FluidGym's D-MPC on its cylinder plans 20 actions
with 10 iterations each; those are the defaults here.

    python recipes/mpc.py --env burgers-v0
    python recipes/mpc.py --env vortex-v0 --horizon 20 --iterations 10 --starts own
    python recipes/mpc.py --env cylinder-v0 --actions 2 --grad-checkpoint

The planner is judged as the recipes' policies are: the same evaluation episodes (the
held-out test set of developed starts by default, or the env's own start), beside no
control from the same starts, in float32, its score normalised as on the results page
(0: no control, 1: the paper's PPO). It knows the physics but not the future: each
iteration draws the noise of noisy inflows from a generator of its own. Where the
reward has no gradient (lorenz's indicator of x < 0), ``--plan-param`` gives the
planner's model a smooth stand-in, the episodes still judged by the env's reward. A member whose
plan's gradient is not finite keeps its plan for that iteration (counted). Writes a
new OUT/mpc.json: the scores, the normalised score, the CPU time per action and the
settings. ``--actions N`` plans N actions only and records their cost, for envs whose
episode takes too long to plan.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import torch

import beacon_torch
from beacon_torch import files, threads
from beacon_torch.core.state import map_state
from beacon_torch.registry import env_class
from beacon_torch.training import config
from beacon_torch.training.config import MPCConfig
from beacon_torch.training.env import horizon_bytes, make_env
from beacon_torch.training.evaluation import EVAL_SEED, evaluate_policy
from beacon_torch.training.report import normalised
from beacon_torch.training.run import fits


def predicted_return(base, model, plan: torch.Tensor, args, generator: torch.Generator) -> torch.Tensor:
    """The discounted return of each member over the plan ``[horizon, members,
    actions]`` from the current state of the env ``base``, stepped by the physics of
    ``model`` (the env itself, or one with the planner's parameters), differentiable
    with respect to the plan. Nothing is counted past a member's episode end or a
    blow-up."""
    physics, params = model.physics, model.params
    state = map_state(torch.Tensor.detach, base.state)
    observation, count = base.observation.detach(), base.step_count
    total = torch.zeros(base.num_envs, dtype=base.dtype, device=base.device)
    going = torch.ones(base.num_envs, dtype=torch.bool, device=base.device)
    for h in range(plan.shape[0]):
        noise = physics.noise(params, generator)
        out = beacon_torch.step(
            physics, params, state, plan[h], noise, count, observation, keep_graph=True, checkpoint=args.grad_checkpoint
        )
        going = going & (count < base.episode_length)
        total = total + args.discount**h * torch.where(going, out.reward, 0.0)
        going = going & ~out.terminated
        state, observation, count = out.state, out.observation, out.count
    return total


def improve(base, model, plan: torch.Tensor, args, generator: torch.Generator, stats: dict) -> torch.Tensor:
    """``plan`` after ``args.iterations`` steps of Adam on its predicted return, each
    projected on the action box. A member whose gradient is not finite keeps its plan
    for that iteration (counted in ``stats["dropped"]``)."""
    plan = plan.detach().clone().requires_grad_(True)  # the given plan is left as it was
    optim = torch.optim.Adam([plan], lr=args.lr)
    with torch.enable_grad():
        for _ in range(args.iterations):
            objective = predicted_return(base, model, plan, args, generator).sum()
            optim.zero_grad()
            (-objective).backward()
            finite = torch.isfinite(plan.grad).flatten(2).all(-1).all(0)
            stats["dropped"] += int((~finite).sum())
            plan.grad[:, ~finite] = 0.0
            optim.step()
            with torch.no_grad():
                plan.clamp_(-1.0, 1.0)
    return plan.detach()


def planner(args, stats: dict):
    """The controller: a function of the evaluation env returning its policy."""

    def on(env):
        base = env.base_env
        model = base
        if args.plan_params:
            params = {**args.params, **args.plan_params}
            model = beacon_torch.make(
                args.env, base.num_envs, params=params, dtype=base.dtype, device=base.device, compile=args.compile
            )
        plan = torch.zeros(
            (args.horizon, base.num_envs, *base.physics.action_shape), dtype=base.dtype, device=base.device
        )
        generator = torch.Generator(device=base.device).manual_seed(args.seed)

        def act(td):
            nonlocal plan
            start = time.process_time()
            plan = improve(base, model, plan, args, generator, stats)
            # the first action is taken; the rest, shifted, start the next plan
            action = plan[0].clone()
            plan = torch.cat([plan[1:], plan[-1:]])
            stats["actions"] += 1
            stats["cpu_s"] += time.process_time() - start
            return td.set(base.action_key, action)

        return act

    on.acts_on_env = True
    return on


def main(args: MPCConfig) -> dict:
    """Plan the evaluation episodes (or ``args.actions`` actions only) and write their
    record, a new ``OUT/mpc.json``; returns the record."""
    # the graph of a plan of every member, estimated from one action, must fit
    model_params = {**args.params, **args.plan_params}
    need = horizon_bytes(
        args.env, args.horizon, args.num_envs, params=model_params, grad_checkpoint=args.grad_checkpoint
    )
    fits(f"the graph of a plan of {args.horizon} actions of {args.num_envs} members", need, args.device)
    threads.use(args.threads or None, args.env, args.num_envs)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    lock = files.Lock(out)  # a second planner writing here is refused
    try:
        record_file = out / "mpc.json"
        files.refuse_existing([record_file], "give another --out")  # before the episodes, not after
        starts = None if args.starts == "own" else args.starts
        stats = {"actions": 0, "cpu_s": 0.0, "dropped": 0}
        control = planner(args, stats)
        record = {
            "env": args.env,
            "params": args.params,
            "plan_params": args.plan_params,
            "starts": args.starts,
            "settings": dataclasses.asdict(args),
        }
        if args.actions:
            # the cost only: a few planned actions of the evaluation episodes
            sets = {} if starts is None else {"starts": starts}
            env = make_env(
                args.env,
                args.num_envs,
                seed=EVAL_SEED,
                norm_steps=0,
                params=args.params,
                compile=args.compile,
                device=args.device,
                **sets,
            )
            act, td = control(env), env.reset()
            for _ in range(args.actions):
                td = env.step(act(td))["next"]
        else:
            result = evaluate_policy(
                args.env,
                control,
                num_envs=args.num_envs,
                seed=EVAL_SEED,
                params=args.params,
                starts=starts,
                progress=args.progress,
                compile=args.compile,
                device=args.device,
            )
            record.update({k: result[k] for k in ("score_mean", "score_std", "uncontrolled")})
            if env_class(args.env).paper_ppo is not None:  # else no reference score to scale by
                record["normalised"] = float(normalised(result["score_mean"], result["uncontrolled"], args.env))
        record.update(
            planned_actions=stats["actions"],
            cpu_s_per_action=stats["cpu_s"] / max(stats["actions"], 1),
            dropped_iterations=stats["dropped"],
            threads=torch.get_num_threads(),
        )
        for key, value in record.items():
            if isinstance(value, float) and not math.isfinite(value):
                raise ValueError(f"{args.env}: the planned episodes' {key} is {value}; nothing is recorded")
        text = json.dumps(record, indent=1, allow_nan=False)
        files.create_file(record_file, lambda tmp: tmp.write_text(text), "give another --out")
    finally:
        lock.release()
    if "score_mean" in record:
        scaled_text = f"normalised {record['normalised']:.2f}, " if "normalised" in record else ""
        print(
            f"mpc on {args.env} ({args.starts} starts): {record['score_mean']:.4g} against "
            f"{record['uncontrolled']:.4g} uncontrolled, {scaled_text}"
            f"{record['cpu_s_per_action']:.2f} CPU s per action"
        )
    else:
        print(f"mpc on {args.env}: {record['cpu_s_per_action']:.2f} CPU s per planned action ({args.actions} actions)")
    return record


def parse(argv: list[str] | None = None) -> MPCConfig:
    """The planner's settings from a command line (``--help`` lists them), checked as
    every recipe's are."""
    return config.parse(MPCConfig, argv)


if __name__ == "__main__":
    config.script(main, MPCConfig)
