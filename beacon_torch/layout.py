"""Where an env's observation, action and reward sit in its TensorDicts: one agent per
member (the entries at the root), or TorchRL's multi-agent layout for the envs whose
actuators are agents (``shkadov-separable-v0``, ``rayleigh-separable-v0``): per-agent
observation, action and reward under the ``"agents"`` sub-TensorDict, the agent
dimension after the batch, the done flags shared at the root. One policy applied per
agent fits any number of them."""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDict
from torchrl.data import Composite, TensorSpec, Unbounded


class Members:
    """One agent per member: ``observation`` ``[B, n_obs]``, ``action`` ``[B, ...]`` and
    ``reward`` ``[B, 1]`` at the root."""

    action_key: str | tuple[str, ...] = "action"
    observation_key: str | tuple[str, ...] = "observation"
    reward_key: str | tuple[str, ...] = "reward"
    agent_name: str | None = None
    n_agents: int = 1

    def __init__(self, batch_size: torch.Size, device: torch.device, dtype: torch.dtype) -> None:
        self.batch_size, self.device, self.dtype = batch_size, device, dtype

    def specs(
        self, n_obs: int, action_shape: tuple[int, ...], action_leaf: Callable[[tuple[int, ...]], TensorSpec]
    ) -> dict[str, Composite | TensorSpec]:
        """The observation, action and reward specs of an env whose physics observes
        ``n_obs`` numbers and acts ``action_shape`` per member, its action leaves made by
        ``action_leaf(shape)``."""
        B, dev = self.batch_size, self.device
        return {
            "observation_spec": Composite(
                observation=Unbounded(shape=(*B, n_obs), dtype=self.dtype, device=dev), shape=B, device=dev
            ),
            "action_spec": action_leaf((*B, *action_shape)),
            "reward_spec": Unbounded(shape=(*B, 1), dtype=self.dtype, device=dev),
        }

    def pack(self, obs: torch.Tensor, reward: torch.Tensor | None) -> dict:
        """TensorDict entries of an observation and a reward (``[B]``)."""
        out = {"observation": obs}
        if reward is not None:
            out["reward"] = reward[:, None]
        return out


class Agents(Members):
    """The physics' actuators as agents named ``f"{agent_name}_{i}"``: it observes
    ``[B, n_agents, n]``, acts ``[B, n_agents, 1]`` and rewards ``[B, n_agents]``."""

    action_key = ("agents", "action")
    observation_key = ("agents", "observation")
    reward_key = ("agents", "reward")

    def __init__(
        self, agent_name: str, n_agents: int, batch_size: torch.Size, device: torch.device, dtype: torch.dtype
    ) -> None:
        super().__init__(batch_size, device, dtype)
        self.agent_name, self.n_agents = agent_name, n_agents

    def specs(self, n_obs, action_shape, action_leaf):
        B, dev = self.batch_size, self.device
        agents = (*B, self.n_agents)
        nested = lambda **leaves: Composite(agents=Composite(**leaves, shape=agents, device=dev), shape=B, device=dev)
        per_agent = n_obs // self.n_agents
        return {
            "observation_spec": nested(observation=Unbounded(shape=(*agents, per_agent), dtype=self.dtype, device=dev)),
            "full_action_spec": nested(action=action_leaf((*agents, 1))),
            "full_reward_spec": nested(reward=Unbounded(shape=(*agents, 1), dtype=self.dtype, device=dev)),
        }

    def pack(self, obs: torch.Tensor, reward: torch.Tensor | None) -> dict:
        agents = {"observation": obs}
        if reward is not None:
            agents["reward"] = reward[..., None]
        return {"agents": TensorDict(agents, batch_size=(*self.batch_size, self.n_agents), device=self.device)}
