"""Gradient-based control: a deterministic policy trained by backpropagating the rewards
through the physics (short-horizon analytic policy gradients).

The batched env runs with ``differentiable=True``. Each update steps the policy through
``horizon`` actions of every member, sums the discounted rewards, and follows their
exact gradient with respect to the policy's weights (through the observation
normalisation, the actions and every substep of the solver); the graph is then cut at
the current state (``detach_state``) and the episodes go on, ending and restarting as
in any collector. No critic, no sampling noise: what a simulator that is torch buys.

    python recipes/grad.py --env burgers-v0
    python recipes/grad.py --env vortex-v0 --horizon 200

The policy is TD3's deterministic actor, so ``beacon-torch eval`` and ``plot`` read
these runs like any other. ``--grad-checkpoint`` recomputes each action in the backward
pass (the env's ``grad_checkpoint``), for horizons whose graph would not fit in memory.
"""

from __future__ import annotations

import torch

from beacon_torch.training import networks
from beacon_torch.training.config import GradConfig, script
from beacon_torch.training.env import horizon_bytes, recipe_env
from beacon_torch.training.run import Run, fits


def main(cfg: GradConfig) -> dict:
    """Train the policy on ``cfg.frames`` transitions; returns the last logged values."""
    # the graph of a horizon of every member, estimated from one action, must fit
    need = horizon_bytes(cfg.env, cfg.horizon, cfg.num_envs, params=cfg.params, grad_checkpoint=cfg.grad_checkpoint)
    fits(f"the graph of {cfg.horizon} differentiated actions of {cfg.num_envs} members", need, cfg.device)
    run = Run.of(cfg)
    torch.manual_seed(cfg.seed)

    # the differentiable env, with the saved normalisation when resuming
    env = recipe_env(cfg, run.obs_norm, differentiable=True, grad_checkpoint=cfg.grad_checkpoint)
    base = env.base_env

    # the policy and its optimiser; the count of updates dropped for a non-finite gradient
    actor = networks.deterministic_actor(env, cfg.hidden, paper_init=False).to(cfg.device)
    optim = torch.optim.Adam(actor.parameters(), lr=cfg.lr)
    run.restore(actor=actor, optim=optim)
    run.counters.setdefault("skipped", 0)

    def save() -> None:
        run.save(env, policy=("deterministic_actor", cfg.hidden, actor), optim=optim)

    discount = cfg.gamma ** torch.arange(cfg.horizon, dtype=base.dtype, device=cfg.device)
    td = env.reset()
    while run.frames < cfg.frames:
        total, scores = 0.0, []
        for h in range(cfg.horizon):
            td, td_next = env.step_and_maybe_reset(actor(td))
            total = total + discount[h] * td["next", "reward"]
            done = td["next", "done"][..., 0]
            if done.any():
                scores.append(td["next", "episode_reward"][done].detach())
            td = td_next
        loss = -total.mean() / cfg.horizon
        optim.zero_grad()
        loss.backward()
        norm = torch.nn.utils.clip_grad_norm_(actor.parameters(), cfg.grad_clip)
        if torch.isfinite(norm):
            optim.step()
        else:
            # a member that blew up inside the horizon can leave 0 * inf in the backward
            # pass; its episode has ended, the update is dropped
            run.counters["skipped"] += 1
        # the next update differentiates from here on: cut the graph behind the state
        base.detach_state()
        td = td.detach()
        values = {"reward": -loss.item() / discount.mean().item(), "skipped_updates": float(run.counters["skipped"])}
        if torch.isfinite(norm):
            values["grad_norm"] = norm.item()
        if scores:
            values["episode_score"] = torch.cat(scores).mean().item()
        run.log(cfg.horizon * cfg.num_envs, values, save)
    return run.close(save)


if __name__ == "__main__":
    script(main, GradConfig)
