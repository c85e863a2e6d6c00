"""Gymnasium interop: every env is registered with gymnasium as ``beacon/<id>`` when
beacon_torch is imported (``gymnasium.make("beacon_torch:beacon/<id>")`` imports it:
gymnasium's own ``module:id`` spelling, since gymnasium 1.0 has no plugin entry points),
with ``max_episode_steps`` the env's episode length.

``gymnasium.make("beacon/lorenz-v0")`` gives :class:`BeaconGymEnv`, a standard single
environment with numpy observations over a batch-of-one :class:`~beacon_torch.FlowEnv`.
``gymnasium.make_vec("beacon/lorenz-v0", num_envs=64)`` gives :class:`BeaconVectorEnv`,
which steps all copies in one batched tensor operation (next-step autoreset, gymnasium's
default). Environment parameters pass through as keyword arguments of either call, and
so do ``compile`` and the env's other options. Both compile their env unless given
``compile=False`` (:func:`~beacon_torch.registry.compiles_by_default`): the first step of a
process then compiles (seconds to a minute, once per env and shape while torch's
on-disk caches are warm), and every step after is one compiled call.

Both step the env through :meth:`FlowEnv.step_members`, the same code as TorchRL's
``step`` (checks, blow-up handling, trajectories bit for bit) without building
TensorDicts or running TorchRL's step wrappers, which at a batch of one cost more than
the physics of the fast envs.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from beacon_torch import gym_ids
from beacon_torch.base import FlowEnv, make
from beacon_torch.registry import compiles_by_default, env_spec, list_envs

NAMESPACE = gym_ids.NAMESPACE
RENDER_FPS = 20


gym_id = gym_ids.gym_id


def _spaces(env: FlowEnv) -> tuple[spaces.Space, spaces.Space]:
    np_dtype = np.float64 if env.dtype == torch.float64 else np.float32
    obs_shape = tuple(env.full_observation_spec[env.observation_key].shape[1:])
    obs = spaces.Box(-np.inf, np.inf, shape=obs_shape, dtype=np_dtype)
    if env.discrete:
        act = spaces.Discrete(env.n_actions)
    else:
        act = spaces.Box(-1.0, 1.0, shape=env.action_shape, dtype=np_dtype)
    return obs, act


def team_reward(env: FlowEnv, reward: torch.Tensor) -> np.ndarray:
    """``[batch]`` float64 rewards of :meth:`FlowEnv.step_members`; for multi-agent
    variants, the mean over the agents."""
    if reward.ndim == 1:
        return reward.detach().cpu().numpy().astype(np.float64)
    return reward.detach().to(torch.float64).reshape(env.num_envs, -1).mean(-1).cpu().numpy()


def diagnostics(env: FlowEnv, terminated: torch.Tensor | None = None) -> dict[str, np.ndarray]:
    """What every adapter puts in its info, per member (``[batch]`` arrays): the env's
    :attr:`~beacon_torch.base.FlowEnv.diagnostics` of the current state (float64) and
    ``blew_up``, whether the last step ended the member's episode by a blow-up (its
    termination: an episode of these envs ends otherwise only by its length)."""
    out = {name: value.detach().to(torch.float64).cpu().numpy() for name, value in env.last_diagnostics.items()}
    blew = torch.zeros(env.num_envs, dtype=torch.bool) if terminated is None else terminated.detach().cpu()
    out["blew_up"] = blew.numpy().copy()
    return out


def reset_options(env, options: Any, known: tuple[str, ...]) -> None:
    """Refuse reset options that the adapter does not take (a misspelt key would
    otherwise be ignored and the reset do what was not asked), as the TorchRL env
    refuses unknown keywords."""
    if options is None:
        return
    if not isinstance(options, dict):
        raise TypeError(f"{env.env_id}: reset options must be a dict, got {type(options).__name__}")
    unknown = sorted(str(k)[:40] for k in options if k not in known)
    if unknown:
        takes = f"it takes {list(known)}" if known else "it takes none"
        raise ValueError(f"{env.env_id}: unknown reset option(s) {unknown}; {takes}")


def member_info(values: dict[str, np.ndarray], i: int) -> dict[str, Any]:
    """Member ``i``'s entries of :func:`diagnostics` as Python numbers."""
    return {name: (bool if name == "blew_up" else float)(v[i]) for name, v in values.items()}


