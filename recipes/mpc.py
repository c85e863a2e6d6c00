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
episode takes too long to plan. Every ``--checkpoint-every`` actions the episodes under
way are saved in OUT (the env's state, the plans, the scores so far); a stopped run goes
on with the same command and ``--resume``, to the same record as without the stop.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

import beacon_torch
from beacon_torch import episodes, files, received, threads
from beacon_torch.core.state import map_state
from beacon_torch.episodes import progress_bar
from beacon_torch.training import config
from beacon_torch.training.config import MPCConfig
from beacon_torch.training.env import horizon_bytes, make_env
from beacon_torch.training.evaluation import EVAL_SEED, uncontrolled_episodes
from beacon_torch.training.report import normalisable, normalised
from beacon_torch.training.run import fits

# where planned episodes under way are kept
CHECKPOINT = "mpc-checkpoint.pt"


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


class Planner:
    """The controller of the evaluation env ``base``: before each action, the plan of
    every member is improved (:func:`improve`), its first action taken, and the rest,
    shifted, with the last one repeated, start the next plan. ``stats`` counts the
    planned actions, their CPU seconds and the iterations dropped."""

    def __init__(self, base, args: MPCConfig) -> None:
        self.base, self.args = base, args
        self.model = base
        if args.plan_params:
            params = {**args.params, **args.plan_params}
            self.model = beacon_torch.make(
                args.env, base.num_envs, params=params, dtype=base.dtype, device=base.device, compile=args.compile
            )
        self.plan = torch.zeros(
            (args.horizon, base.num_envs, *base.physics.action_shape), dtype=base.dtype, device=base.device
        )
        self.generator = torch.Generator(device=base.device).manual_seed(args.seed)
        # the first action a process plans also compiles (where compiled): its CPU time
        # is counted apart, so that a few planned actions give the cost of the next ones
        self.stats = {"actions": 0, "cpu_s": 0.0, "dropped": 0, "first_actions": 0, "first_cpu_s": 0.0}
        self._first = True

    def __call__(self, td):
        start = time.process_time()
        plan = improve(self.base, self.model, self.plan, self.args, self.generator, self.stats)
        action = plan[0].clone()
        self.plan = torch.cat([plan[1:], plan[-1:]])
        seconds = time.process_time() - start
        self.stats["actions"] += 1
        self.stats["cpu_s"] += seconds
        if self._first:
            self.stats["first_actions"] += 1
            self.stats["first_cpu_s"] += seconds
            self._first = False
        return td.set(self.base.action_key, action)

    def cost(self) -> dict:
        """The CPU seconds of a planned action after each process's first, where there
        were such actions (else of every action), and of the first ones."""
        s = self.stats
        later = s["actions"] - s["first_actions"]
        per = (s["cpu_s"] - s["first_cpu_s"]) / later if later > 0 else s["cpu_s"] / max(s["actions"], 1)
        return {"cpu_s_per_action": per, "first_action_cpu_s": s["first_cpu_s"] / max(s["first_actions"], 1)}


def planned_episodes(env, planner: Planner, args: MPCConfig, path: Path) -> tuple[torch.Tensor, dict]:
    """The score of each member's planned episode of ``env`` (float64; of its first
    ``args.actions`` actions where given), as the recipes' evaluation scores an episode:
    the rewards up to its end; and each of the env's diagnostics (a wake's drag) summed
    over the same actions, with their count under ``"actions"``. Every
    ``args.checkpoint_every`` actions, where the episodes are (the env's state and
    generators, the plans, the sums so far) is saved to ``path``; with ``args.resume``
    they go on from there, the same episodes as without the stop."""
    base = env.base_env
    length = args.actions or base.episode_length
    scores = torch.zeros(base.num_envs, dtype=torch.float64, device=base.device)
    sums = {name: torch.zeros_like(scores) for name in (*base.physics.diagnostics, "actions")}
    going = torch.ones(base.num_envs, dtype=torch.bool, device=base.device)
    done = 0
    env.reset()
    if args.resume and path.is_file():
        saved = read_checkpoint(path, base, planner, args, length)
        base.load_state_dict(saved["env"])
        planner.plan, planner.stats = saved["plan"], saved["stats"]
        planner.generator.set_state(saved["generator"])
        scores, going, done = saved["scores"], saved["going"], saved["actions_done"]
        sums = saved["diagnostics"]
        print(f"resuming {path}: {done} of {length} actions planned")
    td = base.current()
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        with progress_bar(f"{args.env} planned" if args.progress else None, length) as bar:
            bar.update(done)
            while done < length and bool(going.any()):
                td = planner(td)
                if not bool(going.all()):
                    # a member whose episode ended (a blow-up) is not stepped again
                    td.set("_step", going.unsqueeze(-1))
                step = env.step(td)["next"]
                scores += torch.where(going, step["reward"][..., 0].to(torch.float64), 0.0)
                for name in sums:
                    seen = 1.0 if name == "actions" else step["diagnostics", name].reshape(-1).to(torch.float64)
                    sums[name] += torch.where(going, seen, 0.0)
                going &= ~step["done"][..., 0]
                td, done = step, done + 1
                bar.update()
                if done % args.checkpoint_every == 0 and done < length and bool(going.any()):
                    saved = {
                        "env_id": args.env,
                        "settings": dataclasses.asdict(args),
                        "actions_done": done,
                        "scores": scores,
                        "diagnostics": sums,
                        "going": going,
                        "env": base.state_dict(),
                        "plan": planner.plan,
                        "generator": planner.generator.get_state(),
                        "stats": planner.stats,
                    }
                    files.save_tensors(saved, path)
    return scores, sums


# how a planning run is carried out, free to change when it is resumed
RUN_OPTIONS = ("out", "resume", "progress", "threads", "checkpoint_every")


def read_checkpoint(path: Path, base, planner: Planner, args: MPCConfig, length: int) -> dict:
    """The checkpoint of planned episodes at ``path``, read as data within bounds: every
    tensor laid out as this run's own (the env's state dict, the plans, the generator's
    state, the scores), its settings this run's (the run options apart), checked before
    anything is copied from the file."""

    def bad(what: str):
        return received.BadFile(f"{path}: not a checkpoint of these planned episodes ({what})")

    def same_layout(saved, own, where: str) -> None:
        if isinstance(own, torch.Tensor):
            if not isinstance(saved, torch.Tensor) or saved.shape != own.shape or saved.dtype != own.dtype:
                raise bad(f"{where} must be a {own.dtype} tensor of shape {tuple(own.shape)}")
        elif isinstance(own, dict):
            if not isinstance(saved, dict) or set(saved) != set(own):
                raise bad(f"{where} must hold {sorted(own)}")
            for key, value in own.items():
                same_layout(saved[key], value, f"{where}.{key}")
        elif type(saved) is not type(own) or (isinstance(own, float) and not received.finite_number(saved)):
            raise bad(f"{where} must be a finite {type(own).__name__}")

    def check(saved) -> None:
        members = base.num_envs
        own = {
            "env_id": args.env,
            "settings": dataclasses.asdict(args),
            "actions_done": 0,
            "scores": torch.zeros(members, dtype=torch.float64),
            "diagnostics": {
                name: torch.zeros(members, dtype=torch.float64) for name in (*base.physics.diagnostics, "actions")
            },
            "going": torch.zeros(members, dtype=torch.bool),
            "env": base.state_dict(),
            "plan": planner.plan,
            "generator": planner.generator.get_state(),
            "stats": planner.stats,
        }
        if not isinstance(saved, dict) or set(saved) != set(own):
            raise bad(f"it must hold {sorted(own)}")
        if saved["env_id"] != args.env:
            raise bad(f"its env is {str(saved['env_id'])[:100]!r}, not {args.env}")
        if not isinstance(saved["settings"], dict):
            raise bad("'settings' must be a dict")
        for name, value in own["settings"].items():
            if name not in RUN_OPTIONS and saved["settings"].get(name) != value:
                raise ValueError(
                    f"{path}: setting '{name}' = {value!r} differs from the planned episodes' "
                    f"{saved['settings'].get(name)!r}; resumed episodes keep the settings they were started with"
                )
        for key in ("actions_done", "scores", "diagnostics", "going", "env", "plan", "generator", "stats"):
            same_layout(saved[key], own[key], key)
        if not 0 < saved["actions_done"] < length or min(saved["stats"].values()) < 0:
            raise bad(f"'actions_done' must lie in [1, {length - 1}] and the counts be non-negative")

    return received.torch_file(path, "checkpoint of planned episodes", check)


def diagnostic_means(sums: dict, free) -> dict:
    """Each of the env's diagnostics averaged over each member's episode and then over
    the members, planned (from ``sums``) and without control (from the rollout
    ``free`` of the same starts), with the relative change (a wake's drag reduction is
    minus it)."""
    means = {}
    for name, total in sums.items():
        if name == "actions":
            continue
        planned = (total / sums["actions"]).mean().item()
        values = free["next", "diagnostics", name].reshape(*free.batch_size).to(torch.float64)
        uncontrolled = episodes.episode_means(values, free).mean().item()
        change = planned / uncontrolled - 1.0 if uncontrolled else None
        means[name] = {"planned": planned, "uncontrolled": uncontrolled, "relative_change": change}
    return means


def main(args: MPCConfig) -> dict:
    """Plan the evaluation episodes (or ``args.actions`` actions only) and write their
    record, a new ``OUT/mpc.json``; returns the record. A stopped run goes on with
    ``--resume`` from its last checkpoint (``OUT/mpc-checkpoint.pt``, removed once the
    record is written)."""
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
        record_file, checkpoint = out / "mpc.json", out / CHECKPOINT
        files.refuse_existing([record_file], "give another --out")  # before the episodes, not after
        if not args.resume:
            files.refuse_existing([checkpoint], "it holds planned episodes under way: give --resume, or another --out")
        starts = None if args.starts == "own" else args.starts
        sets = {} if starts is None else {"starts": starts}
        env = make_env(
            args.env, args.num_envs, seed=EVAL_SEED, norm_steps=0, params=args.params, compile=args.compile,
            device=args.device, **sets,
        )  # fmt: skip
        planner = Planner(env.base_env, args)
        scores, sums = planned_episodes(env, planner, args, checkpoint)
        record = {
            "env": args.env,
            "params": args.params,
            "plan_params": args.plan_params,
            "starts": args.starts,
            "settings": dataclasses.asdict(args),
        }
        if not args.actions:
            free, _ = uncontrolled_episodes(
                args.env, args.num_envs, device=args.device, seed=EVAL_SEED, params=args.params, starts=starts
            )
            record.update(
                score_mean=scores.mean().item(),
                score_std=scores.std(unbiased=False).item(),
                uncontrolled=episodes.scores(free).mean().item(),
                diagnostics=diagnostic_means(sums, free),
            )
            if normalisable(args.env):  # else no reference score to scale by
                record["normalised"] = float(normalised(record["score_mean"], record["uncontrolled"], args.env))
        stats = planner.stats
        record.update(
            planned_actions=stats["actions"],
            **planner.cost(),
            dropped_iterations=stats["dropped"],
            threads=torch.get_num_threads(),
        )
        numbers = {
            **record,
            **{f"{n} {k}": v for n, means in record.get("diagnostics", {}).items() for k, v in means.items()},
        }
        for key, value in numbers.items():
            if isinstance(value, float) and not math.isfinite(value):
                raise ValueError(f"{args.env}: the planned episodes' {key} is {value}; nothing is recorded")
        text = json.dumps(record, indent=1, allow_nan=False)
        files.create_file(record_file, lambda tmp: tmp.write_text(text), "give another --out")
        checkpoint.unlink(missing_ok=True)
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
