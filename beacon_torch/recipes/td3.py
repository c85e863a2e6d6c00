"""TD3 on a BEACON env with continuous actions, from TorchRL's pieces: ``TD3Loss``
(twin Q-networks, target policy smoothing, delayed actor and target updates through
``SoftUpdate``), ``AdditiveGaussianModule`` exploration, a ``Collector`` over the
batched env and a ``ReplayBuffer`` (the loop is ``common.off_policy_train``).

    beacon-torch train burgers-v0 --algo td3 --frames 200000
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.modules import MLP, AdditiveGaussianModule, TanhModule, ValueOperator
from torchrl.objectives import SoftUpdate, TD3Loss

from beacon_torch.recipes import common
from beacon_torch.recipes.config import OffPolicyConfig

ACTOR_DELAY = 2  # critic updates per actor update


def action_bounds(env) -> tuple[torch.Tensor, torch.Tensor]:
    """The action box of one member (the env's spec carries the batch dimension)."""
    space = env.action_spec.space
    return space.low.reshape(-1, env.action_spec.shape[-1])[0], space.high.reshape(-1, env.action_spec.shape[-1])[0]


def make_actor(env, hidden: int) -> TensorDictSequential:
    """A deterministic policy: an MLP squashed into the action box."""
    n_obs, n_act = env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1]
    low, high = action_bounds(env)
    net = MLP(in_features=n_obs, out_features=n_act, num_cells=[hidden, hidden], activation_class=nn.ReLU)
    return TensorDictSequential(
        TensorDictModule(net, in_keys=["observation"], out_keys=["param"]),
        TanhModule(in_keys=["param"], out_keys=["action"], low=low, high=high),
    )


def make_qvalue(env, hidden: int) -> ValueOperator:
    n_in = env.observation_spec["observation"].shape[-1] + env.action_spec.shape[-1]
    net = MLP(in_features=n_in, out_features=1, num_cells=[hidden, hidden], activation_class=nn.ReLU)
    return ValueOperator(net, in_keys=["observation", "action"])


def train(env_id: str, cfg: OffPolicyConfig, out: str | Path, *, seed: int = 0, device="cpu", resume: bool = False, checkpoint_every: int = 10, progress: bool = True, collectors: int = 1, ray: str | None = None, tensorboard: bool | None = None) -> dict:
    """Train TD3; returns the last logged values and the frames collected."""
    run, env = common.start(env_id, "td3", cfg, out, seed=seed, device=device, resume=resume, progress=progress, tensorboard=tensorboard)
    state = run.state
    actor, qvalue = make_actor(env, cfg.hidden).to(device), make_qvalue(env, cfg.hidden).to(device)
    loss = TD3Loss(actor, qvalue, bounds=action_bounds(env), policy_noise=cfg.policy_noise, noise_clip=cfg.noise_clip, loss_function="l2")
    loss.make_value_estimator(gamma=cfg.gamma)
    target = SoftUpdate(loss, tau=cfg.tau)
    actor_optim = torch.optim.Adam(loss.actor_network_params.flatten_keys().values(), lr=cfg.lr)
    critic_optim = torch.optim.Adam(loss.qvalue_network_params.flatten_keys().values(), lr=cfg.lr)
    if state is not None:
        loss.load_state_dict(state["loss"])
        actor_optim.load_state_dict(state["actor_optim"])
        critic_optim.load_state_dict(state["critic_optim"])
    noise = AdditiveGaussianModule(spec=env.action_spec, sigma_init=cfg.exploration_sigma, sigma_end=cfg.exploration_sigma, annealing_num_steps=1)
    policy = TensorDictSequential(actor, noise)
    updates = 0

    def update(sample) -> float:
        nonlocal updates
        updates += 1
        critic_loss = loss.value_loss(sample)[0]
        critic_optim.zero_grad()
        critic_loss.backward()
        critic_optim.step()
        if updates % ACTOR_DELAY == 0:
            actor_loss = loss.actor_loss(sample)[0]
            actor_optim.zero_grad()
            actor_loss.backward()
            actor_optim.step()
            target.step()
        return critic_loss.item()

    def save() -> None:
        run.save(
            seed=seed,
            config=asdict(cfg),
            actor=actor.state_dict(),
            loss=loss.state_dict(),
            actor_optim=actor_optim.state_dict(),
            critic_optim=critic_optim.state_dict(),
            obs_norm=env.transform[0].state_dict(),
        )

    return common.off_policy_train(run, env, policy, cfg, update, save, device=device, checkpoint_every=checkpoint_every, seed=seed, collectors=collectors, ray=ray)
