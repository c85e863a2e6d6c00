"""TorchRL's multi-agent layout, shared by the envs whose actuators are agents
(``shkadov-separable-v0``, ``rayleigh-separable-v0``): per-agent observation, action and
reward under the ``"agents"`` sub-TensorDict, the agent dimension after the batch; the
done flags shared, at the root. One policy applied per agent fits any number of them.
"""

from __future__ import annotations

from typing import ClassVar

import torch
from tensordict import TensorDict
from torchrl.data import Composite, Unbounded


class AgentsLayout:
    """Mixin of a :class:`~beacon_torch.base.FlowEnv` whose physics observes
    ``[B, n_agents, n]``, acts ``[B, n_agents, 1]`` and rewards ``[B, n_agents]``."""

    action_key = ("agents", "action")
    observation_key = ("agents", "observation")
    reward_key = ("agents", "reward")
    agent_name: ClassVar[str]  # an agent's name in PettingZoo is f"{agent_name}_{i}"

    @property
    def n_agents(self) -> int:
        return self.physics.action_shape[0]

    def _make_specs(self) -> None:
        super()._make_specs()
        B, dev = self.batch_size, self.device
        per_agent = self.physics.n_obs // self.n_agents
        agents = (*B, self.n_agents)
        self.observation_spec = Composite(
            agents=Composite(
                observation=Unbounded(shape=(*agents, per_agent), dtype=self.dtype, device=dev),
                shape=agents,
                device=dev,
            ),
            shape=B,
            device=dev,
        )
        self.full_action_spec = Composite(
            agents=Composite(action=self._action_leaf_spec((*agents, 1)), shape=agents, device=dev),
            shape=B,
            device=dev,
        )
        self.full_reward_spec = Composite(
            agents=Composite(
                reward=Unbounded(shape=(*agents, 1), dtype=self.dtype, device=dev), shape=agents, device=dev
            ),
            shape=B,
            device=dev,
        )

    def _pack(self, obs: torch.Tensor, reward: torch.Tensor | None) -> dict:
        agents = {"observation": obs}
        if reward is not None:
            agents["reward"] = reward[..., None]
        return {"agents": TensorDict(agents, batch_size=(*self.batch_size, self.n_agents), device=self.device)}
