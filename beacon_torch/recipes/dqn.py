"""DQN on a BEACON env with discrete actions (lorenz-v0, mixing-v0), from TorchRL's
pieces: ``DQNLoss`` (double DQN, a target network through ``SoftUpdate``), a
``QValueActor``, epsilon-greedy exploration (``EGreedyModule``), a ``Collector`` over
the batched env and a ``ReplayBuffer`` (the loop is ``common.off_policy_train``).

    beacon-torch train lorenz-v0 --algo dqn --frames 200000
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import torch
from tensordict.nn import TensorDictSequential
from torch import nn
from torchrl.modules import MLP, EGreedyModule, QValueActor
from torchrl.objectives import DQNLoss, SoftUpdate

from beacon_torch.recipes import common
from beacon_torch.recipes.config import OffPolicyConfig


def make_qvalue_actor(env, hidden: int) -> QValueActor:
    """Action values of every discrete action; the greedy action is the policy."""
    n_obs = env.observation_spec["observation"].shape[-1]
    net = MLP(in_features=n_obs, out_features=env.base_env.n_actions, num_cells=[hidden, hidden], activation_class=nn.ReLU)
    return QValueActor(net, in_keys=["observation"], action_space="categorical")


def train(env_id: str, cfg: OffPolicyConfig, out: str | Path, *, seed: int = 0, device="cpu", resume: bool = False, checkpoint_every: int = 10, progress: bool = True, collectors: int = 1, ray: str | None = None, tensorboard: bool | None = None) -> dict:
    """Train DQN; returns the last logged values and the frames collected."""
    run, env = common.start(env_id, "dqn", cfg, out, seed=seed, device=device, resume=resume, progress=progress, tensorboard=tensorboard)
    state = run.state
    qvalue = make_qvalue_actor(env, cfg.hidden).to(device)
    loss = DQNLoss(qvalue, delay_value=True, double_dqn=True, action_space="categorical")
    loss.make_value_estimator(gamma=cfg.gamma)
    target = SoftUpdate(loss, tau=cfg.tau)
    optim = torch.optim.Adam(loss.parameters(), lr=cfg.lr)
    if state is not None:
        loss.load_state_dict(state["loss"])
        optim.load_state_dict(state["optim"])
    explore = EGreedyModule(spec=env.action_spec, eps_init=cfg.eps_init, eps_end=cfg.eps_end, annealing_num_steps=cfg.eps_frames)
    explore.step(run.frames)
    policy = TensorDictSequential(qvalue, explore)

    def update(sample) -> float:
        value = loss(sample)["loss"]
        optim.zero_grad()
        value.backward()
        optim.step()
        target.step()
        return value.item()

    def save() -> None:
        run.save(seed=seed, config=asdict(cfg), actor=qvalue.state_dict(), loss=loss.state_dict(), optim=optim.state_dict(), obs_norm=env.transform[0].state_dict())

    return common.off_policy_train(run, env, policy, cfg, update, save, device=device, checkpoint_every=checkpoint_every, seed=seed, collectors=collectors, ray=ray, on_batch=explore.step)
