"""PPO on a BEACON env, from TorchRL's pieces: ``ClipPPOLoss`` with ``GAE``, a
``Collector`` over the batched env, a replay buffer for the minibatches, observation
normalisation (``ObservationNorm``) and episode returns (``RewardSum``) as transforms,
and a ``CSVLogger``. The paper's settings are the defaults (``recipes/config.py``).

    beacon-torch train lorenz-v0 --algo ppo --frames 200000 --out runs/ppo-lorenz

A run directory holds ``checkpoint.pt`` (networks, optimiser, normalisation, frames
collected; written every ``checkpoint_every`` updates and at the end) and the logger's
CSV files; ``train(..., resume=True)`` continues from the checkpoint.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers.samplers import SamplerWithoutReplacement
from torchrl.envs import TransformedEnv
from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from beacon_torch.recipes import common
from beacon_torch.recipes.common import orthogonal
from beacon_torch.recipes.config import PPOConfig

def make_actor(env: TransformedEnv, hidden: int) -> ProbabilisticActor:
    """The paper's actor: a shared tanh layer, then one tanh head each for the mean and
    the spread (continuous) or for the logits (discrete)."""
    n_obs = env.observation_spec["observation"].shape[-1]
    spec = env.action_spec
    trunk = [nn.Linear(n_obs, hidden), nn.Tanh()]
    if env.base_env.discrete:
        net = orthogonal(nn.Sequential(*trunk, nn.Linear(hidden, hidden), nn.Tanh(), nn.Linear(hidden, env.base_env.n_actions)))
        module = TensorDictModule(net, in_keys=["observation"], out_keys=["logits"])
        return ProbabilisticActor(module, in_keys=["logits"], distribution_class=torch.distributions.Categorical, return_log_prob=True, spec=spec)
    n_act = spec.shape[-1]

    class Heads(nn.Module):
        def __init__(self):
            super().__init__()
            self.trunk = nn.Sequential(*trunk)
            self.mean = nn.Sequential(nn.Linear(hidden, hidden), nn.Tanh(), nn.Linear(hidden, n_act))
            self.spread = nn.Sequential(nn.Linear(hidden, hidden), nn.Tanh(), nn.Linear(hidden, n_act))
            self.scale = NormalParamExtractor()

        def forward(self, obs):
            z = self.trunk(obs)
            return self.scale(torch.cat((self.mean(z), self.spread(z)), -1))

    module = TensorDictModule(orthogonal(Heads()), in_keys=["observation"], out_keys=["loc", "scale"])
    return ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        distribution_class=TanhNormal,
        distribution_kwargs={"low": spec.space.low, "high": spec.space.high},
        return_log_prob=True,
        spec=spec,
    )


def make_critic(env: TransformedEnv, hidden: int) -> ValueOperator:
    n_obs = env.observation_spec["observation"].shape[-1]
    net = orthogonal(nn.Sequential(nn.Linear(n_obs, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, 1)))
    return ValueOperator(net, in_keys=["observation"])


def train(env_id: str, cfg: PPOConfig, out: str | Path, *, seed: int = 0, device="cpu", resume: bool = False, checkpoint_every: int = 10, progress: bool = True) -> dict:
    """Train PPO; returns the last logged values and the frames collected."""
    run, env = common.start(env_id, "ppo", cfg, out, seed=seed, device=device, resume=resume, progress=progress)
    state = run.state
    actor, critic = make_actor(env, cfg.hidden).to(device), make_critic(env, cfg.hidden).to(device)
    loss = ClipPPOLoss(actor, critic, clip_epsilon=cfg.clip, entropy_coeff=cfg.entropy, normalize_advantage=True, loss_critic_type="l2")
    advantage = GAE(gamma=cfg.gamma, lmbda=cfg.gae_lambda, value_network=critic, average_gae=False)
    optim = torch.optim.Adam([{"params": actor.parameters(), "lr": cfg.actor_lr}, {"params": critic.parameters(), "lr": cfg.critic_lr}])
    if state is not None:
        actor.load_state_dict(state["actor"])
        critic.load_state_dict(state["critic"])
        optim.load_state_dict(state["optim"])
    remaining = cfg.frames - run.frames
    if remaining <= 0:
        return run.last

    def save() -> None:
        run.save(seed=seed, config=asdict(cfg), actor=actor.state_dict(), critic=critic.state_dict(), optim=optim.state_dict(), obs_norm=env.transform[0].state_dict())

    collector = Collector(env, actor, frames_per_batch=cfg.n_rollout, total_frames=remaining, device=device, auto_register_policy_transforms=False)
    buffer = ReplayBuffer(storage=LazyTensorStorage(cfg.n_rollout, device=device), sampler=SamplerWithoutReplacement(), batch_size=cfg.n_rollout // cfg.minibatches)
    for update, data in enumerate(collector):
        with torch.no_grad():
            data = advantage(data)
        buffer.extend(data.reshape(-1))
        for _ in range(cfg.epochs):
            for _ in range(cfg.minibatches):
                losses = loss(buffer.sample())
                total = losses["loss_objective"] + losses["loss_critic"] + losses["loss_entropy"]
                optim.zero_grad()
                total.backward()
                nn.utils.clip_grad_norm_(loss.parameters(), cfg.grad_clip)
                optim.step()
        collector.update_policy_weights_()
        run.log(data.numel(), {**common.episode_values(data), "loss": total.item()})
        if (update + 1) % checkpoint_every == 0:
            save()
    collector.shutdown()
    run.close()
    save()
    return run.last
