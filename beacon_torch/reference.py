"""Per-step agreement with the published BEACON code.

``data/reference-rollouts.json`` holds, for the five deterministic envs of the published
code (lorenz, vortex, sloshing, rayleigh, mixing), the actions of one seeded open-loop
episode (seed 2026, float64), the reward the published code returned for each, and its
first and last observations. :func:`replay` steps our env through the same actions from
the published start (batch of one, float64) and measures the differences.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import torch

import beacon_torch
from beacon_torch import received
from beacon_torch.cache import PACKAGE_DATA


@functools.cache
def _records() -> dict:
    records = received.json_file(PACKAGE_DATA / "reference-rollouts.json", "record of published rollouts")
    if not isinstance(records, dict) or not isinstance(records.get("envs"), dict):
        raise received.BadFile(f"{PACKAGE_DATA / 'reference-rollouts.json'}: no 'envs' in it")
    return records["envs"]


def env_ids() -> list[str]:
    """The envs with a recorded published rollout."""
    return sorted(_records())


def record(env_id: str) -> dict:
    """The published rollout of ``env_id``: ``actions``, ``rewards``,
    ``first_observation``, ``last_observation``, ``return``."""
    try:
        return _records()[env_id]
    except KeyError:
        raise ValueError(f"no published rollout of {env_id!r}; there are: {', '.join(env_ids())}") from None


@dataclass
class Agreement:
    env_id: str
    steps: int
    rewards: np.ndarray  # ours, per step
    published: np.ndarray  # the published code's, per step
    first_observation_error: float  # max |ours - published|
    last_observation_error: float | None  # the same after the whole episode, else None

    @property
    def running_error(self) -> np.ndarray:
        """|our running return - the published one| / |the published one| per step
        (absolute where the published running return is 0)."""
        ours, theirs = np.cumsum(self.rewards), np.cumsum(self.published)
        scale = np.where(theirs == 0.0, 1.0, np.abs(theirs))
        return np.abs(ours - theirs) / scale

    def summary(self) -> str:
        worst = self.running_error.max()
        last = "" if self.last_observation_error is None else f", last observation {self.last_observation_error:.2e}"
        return (
            f"{self.env_id}: {self.steps} actions, return {self.rewards.sum():.10g} "
            f"(published {self.published.sum():.10g}), largest relative difference of the "
            f"running return {worst:.2e}, first observation {self.first_observation_error:.2e}{last}"
        )


def replay(env_id: str, n_actions: int | None = None, **params) -> Agreement:
    """Step ``env_id`` (batch 1, float64, published start, ``params`` as for
    :func:`beacon_torch.make`) through the first ``n_actions`` recorded actions (all by
    default) and compare with the published code's rewards and observations."""
    rec = record(env_id)
    actions = rec["actions"][:n_actions] if n_actions else rec["actions"]
    env = beacon_torch.make(env_id, 1, dtype=torch.float64, **params)
    td = env.reset()
    first = td[env.observation_key][0].numpy()
    dtype = torch.int64 if env.discrete else torch.float64
    rewards = []
    for a in actions:
        td[env.action_key] = torch.tensor([a], dtype=dtype).reshape(1, *env.action_shape)
        td = env.step(td)["next"]
        rewards.append(td[env.reward_key].item())
    last = None
    if len(actions) == len(rec["actions"]):
        last = float(np.abs(td[env.observation_key][0].numpy() - np.array(rec["last_observation"])).max())
    return Agreement(
        env_id=env_id,
        steps=len(actions),
        rewards=np.array(rewards),
        published=np.array(rec["rewards"][: len(actions)]),
        first_observation_error=float(np.abs(first - np.array(rec["first_observation"])).max()),
        last_observation_error=last,
    )
