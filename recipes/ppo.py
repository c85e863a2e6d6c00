"""PPO on a BEACON env, from TorchRL's pieces: ``ClipPPOLoss`` with ``GAE``, a
``Collector`` over the batched env, a replay buffer for the minibatches, observation
normalisation (``ObservationNorm``) and episode returns (``RewardSum``) as transforms,
and TorchRL's loggers. The paper's settings are the defaults (``beacon_torch.training.config``).

    python recipes/ppo.py --env lorenz-v0 --frames 200000 --num-envs 16
    python recipes/ppo.py --env lorenz-v0 --frames 400000 --resume    # continue to 400k

The run directory (``--out``, default ``runs/ppo/ENV/seedSEED``) holds
``checkpoint.pt`` (networks, optimiser, normalisation, transitions collected; written
every ``checkpoint_every`` updates and at the end), the logs and the learning curve.
"""

from __future__ import annotations

import torch
from torch import nn
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers.samplers import SamplerWithoutReplacement
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from beacon_torch.training import networks
from beacon_torch.training.config import PPOConfig, script
from beacon_torch.training.env import recipe_collector, recipe_env
from beacon_torch.training.run import Run, episode_values


def main(cfg: PPOConfig) -> dict:
    """Train PPO; returns the last logged values and the transitions collected."""
    run = Run.of(cfg)
    torch.manual_seed(cfg.seed)

    # the env, with the saved normalisation when resuming
    env = recipe_env(cfg, run.obs_norm)
    keys = networks.Keys.of(env)

    # the paper's networks, or Stable-Baselines3's actor
    network = {"paper": "stochastic_actor", "free-spread": "free_spread_actor"}[cfg.actor]
    actor = networks.policy(env, network, cfg.hidden).to(cfg.device)
    critic = networks.state_value(env, cfg.hidden, kind=cfg.critic).to(cfg.device)

    # the loss (clipped surrogate, analytic entropy, squared value error), GAE, and one
    # optimiser per network: each network's gradient is clipped on its own, as the
    # critic's is far larger at the start and a common clip would starve the actor;
    # Stable-Baselines3's update clips the two as one and weighs the value error by half
    sb3 = cfg.update == "sb3"
    loss = ClipPPOLoss(
        actor,
        critic,
        clip_epsilon=cfg.clip,
        entropy_coeff=cfg.entropy,
        critic_coeff=0.5 if sb3 else 1.0,
        loss_critic_type="l2",
    )
    advantage = GAE(gamma=cfg.gamma, lmbda=cfg.gae_lambda, value_network=critic, average_gae=False)
    fields = dict(
        reward=keys.reward,
        done=keys.done,
        terminated=keys.terminated,
        value=keys.value,
        advantage=keys.advantage,
        value_target=keys.value_target,
    )
    loss.set_keys(action=keys.action, sample_log_prob=keys.log_prob, **fields)
    advantage.set_keys(**fields)
    eps = 1e-5 if sb3 else 1e-8  # Adam's per parameter: two optimisers step as one would
    actor_optim = torch.optim.Adam(actor.parameters(), lr=cfg.actor_lr, eps=eps)
    critic_optim = {"adam": torch.optim.Adam, "nadam": torch.optim.NAdam}[cfg.critic_optim](
        critic.parameters(), lr=cfg.critic_lr, eps=eps
    )
    run.restore(actor=actor, critic=critic, actor_optim=actor_optim, critic_optim=critic_optim)
    if run.remaining <= 0:
        return run.last

    def save() -> None:
        run.save(
            env,
            policy=(network, cfg.hidden, actor),
            critic=critic,
            actor_optim=actor_optim,
            critic_optim=critic_optim,
        )

    # the collector and the buffer the minibatches are drawn from
    collector = recipe_collector(cfg, env, actor, run, frames_per_batch=cfg.n_rollout)
    buffer = ReplayBuffer(
        storage=LazyTensorStorage(cfg.n_rollout, device=cfg.device),
        sampler=SamplerWithoutReplacement(),
        batch_size=cfg.n_rollout // cfg.minibatches,
    )

    for data in collector:
        if keys.agents:  # the shared end of an episode, as each agent's
            for flag, key in (("done", keys.done), ("terminated", keys.terminated)):
                data[("next", *key)] = data["next", flag].unsqueeze(-2).expand(data[("next", *keys.reward)].shape)
        with torch.no_grad():
            data = advantage(data)
            if not sb3:
                # normalised once over the whole rollout, not per minibatch; per agent in a
                # multi-agent layout, as the jets sit at different places of the film
                adv = data[keys.advantage]
                dims = tuple(d for d in range(adv.ndim) if not (keys.agents and d == adv.ndim - 2))
                data[keys.advantage] = (adv - adv.mean(dims, keepdim=True)) / (adv.std(dims, keepdim=True) + 1e-8)
        buffer.extend(data.reshape(-1))
        for _ in range(cfg.epochs):
            for _ in range(cfg.minibatches):
                batch = buffer.sample()
                if sb3:  # over the minibatch's transitions, every agent's alike
                    adv = batch[keys.advantage]
                    batch[keys.advantage] = (adv - adv.mean()) / (adv.std() + 1e-8)
                losses = loss(batch)
                total = losses["loss_objective"] + losses["loss_critic"] + losses["loss_entropy"]
                actor_optim.zero_grad()
                critic_optim.zero_grad()
                total.backward()
                if sb3:
                    nn.utils.clip_grad_norm_([*actor.parameters(), *critic.parameters()], cfg.grad_clip)
                for net, optim in ((actor, actor_optim), (critic, critic_optim)):
                    if not sb3:
                        nn.utils.clip_grad_norm_(net.parameters(), cfg.grad_clip)
                    optim.step()
        collector.update_policy_weights_()
        run.log(data.numel(), {**episode_values(data, keys.reward), "loss": total.item()}, save)
    collector.shutdown()
    return run.close(save)


if __name__ == "__main__":
    script(main, PPOConfig)
