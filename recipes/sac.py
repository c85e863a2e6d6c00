"""SAC on a BEACON env with continuous actions, from TorchRL's pieces: ``SACLoss``
(twin critics, their targets updated by ``SoftUpdate``, the entropy's weight tuned to
the target entropy -dim(action)), a squashed Gaussian actor that explores by sampling,
a ``Collector`` over the batched env and a ``ReplayBuffer`` saved with each checkpoint.
In a multi-agent layout (rbc2d-easy-ma-v0) the agents share the actor and the critics,
each agent's value is learnt from its own reward, and a stored transition holds every
agent's.

    .venv/bin/python recipes/sac.py --env cylinder-v0
"""

from __future__ import annotations

import torch
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.objectives import SACLoss, SoftUpdate

from beacon_torch.training import networks
from beacon_torch.training.config import SACConfig, script
from beacon_torch.training.env import recipe_collector, recipe_env
from beacon_torch.training.run import Run, episode_values


def main(cfg: SACConfig) -> dict:
    """Train SAC; returns the last logged values and the transitions collected."""
    run = Run.of(cfg)
    torch.manual_seed(cfg.seed)

    # the env, with the saved normalisation when resuming
    env = recipe_env(cfg, run.obs_norm)
    keys = networks.Keys.of(env)

    # the actor, the twin critics (inside the loss), the entropy's weight, their optimisers
    actor = networks.squashed_gaussian_actor(env, cfg.hidden).to(cfg.device)
    qvalue = networks.action_value(env, cfg.hidden).to(cfg.device)
    loss = SACLoss(actor, qvalue, num_qvalue_nets=2, loss_function="l2", alpha_init=cfg.alpha_init)
    loss.set_keys(
        action=keys.action,
        state_action_value=qvalue.out_keys[0],
        reward=keys.reward,
        done=keys.done,
        terminated=keys.terminated,
    )
    loss.make_value_estimator(gamma=cfg.gamma)
    target = SoftUpdate(loss, tau=cfg.tau)
    # Adam's fused kernel: a gradient step a transition makes its element-wise work a
    # tenth of the update
    actor_optim = torch.optim.Adam(loss.actor_network_params.flatten_keys().values(), lr=cfg.lr, fused=True)
    critic_optim = torch.optim.Adam(loss.qvalue_network_params.flatten_keys().values(), lr=cfg.lr, fused=True)
    alpha_optim = torch.optim.Adam([loss.log_alpha], lr=cfg.alpha_lr, fused=True)

    # the replay buffer; the actor samples its actions while collecting
    buffer = ReplayBuffer(
        storage=LazyTensorStorage(cfg.buffer_size or cfg.frames, device=cfg.device), batch_size=cfg.batch_size
    )
    optims = dict(actor_optim=actor_optim, critic_optim=critic_optim, alpha_optim=alpha_optim)
    run.restore(buffer, actor=actor, loss=loss, **optims)
    if run.remaining <= 0:
        return run.last

    def save() -> None:
        run.save(env, policy=("squashed_gaussian_actor", cfg.hidden, actor), buffer=buffer, loss=loss, **optims)

    collector = recipe_collector(cfg, env, actor, run)

    for data in collector:
        if keys.agents:  # the shared end of an episode, as each agent's
            for flag, key in (("done", keys.done), ("terminated", keys.terminated)):
                data[("next", *key)] = data["next", flag].unsqueeze(-2).expand(data[("next", *keys.reward)].shape)
        buffer.extend(data.reshape(-1))
        values = episode_values(data, keys.reward)
        if run.frames + data.numel() > cfg.init_random_frames:
            for _ in range(cfg.updates_per_batch):
                losses = loss(buffer.sample())
                # each loss reaches its own parameters only (the actor's loss reads the
                # critics detached, the entropy's loss the log-probabilities): one
                # backward of their sum gives each optimiser its own gradient
                for optim in optims.values():
                    optim.zero_grad()
                (losses["loss_actor"] + losses["loss_qvalue"] + losses["loss_alpha"]).backward()
                for optim in optims.values():
                    optim.step()
                target.step()
            values.update(loss=losses["loss_qvalue"].item(), alpha=losses["alpha"].item())
            collector.update_policy_weights_()
        run.log(data.numel(), values, save)
    collector.shutdown()
    return run.close(save)


if __name__ == "__main__":
    script(main, SACConfig)
