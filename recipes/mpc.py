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

import argparse
import json
import time
from pathlib import Path

import torch

import beacon_torch
from beacon_torch import threads
from beacon_torch.core.state import map_state
from beacon_torch.files import create_file, refuse_existing
from beacon_torch.params import parse_assignments
from beacon_torch.registry import env_class
from beacon_torch.training.env import make_env
from beacon_torch.training.evaluation import EVAL_SEED, HELD_OUT, evaluate_policy
from beacon_torch.training.report import normalised


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


def main(args) -> dict:
    threads.use(args.threads or None, args.env, args.num_envs)
    params = args.params
    record_file = args.out / "mpc.json"
    refuse_existing([record_file], "give another --out")  # before the episodes, not after
    starts = None if args.starts == "own" else args.starts
    stats = {"actions": 0, "cpu_s": 0.0, "dropped": 0}
    control = planner(args, stats)
    settings = vars(args) | {"out": str(args.out)}
    record = {
        "env": args.env,
        "params": params,
        "plan_params": args.plan_params,
        "starts": args.starts,
        "settings": settings,
    }
    if args.actions:
        # the cost only: a few planned actions of the evaluation episodes
        sets = {} if starts is None else {"starts": starts}
        env = make_env(
            args.env, args.num_envs, seed=EVAL_SEED, norm_steps=0, params=params, compile=args.compile, **sets
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
            params=params,
            starts=starts,
            progress=args.progress,
            compile=args.compile,
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
    args.out.mkdir(parents=True, exist_ok=True)
    text = json.dumps(record, indent=1)
    create_file(record_file, lambda tmp: tmp.write_text(text), "give another --out")
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


def parse(argv: list[str] | None = None):
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--env", required=True, help="an env id with continuous actions (beacon-torch list)")
    parser.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", help="a physical parameter")
    parser.add_argument(
        "--plan-param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a parameter of the planner's model only (lorenz's reward_width=1: a smooth stand-in for its\n"
        "indicator reward, whose gradient is zero); the episodes are judged by the env's own",
    )
    parser.add_argument("--horizon", type=int, default=20, help="actions planned ahead (default 20)")
    parser.add_argument("--iterations", type=int, default=10, help="gradient steps per action (default 10)")
    parser.add_argument("--lr", type=float, default=0.1, help="Adam's rate on the actions, in [-1, 1] (default 0.1)")
    parser.add_argument("--discount", type=float, default=1.0, help="of the predicted rewards (default 1)")
    parser.add_argument("--starts", default=HELD_OUT, choices=("own", "validation", "test"), help="(default test)")
    parser.add_argument("--num-envs", type=int, default=8, help="evaluation episodes, one member each (default 8)")
    parser.add_argument("--actions", type=int, default=0, help="plan this many actions only, for their cost")
    parser.add_argument("--grad-checkpoint", action="store_true", help="recompute each action in the backward pass")
    parser.add_argument("--compile", action=argparse.BooleanOptionalAction, default=False, help="(default: eager)")
    parser.add_argument("--seed", type=int, default=0, help="of the planner's noise (default 0)")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: the env's measured fastest)")
    parser.add_argument("--out", type=Path, default=None, help="(default runs/mpc/ENV)")
    parser.add_argument("--no-progress", dest="progress", action="store_false")
    args = parser.parse_args(argv)
    cls = env_class(args.env)
    if cls.discrete:
        parser.error(f"{args.env} has discrete actions: the planner differentiates continuous ones")
    for name in ("horizon", "iterations", "num_envs"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be a positive integer")
    args.params = dict(parse_assignments(args.param))
    args.plan_params = dict(parse_assignments(args.plan_param))
    if args.out is None:
        args.out = Path("runs") / "mpc" / args.env
    return args


if __name__ == "__main__":
    main(parse())