def batched_action(env: FlowEnv, action: Any, batch: int) -> torch.Tensor:
    """numpy/python actions of a gymnasium caller as the env's action batch."""
    a = np.asarray(action)
    if env.discrete:
        if a.dtype.kind not in "iu":
            raise TypeError(f"{env.env_id}: action must be an integer in [0, {env.n_actions - 1}], got {action!r}")
        if a.size != batch:
            raise ValueError(f"{env.env_id}: expected {batch} discrete action(s), got shape {a.shape}")
        return torch.as_tensor(a.reshape(batch).astype(np.int64))
    if a.dtype.kind not in "fiu":
        raise TypeError(f"{env.env_id}: action must be floats in [-1, 1], got dtype {a.dtype}")
    full = (batch, *env.action_shape)
    expected = full if batch > 1 else env.action_shape
    if a.shape != expected and a.shape != full:
        raise ValueError(f"{env.env_id}: action must have shape {expected}, got {a.shape}")
    # straight to the env's dtype: the conversion torch would make, without a tensor copy
    return torch.as_tensor(a.reshape(full).astype(np.float32 if env.dtype == torch.float32 else np.float64))


class BeaconGymEnv(gymnasium.Env):
    """A single BEACON environment behind the standard ``gymnasium.Env`` interface."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": RENDER_FPS}

    def __init__(
        self,
        env_id: str | None = None,
        render_mode: str | None = None,
        dtype: Any = "float32",
        *,
        registered_id: str | None = None,
        **params: Any,
    ):
        env_id = _own_id(env_id, registered_id)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        params.setdefault("compile", compiles_by_default())
        self.env = make(env_id, num_envs=1, dtype=dtype, record_history=render_mode is not None, **params)
        self.observation_space, self.action_space = _spaces(self.env)
        self._np_dtype = self.observation_space.dtype

    def _numpy(self, obs: torch.Tensor) -> np.ndarray:
        return obs[0].detach().cpu().numpy().astype(self._np_dtype)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        reset_options(self.env, options, ())
        super().reset(seed=seed)
        if seed is not None:
            self.env.set_seed(seed)
        obs = self.env.reset_members()
        return self._numpy(obs), member_info(diagnostics(self.env), 0)

    def step(self, action):
        obs, reward, terminated, truncated = self.env.step_members(batched_action(self.env, action, 1))
        info = member_info(diagnostics(self.env, terminated), 0)
        return self._numpy(obs), float(team_reward(self.env, reward)[0]), bool(terminated[0]), bool(truncated[0]), info

    def render(self):
        if self.render_mode == "rgb_array":
            return self.env.render()
        return None


class BeaconVectorEnv(VectorEnv):
    """``num_envs`` copies of a BEACON env stepped as one batch (next-step autoreset).

    As in gymnasium's own vector envs, the step after a copy's episode ended resets that
    copy (its action is ignored) and returns its first observation with zero reward.
    """

    metadata = {
        "render_modes": ["rgb_array"],
        "render_fps": RENDER_FPS,
        "autoreset_mode": AutoresetMode.NEXT_STEP,
    }

    def __init__(
        self,
        env_id: str | None = None,
        num_envs: int = 1,
        render_mode: str | None = None,
        dtype: Any = "float32",
        device: Any = "cpu",
        *,
        registered_id: str | None = None,
        max_episode_steps: int | None = None,
        **params: Any,
    ):
        env_id = _own_id(env_id, registered_id)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        length = env_spec(env_id).physics.episode_length
        if max_episode_steps not in (None, length):
            # the batched env truncates its members itself, at the benchmark's length
            raise ValueError(
                f"{env_id}'s episodes are {length} actions long (the benchmark's); max_episode_steps="
                f"{max_episode_steps} applies to gymnasium.make's single env (its TimeLimit), not to make_vec"
            )
        params.setdefault("compile", compiles_by_default())
        self.env = make(
            env_id,
            num_envs=num_envs,
            dtype=dtype,
            device=device,
            record_history=render_mode is not None,
            **params,
        )
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.single_observation_space, self.single_action_space = _spaces(self.env)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._np_dtype = self.single_observation_space.dtype
        self._autoreset = np.zeros(num_envs, dtype=bool)

    def _obs(self) -> np.ndarray:
        return self.env.observation.cpu().numpy().astype(self._np_dtype)

    def reset(self, *, seed: int | list[int] | None = None, options: dict | None = None):
        if isinstance(seed, (list, tuple)):
            # the copies draw from one random stream, seeded once: a list can only be
            # the seeds gymnasium derives from one (s, s + 1, ...) or s for copy 0 alone
            first = seed[0] if len(seed) == self.num_envs else None
            if not isinstance(first, int) or list(seed) not in (
                [first + i for i in range(self.num_envs)],
                [first] + [None] * (self.num_envs - 1),
            ):
                raise ValueError(
                    f"{self.env.env_id}: the {self.num_envs} copies share one random stream, so "
                    f"they take one seed (or s, s + 1, ...), not {list(seed)}"
                )
            seed = first
        reset_options(self.env, options, ("reset_mask",))
        super().reset(seed=seed)
        if seed is not None:
            self.env.set_seed(seed)
        mask = None if options is None else options.get("reset_mask")
        if mask is None:
            self.env.reset_members()
            self._autoreset[:] = False
        else:
            given = np.asarray(mask)
            if given.dtype != np.bool_ or given.size != self.num_envs:
                raise ValueError(
                    f"{self.env.env_id}: options['reset_mask'] must hold one bool per copy ({self.num_envs}), "
                    f"got {given.size} values of dtype {given.dtype}"
                )
            mask = given.reshape(self.num_envs)
            self.env.reset_members(torch.as_tensor(mask))
            self._autoreset[mask] = False
        return self._obs(), self._info(diagnostics(self.env))

    def _info(self, values: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """gymnasium's vector info: each entry's values and its mask of copies (all)."""
        info = {}
        for name, v in values.items():
            info[name], info[f"_{name}"] = v, np.ones(self.num_envs, dtype=bool)
        return info

    def step(self, actions):
        _, reward, terminated, truncated = self.env.step_members(batched_action(self.env, actions, self.num_envs))
        values = diagnostics(self.env, terminated)
        obs = self._obs()
        reward = team_reward(self.env, reward)
        terminated = terminated.cpu().numpy().copy()
        truncated = truncated.cpu().numpy().copy()
        if self._autoreset.any():
            self.env.reset_members(torch.as_tensor(self._autoreset))
            obs[self._autoreset] = self._obs()[self._autoreset]
            reward[self._autoreset] = 0.0
            terminated[self._autoreset] = False
            truncated[self._autoreset] = False
            # the copies reset here report their first state, as their observation does
            fresh = diagnostics(self.env)
            for name, v in values.items():
                v[self._autoreset] = fresh[name][self._autoreset] if name != "blew_up" else False
        self._autoreset = terminated | truncated
        return obs, reward, terminated, truncated, self._info(values)

    def render(self):
        if self.render_mode == "rgb_array":
            return self.env.render()
        return None


def _own_id(env_id: str | None, registered_id: str | None) -> str:
    """The env a gymnasium id stands for: ``env_id`` given to ``gymnasium.make`` beside
    an id of ours may only repeat it."""
    if registered_id is None:
        if env_id is None:
            raise TypeError("an env id is needed (e.g. 'burgers-v0')")
        return env_id
    if env_id is not None and env_id != registered_id:
        raise ValueError(
            f"{gym_id(registered_id)} is {registered_id}, so env_id={env_id!r} cannot change it; "
            f"make {gym_id(env_id)!r} instead"
        )
    return registered_id


def register(env_id: str | None = None) -> None:
    """Register ``env_id`` (by default every env id of the registry) with gymnasium
    (idempotent; ``beacon_torch.register`` registers each new id there too)."""
    for own in [env_id] if env_id else list_envs():
        gym_ids.register(own, env_spec(own).physics.episode_length)


register()
