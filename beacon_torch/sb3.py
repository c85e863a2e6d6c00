"""Stable-Baselines3 on the batched envs: :class:`BeaconVecEnv`, a ``VecEnv`` whose
``n_envs`` copies are the members of one batched :class:`~beacon_torch.FlowEnv`.

    from stable_baselines3 import PPO
    from beacon_torch.sb3 import BeaconVecEnv

    env = BeaconVecEnv("burgers-v0", n_envs=16)
    PPO("MlpPolicy", env).learn(500_000)

Every step is one batched tensor operation of the physics (``FlowEnv.step_members``,
the code of TorchRL's ``step``), never a loop over copies, where SB3's own
``DummyVecEnv`` steps single envs one after another. Needs the ``sb3`` extra
(``pip install beacon-torch[sb3]``).

What SB3 expects of a vector env, and how the batch provides it:

- **auto-reset**: a copy whose episode ends is reset within the same ``step``; its last
  observation is in ``infos[i]["terminal_observation"]`` and
  ``infos[i]["TimeLimit.truncated"]`` says whether the episode was cut by the time
  limit rather than terminated (a blow-up terminates);
- **seeding**: ``seed(s)`` seeds the next ``reset``; the copies share the env's one
  random stream, so ``s`` (the seed of copy 0) fixes every copy's draws. Only the envs
  with random parts draw from it (``FlowEnv.deterministic`` is False for them);
- ``get_attr``: the batched env's attributes, and the per-copy values of its parameters
  (``get_attr("Re")``); ``set_attr`` and ``env_method`` act on the batched env and so on
  every copy at once (``indices`` must name them all), except ``env_method("render")``,
  which draws the copies asked for;
- **rendering**: with ``render_mode="rgb_array"`` each copy draws its own frame
  (``get_images``) and ``render()`` tiles them as SB3 does.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
import torch

try:
    from stable_baselines3.common.vec_env import VecEnv
except ImportError as err:  # pragma: no cover - exercised without the extra only
    raise ImportError("beacon_torch.sb3 needs Stable-Baselines3: pip install 'beacon-torch[sb3]'") from err

from beacon_torch.base import make
from beacon_torch.core.checks import as_flag, as_seed
from beacon_torch.gym import _spaces, batched_action, diagnostics, member_info, reset_options, team_reward
from beacon_torch.registry import compiles_by_default

# what ``set_attr`` may change on a made env, each with its check
SETTABLE = {"render_index": lambda index: index, "check_actions": lambda flag: as_flag("check_actions", flag)}


class BeaconVecEnv(VecEnv):
    """``n_envs`` copies of ``env_id`` as one batched env, behind SB3's ``VecEnv``.

    ``render_mode`` None or ``"rgb_array"``; ``dtype``, ``device``, ``seed``,
    ``compile`` (default True: one compiled call a step, unless
    ``BEACON_TORCH_COMPILE=0``) and the env's parameters go to
    :func:`beacon_torch.make` (``BeaconVecEnv("rayleigh-v0", 16, compile=False)``)."""

    def __init__(
        self,
        env_id: str,
        n_envs: int = 1,
        *,
        render_mode: str | None = None,
        dtype: Any = "float32",
        device: Any = "cpu",
        **options: Any,
    ) -> None:
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        options.setdefault("compile", compiles_by_default())
        self.env = make(
            env_id, num_envs=n_envs, dtype=dtype, device=device, record_history=render_mode is not None, **options
        )
        self.render_mode = render_mode
        self.env_id = env_id
        observation_space, action_space = _spaces(self.env)
        self._np_dtype = observation_space.dtype
        self._actions: torch.Tensor | None = None
        super().__init__(self.env.num_envs, observation_space, action_space)

    # ------------------------------------------------------------------ stepping
    def _numpy(self, obs: torch.Tensor) -> np.ndarray:
        return obs.detach().cpu().numpy().astype(self._np_dtype)

    def reset(self) -> np.ndarray:
        for options in self._options:  # set_options's: none is taken
            reset_options(self.env, options or None, ())
        seed = self._seeds[0]
        if seed is not None:
            self.env.set_seed(int(seed))
        obs = self._numpy(self.env.reset_members())
        values = diagnostics(self.env)
        self.reset_infos = [member_info(values, i) for i in range(self.num_envs)]
        # as in SB3's own vector envs, seeds and options apply to one reset only
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = batched_action(self.env, actions, self.num_envs)

    def step_wait(self):
        if self._actions is None:
            raise RuntimeError(f"{self.env_id}: step_wait() without step_async()")
        action, self._actions = self._actions, None
        obs, reward, terminated, truncated = self.env.step_members(action)
        done = terminated | truncated
        obs = self._numpy(obs)
        time_limit = (truncated & ~terminated).cpu().numpy()
        values = diagnostics(self.env, terminated)  # of the step's last state, before any reset
        infos: list[dict[str, Any]] = [
            {**member_info(values, i), "TimeLimit.truncated": bool(cut)} for i, cut in enumerate(time_limit)
        ]
        ended = done.cpu().numpy()
        if ended.any():
            for i in np.flatnonzero(ended):
                infos[i]["terminal_observation"] = obs[i].copy()
            obs = self._numpy(self.env.reset_members(done))
        return obs, team_reward(self.env, reward).astype(np.float32), ended, infos

    def close(self) -> None:
        """Free the batched env; stepping or resetting afterwards is an error."""
        self._actions = None
        self.env.close(raise_if_closed=False)

    # ------------------------------------------------------------------ attributes
    def _indices(self, indices) -> list[int]:
        chosen = list(self._get_indices(indices))
        for i in chosen:
            if not 0 <= int(i) < self.num_envs:
                raise IndexError(f"{self.env_id}: copy index {i} is outside [0, {self.num_envs})")
        return [int(i) for i in chosen]

    def _all(self, indices, what: str) -> list[int]:
        chosen = self._indices(indices)
        if sorted(set(chosen)) != list(range(self.num_envs)):
            raise ValueError(
                f"{self.env_id}: the copies are one batched env, so {what} acts on all "
                f"{self.num_envs} of them at once; got indices {chosen}"
            )
        return chosen

    def get_attr(self, attr_name: str, indices: Iterable[int] | int | None = None) -> list[Any]:
        chosen = self._indices(indices)
        if attr_name == "render_mode":
            return [self.render_mode for _ in chosen]
        params = self.env.params
        if hasattr(params, attr_name):
            value = getattr(params, attr_name)
            if isinstance(value, torch.Tensor) and value.ndim >= 1 and value.shape[0] == self.num_envs:
                return [value[i].item() if value[i].numel() == 1 else value[i].cpu().numpy() for i in chosen]
            return [value for _ in chosen]
        value = getattr(self.env, attr_name)  # AttributeError names the attribute
        return [value for _ in chosen]

    def set_attr(self, attr_name: str, value: Any, indices: Iterable[int] | int | None = None) -> None:
        """Set one of :data:`SETTABLE` on the batched env (the copies' parameters,
        size, precision and device are fixed when it is made)."""
        self._all(indices, f"set_attr({attr_name!r})")
        if attr_name not in SETTABLE:
            fixed = "a parameter of the env" if hasattr(self.env.params, attr_name) else "not settable"
            raise AttributeError(
                f"{self.env_id}: {attr_name!r} is {fixed}; set_attr sets {', '.join(SETTABLE)} "
                f"(make a new BeaconVecEnv for other settings)"
            )
        setattr(self.env, attr_name, SETTABLE[attr_name](value))

    def seed(self, seed: int | None = None) -> Sequence[int | None]:
        # an integer of the generator's range (not 1.5, not "a"), or None for a random one
        return super().seed(None if seed is None else as_seed(seed))

    def env_method(
        self, method_name: str, *method_args, indices: Iterable[int] | int | None = None, **method_kwargs
    ) -> list[Any]:
        if method_name == "render":
            return [self._render_copy(i) for i in self._indices(indices)]
        chosen = self._all(indices, f"env_method({method_name!r})")
        result = getattr(self.env, method_name)(*method_args, **method_kwargs)
        return [result for _ in chosen]

    def env_is_wrapped(self, wrapper_class: type, indices: Iterable[int] | int | None = None) -> list[bool]:
        # the copies are members of a tensor batch: no gymnasium wrapper can sit on one
        return [False for _ in self._indices(indices)]

    # ------------------------------------------------------------------ rendering
    def _render_copy(self, index: int) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        self.env.render_index = index
        return self.env.render()

    def get_images(self) -> Sequence[np.ndarray | None]:
        return [self._render_copy(i) for i in range(self.num_envs)]
