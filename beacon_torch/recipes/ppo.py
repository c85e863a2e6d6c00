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

from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path

import torch
from tensordict import NestedKey
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers.samplers import SamplerWithoutReplacement
from torchrl.envs import TransformedEnv
from torchrl.modules import IndependentNormal, ProbabilisticActor, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from beacon_torch.recipes import common
from beacon_torch.recipes.common import orthogonal
from beacon_torch.recipes.config import PPOConfig


class Heads(nn.Module):
    """The paper's continuous actor: a shared tanh layer, then a mean head ending in tanh
    (within the action box) and a spread head ending in a sigmoid (0 to 1), the
    parameters of a normal distribution. Module level, so that multi-process collectors
    can pickle it."""

    def __init__(self, n_obs: int, hidden: int, n_act: int) -> None:
        super().__init__()
        self.trunk = nn.Sequential(nn.Linear(n_obs, hidden), nn.Tanh())
        self.mean = nn.Sequential(nn.Linear(hidden, hidden), nn.Tanh(), nn.Linear(hidden, n_act), nn.Tanh())
        self.spread = nn.Sequential(nn.Linear(hidden, hidden), nn.Tanh(), nn.Linear(hidden, n_act), nn.Sigmoid())

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        z = self.trunk(obs)
        return self.mean(z), self.spread(z)


@dataclass(frozen=True)
class Keys:
    """Where PPO reads and writes: at the root, or under ``"agents"`` in a multi-agent
    layout (shkadov-separable-v0), where one policy and one critic are shared by the
    agents (the agent dimension is one more batch dimension to the networks) and each
    agent's advantage comes from its own reward."""

    obs: NestedKey
    action: NestedKey
    reward: NestedKey
    log_prob: NestedKey
    value: NestedKey
    advantage: NestedKey
    value_target: NestedKey
    done: NestedKey
    terminated: NestedKey

    @classmethod
    def of(cls, env: TransformedEnv) -> "Keys":
        base = env.base_env
        at = partial(common.sibling, base.observation_key)
        names = ("action_log_prob", "state_value", "advantage", "value_target", "done", "terminated")
        return cls(base.observation_key, base.action_key, base.reward_key, *map(at, names))

    @property
    def agents(self) -> bool:
        return isinstance(self.obs, tuple)


def make_actor(env: TransformedEnv, hidden: int) -> ProbabilisticActor:
    """The paper's actor: a shared tanh layer, then one tanh head each for the mean and
    the spread (continuous) or for the logits (discrete)."""
    keys = Keys.of(env)
    n_obs = env.observation_spec[keys.obs].shape[-1]
    spec = env.full_action_spec[keys.action]
    if env.base_env.discrete:
        trunk = [nn.Linear(n_obs, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh()]
        net = orthogonal(nn.Sequential(*trunk, nn.Linear(hidden, env.base_env.n_actions)))
        module = TensorDictModule(net, in_keys=[keys.obs], out_keys=["logits"])
        return ProbabilisticActor(module, in_keys=["logits"], distribution_class=torch.distributions.Categorical, return_log_prob=True, spec=env.action_spec)
    params = [common.sibling(keys.action, "loc"), common.sibling(keys.action, "scale")]
    module = TensorDictModule(orthogonal(Heads(n_obs, hidden, spec.shape[-1])), in_keys=[keys.obs], out_keys=params)
    # as the paper's agent: a normal sample, clipped to the box by the env's transform
    # (common.make_env) while the loss sees the sample itself; not a tanh-squashed
    # distribution, whose vanishing gradient at the bounds traps "no control" policies
    return ProbabilisticActor(
        module,
        in_keys=dict(zip(("loc", "scale"), params)),
        out_keys=[keys.action],
        log_prob_key=keys.log_prob,
        distribution_class=IndependentNormal,
        return_log_prob=True,
        spec=env.full_action_spec,
    )


def make_critic(env: TransformedEnv, hidden: int) -> ValueOperator:
    keys = Keys.of(env)
    n_obs = env.observation_spec[keys.obs].shape[-1]
    net = orthogonal(nn.Sequential(nn.Linear(n_obs, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, 1)))
    return ValueOperator(net, in_keys=[keys.obs], out_keys=[keys.value])


def train(env_id: str, cfg: PPOConfig, out: str | Path, *, seed: int = 0, device="cpu", resume: bool = False, checkpoint_every: int = 10, progress: bool = True, collectors: int = 1, ray: str | None = None, tensorboard: bool | None = None) -> dict:
    """Train PPO; returns the last logged values and the frames collected."""
    run, env = common.start(env_id, "ppo", cfg, out, seed=seed, device=device, resume=resume, progress=progress, tensorboard=tensorboard)
    state = run.state
    keys = Keys.of(env)
    actor, critic = make_actor(env, cfg.hidden).to(device), make_critic(env, cfg.hidden).to(device)
    # agents sit at different places of the film: their advantages are normalised apart
    exclude = (-2,) if keys.agents else ()
    loss = ClipPPOLoss(actor, critic, clip_epsilon=cfg.clip, entropy_coeff=cfg.entropy, normalize_advantage=True, normalize_advantage_exclude_dims=exclude, loss_critic_type="l2")
    advantage = GAE(gamma=cfg.gamma, lmbda=cfg.gae_lambda, value_network=critic, average_gae=False)
    fields = dict(reward=keys.reward, done=keys.done, terminated=keys.terminated, value=keys.value, advantage=keys.advantage, value_target=keys.value_target)
    loss.set_keys(action=keys.action, sample_log_prob=keys.log_prob, **fields)
    advantage.set_keys(**fields)
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

    collector = common.make_collector(env_id, env, actor, frames_per_batch=cfg.n_rollout, total_frames=remaining, collectors=collectors, ray=ray, seed=seed, device=device)
    buffer = ReplayBuffer(storage=LazyTensorStorage(cfg.n_rollout, device=device), sampler=SamplerWithoutReplacement(), batch_size=cfg.n_rollout // cfg.minibatches)
    for update, data in enumerate(collector):
        if keys.agents:  # the shared end of an episode, as each agent's
            for flag, key in (("done", keys.done), ("terminated", keys.terminated)):
                data["next", *key] = data["next", flag].unsqueeze(-2).expand(data["next", *keys.reward].shape)
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
        run.log(data.numel(), {**common.episode_values(data, keys.reward), "loss": total.item()})
        if (update + 1) % checkpoint_every == 0:
            save()
    collector.shutdown()
    run.close()
    save()
    return run.last
