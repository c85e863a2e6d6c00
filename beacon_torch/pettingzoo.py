"""PettingZoo's parallel API for the multi-agent layouts (``shkadov-separable-v0``,
``rayleigh-separable-v0``): :class:`BeaconParallelEnv`, each agent an actuator (a jet, a
heated segment) of one batch member.

    from beacon_torch.pettingzoo import parallel_env   # pip install "beacon-torch[pettingzoo]"

    env = parallel_env("shkadov-separable-v0", n_jets=5)
    observations, infos = env.reset(seed=0)
    while env.agents:
        actions = {agent: env.action_space(agent).sample() for agent in env.agents}
        observations, rewards, terminations, truncations, infos = env.step(actions)

The agents (``jet_0`` ... ``jet_{n-1}``) act together on one film: each observes the
flow rate upstream of its jet, sets its jet's strength in ``[-1, 1]`` and is rewarded
by the flatness downstream of it (their mean is the single-agent ``shkadov-v0``
reward); on ``rayleigh-separable-v0`` the agents ``segment_0`` ... are the heated segments
of the convection channel. An episode ends for all of them at once, at the episode length or when the
film blows up. The step is :meth:`FlowEnv.step_members` of a batch of one, the code of
TorchRL's ``step`` (checks, blow-ups, trajectories bit for bit). PettingZoo's
``parallel_api_test`` passes (tested).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv

from beacon_torch.base import make
from beacon_torch.gym import diagnostics, member_info
from beacon_torch.registry import env_spec, list_envs


def multi_agent_envs() -> list[str]:
    """The ids whose envs have the multi-agent layout (agents under ``"agents"``)."""
    return [e for e in list_envs() if env_spec(e).agents is not None]


class BeaconParallelEnv(ParallelEnv):
    """PettingZoo's ``ParallelEnv`` over one member of a multi-agent env (see the
    module's docstring). Physical parameters and the env's options are keywords, as
    in :func:`beacon_torch.make`."""

    metadata = {"name": "beacon_parallel_v0", "render_modes": ["rgb_array"], "is_parallelizable": True}

    def __init__(
        self,
        env_id: str = "shkadov-separable-v0",
        render_mode: str | None = None,
        dtype: Any = "float32",
        device: Any = "cpu",
        **params: Any,
    ):
        if env_spec(env_id).agents is None:
            raise ValueError(
                f"{env_id} has one agent; PettingZoo's API is for the multi-agent layouts: {multi_agent_envs()}"
            )
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.env = make(env_id, 1, dtype=dtype, device=device, record_history=render_mode is not None, **params)
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "name": env_id.replace("-", "_")}
        obs_spec = self.env.full_observation_spec[self.env.observation_key]
        n_agents, n_obs = obs_spec.shape[1:]
        self.possible_agents = [f"{self.env.agent_name}_{i}" for i in range(n_agents)]
        self.agents: list[str] = []
        np_dtype = np.float64 if self.env.dtype == torch.float64 else np.float32
        self._observation_space = spaces.Box(-np.inf, np.inf, shape=(n_obs,), dtype=np_dtype)
        self._action_space = spaces.Box(-1.0, 1.0, shape=(1,), dtype=np_dtype)

    def _known(self, agent: Any) -> str:
        if agent not in self.possible_agents:
            raise ValueError(
                f"{self.env.env_id}: unknown agent {str(agent)[:60]!r}; the agents are "
                f"{self.possible_agents[0]} ... {self.possible_agents[-1]}"
            )
        return agent

    def observation_space(self, agent: str) -> spaces.Box:
        self._known(agent)
        return self._observation_space

    def action_space(self, agent: str) -> spaces.Box:
        self._known(agent)
        return self._action_space

    def _action(self, agent: str, value: Any) -> float:
        """One agent's action as a number, refused in one line naming the agent unless
        it is a real number or an array of one real number."""
        expected = f"a real number in [-1, 1] (or an array of shape (1,)), got {str(value)[:40]!r}"
        where = f"{self.env.env_id}: the action of {agent} must be"
        if isinstance(value, torch.Tensor):
            value = value.detach().cpu().numpy()
        if value is None or isinstance(value, (bool, np.bool_, str, bytes)):
            raise TypeError(f"{where} {expected}")
        try:
            array = np.asarray(value)
        except (TypeError, ValueError):
            raise TypeError(f"{where} {expected}") from None
        if array.dtype.kind not in "fiu":
            raise TypeError(f"{where} {expected} (of dtype {array.dtype})")
        if array.shape not in ((), (1,)):
            raise ValueError(f"{where} {expected} (of shape {array.shape})")
        return float(array.reshape(()))

    def _observations(self, obs: torch.Tensor) -> dict[str, np.ndarray]:
        values = obs[0].detach().cpu().numpy().astype(self._observation_space.dtype)
        return {agent: values[i] for i, agent in enumerate(self.possible_agents)}

    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self.env.set_seed(seed)
        obs = self.env.reset_members()
        self.agents = list(self.possible_agents)
        info = member_info(diagnostics(self.env), 0)
        return self._observations(obs), {agent: dict(info) for agent in self.agents}

    def step(self, actions: dict[str, Any]):
        if not self.agents:
            raise RuntimeError(f"{self.env.env_id}: the episode has ended; call reset()")
        if not isinstance(actions, dict):
            raise TypeError(
                f"{self.env.env_id}: actions must be a dict of agent to action, got {type(actions).__name__}"
            )
        unknown = [str(agent)[:60] for agent in actions if agent not in self.agents]
        if unknown:
            raise ValueError(
                f"{self.env.env_id}: actions for unknown agents {unknown[:3]}; the agents are "
                f"{self.agents[0]} ... {self.agents[-1]}"
            )
        missing = [agent for agent in self.agents if agent not in actions]
        if missing:
            raise ValueError(f"{self.env.env_id}: no action for {missing}; every agent acts at each step")
        action = [[self._action(agent, actions[agent])] for agent in self.possible_agents]
        obs, reward, terminated, truncated = self.env.step_members(torch.tensor(action, dtype=torch.float64)[None])
        rewards = reward[0].detach().cpu().to(torch.float64).numpy()
        ended_by = (bool(terminated[0]), bool(truncated[0]))
        agents = self.agents
        info = member_info(diagnostics(self.env, terminated), 0)  # the flow's, shared by the agents
        out = (
            self._observations(obs),
            {agent: float(rewards[i]) for i, agent in enumerate(agents)},
            {agent: ended_by[0] for agent in agents},
            {agent: ended_by[1] for agent in agents},
            {agent: dict(info) for agent in agents},
        )
        if any(ended_by):
            self.agents = []
        return out

    def render(self):
        return self.env.render() if self.render_mode == "rgb_array" else None

    def close(self) -> None:
        self.env.close()


def parallel_env(env_id: str = "shkadov-separable-v0", **kwargs: Any) -> BeaconParallelEnv:
    """PettingZoo's conventional constructor: :class:`BeaconParallelEnv`."""
    return BeaconParallelEnv(env_id, **kwargs)
