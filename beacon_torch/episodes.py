"""Whole-episode rollouts and their scores."""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase

from beacon_torch import seeds
from beacon_torch.base import FlowEnv

Policy = Callable[[TensorDictBase], TensorDictBase]


def null_policy(env: FlowEnv) -> Policy:
    """The benchmark's "no control" action, held for the whole episode."""
    return lambda td: td.set(env.action_key, env.null_action())


def random_policy(env: FlowEnv, seed: int = 0) -> Policy:
    """Uniformly random actions from a generator of its own, seeded by ``seed``."""
    g = seeds.generator(seed, env.device)
    return lambda td: td.set(env.action_key, env.random_action(g))


def episode(
    env: FlowEnv,
    policy: Policy,
    *,
    frame_hook: Callable[[int], None] | None = None,
    progress: str | None = None,
) -> TensorDictBase:
    """One full episode of every batch member, as TorchRL's ``rollout`` returns it
    (``[batch, episode_length]``). ``frame_hook(step)`` runs after each step (rendering);
    ``progress``: a progress bar (on stderr) with this title."""
    with progress_bar(progress, env.episode_length) as bar:

        def callback(env_, td):
            bar.update()
            if frame_hook is not None:
                frame_hook(int(env_.step_count[env_.render_index]))

        return env.rollout(
            env.episode_length,
            policy=policy,
            break_when_any_done=False,
            # members whose episode ended (a blow-up) stop stepping; the others go on
            break_when_all_done=True,
            callback=callback,
        )


def progress_bar(title: str | None, actions: int):
    """A progress bar over ``actions`` steps, on stderr and gone when done; a bar that
    shows nothing when ``title`` is None."""
    from tqdm.auto import tqdm

    return tqdm(total=actions, desc=title, unit="actions", leave=False, disable=title is None)


def step_rewards(rollout: TensorDictBase) -> torch.Tensor:
    """``[batch, steps]`` rewards in float64; for multi-agent variants the team's reward,
    the mean over the agents."""
    if ("next", "agents", "reward") in rollout.keys(include_nested=True):
        return rollout["next", "agents", "reward"][..., 0].to(torch.float64).mean(-1)
    return rollout["next", "reward"][..., 0].to(torch.float64)


def scores(rollout: TensorDictBase) -> torch.Tensor:
    """Episode score (sum of rewards up to the end of the first episode) of each member,
    in float64. Steps after a member's end repeat its last entry in TorchRL's rollout
    and are not counted."""
    return (step_rewards(rollout) * _in_episode(rollout)).sum(-1)


def episode_means(values: torch.Tensor, rollout: TensorDictBase) -> torch.Tensor:
    """The mean of ``[batch, steps]`` per-step ``values`` (a diagnostic of ``rollout``)
    over each member's first episode, in float64."""
    in_episode = _in_episode(rollout)
    return (values.to(torch.float64) * in_episode).sum(-1) / in_episode.sum(-1)


def _in_episode(rollout: TensorDictBase) -> torch.Tensor:
    """``[batch, steps]``: True up to and with each member's first end."""
    done = rollout["next", "done"][..., 0].to(torch.int64)
    return (done.cumsum(-1) - done) == 0
