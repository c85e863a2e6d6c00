"""Gradient-based control: a deterministic policy trained by backpropagating the rewards
through the physics (short-horizon analytic policy gradients).

The batched env runs with ``differentiable=True``. Each update steps the policy through
``horizon`` actions of every member, sums the discounted rewards, and follows their
exact gradient with respect to the policy's weights (through the observation
normalisation, the actions and every substep of the solver); the graph is then cut at
the current state (``detach_state``) and the episodes go on, ending and restarting as
in any collector. No critic, no sampling noise: what a simulator that is torch buys.

    beacon-torch train burgers-v0 --algo grad
    beacon-torch train vortex-v0 --algo grad --set horizon=200

The policy is TD3's actor (an MLP squashed into the box), so ``eval`` and ``plot`` read
these runs like any other. ``checkpoint=true`` recomputes each action in the backward
pass (``grad_checkpoint``), for horizons whose graph would not fit in memory.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import torch

from beacon_torch.recipes import common
from beacon_torch.recipes.config import GradConfig
from beacon_torch.recipes.td3 import make_actor


def train(env_id: str, cfg: GradConfig, out: str | Path, *, seed: int = 0, device="cpu", resume: bool = False, checkpoint_every: int = 10, progress: bool = True, collectors: int = 1, ray: str | None = None, tensorboard: bool | None = None) -> dict:
    """Train the policy on ``cfg.frames`` transitions; returns the last logged values."""
    if collectors != 1 or ray is not None:
        raise ValueError("grad differentiates through the env in this process: --collectors and --ray do not apply")
    run, env = common.start(
        env_id, "grad", cfg, out, seed=seed, device=device, resume=resume, progress=progress, tensorboard=tensorboard,
        differentiable=True, grad_checkpoint=cfg.checkpoint,
    )
    actor = make_actor(env, cfg.hidden).to(device)
    optim = torch.optim.Adam(actor.parameters(), lr=cfg.lr)
    skipped = 0
    if run.state is not None:
        actor.load_state_dict(run.state["actor"])
        optim.load_state_dict(run.state["optim"])
        skipped = run.state.get("skipped", 0)

    def save() -> None:
        run.save(seed=seed, config=asdict(cfg), actor=actor.state_dict(), optim=optim.state_dict(), obs_norm=env.transform[0].state_dict(), skipped=skipped)

    base = env.base_env
    discount = cfg.gamma ** torch.arange(cfg.horizon, dtype=base.dtype, device=device)
    td = env.reset()
    update = 0
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
            skipped += 1
        # the next update differentiates from here on: cut the graph behind the state
        base.detach_state()
        td = td.detach()
        values = {"reward": -loss.item() / discount.mean().item(), "grad_norm": norm.item(), "skipped_updates": float(skipped)}
        if scores:
            values["episode_score"] = torch.cat(scores).mean().item()
        run.log(cfg.horizon * cfg.num_envs, values)
        update += 1
        if update % checkpoint_every == 0:
            save()
    run.close()
    save()
    return run.last
