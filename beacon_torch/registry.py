"""Environment ids and their classes."""

from __future__ import annotations

import os
from typing import Any

from beacon_torch.base import FlowEnv
from beacon_torch.envs.burgers import BurgersEnv
from beacon_torch.envs.lorenz import LorenzContinuousEnv, LorenzEnv
from beacon_torch.envs.mixing import MixingContinuousEnv, MixingEnv
from beacon_torch.envs.rayleigh import RayleighEnv
from beacon_torch.envs.shkadov import ShkadovEnv, ShkadovSeparableEnv
from beacon_torch.envs.sloshing import SloshingEnv
from beacon_torch.envs.vortex import VortexEnv

ENVS: dict[str, type[FlowEnv]] = {
    cls.env_id: cls
    for cls in (
        LorenzEnv,
        LorenzContinuousEnv,
        VortexEnv,
        BurgersEnv,
        SloshingEnv,
        ShkadovEnv,
        ShkadovSeparableEnv,
        RayleighEnv,
        MixingEnv,
        MixingContinuousEnv,
    )
}


def list_envs() -> list[str]:
    """The registered environment ids, sorted."""
    return sorted(ENVS)


def base_envs() -> list[str]:
    """The benchmark's own envs, without their variants, in the paper's order."""
    return [env_id for env_id, cls in ENVS.items() if cls.base_id() == env_id]


def env_class(env_id: str) -> type[FlowEnv]:
    if not isinstance(env_id, str):
        raise TypeError(f"env id must be a string, got {type(env_id).__name__}")
    try:
        return ENVS[env_id]
    except KeyError:
        raise ValueError(
            f"unknown env id {env_id!r}; available: {', '.join(list_envs())}"
        ) from None


def compiles_by_default() -> bool:
    """Whether the gymnasium and Stable-Baselines3 adapters and the training recipes
    compile their env when not told (``compile=...``, ``--no-compile``): yes, unless the
    environment variable ``BEACON_TORCH_COMPILE`` is ``0`` (a debugging session, a test
    suite that checks behaviour rather than speed)."""
    return os.environ.get("BEACON_TORCH_COMPILE", "1") != "0"


def make(
    env_id: str,
    batch_size: int = 1,
    *,
    device: Any = "cpu",
    dtype: Any = "float32",
    seed: int | None = None,
    **params: Any,
) -> FlowEnv:
    """Build a batched BEACON environment.

    ``batch_size`` members are stepped together; ``device`` and ``dtype`` (float32 or
    float64) place the state; ``seed`` seeds the env's own generator. The other keyword
    arguments are the env's physical parameters (``beacon-torch list``, ``docs/envs``)
    and the options every env has:

    ``compile``
        True (or a dict of ``torch.compile`` options) runs each step as one compiled
        call (:meth:`FlowEnv.compile`); default False, eager (the gymnasium and
        Stable-Baselines3 adapters default to True).
    ``differentiable``
        True keeps the autograd graph through the steps, so that rewards can be
        differentiated with respect to actions, parameters and states; default False
        (no graph).
    ``grad_checkpoint``
        with ``differentiable``, recompute each action's substeps in the backward pass
        instead of keeping them (the memory of a differentiated episode becomes one
        state per action); default False.
    ``record_history``
        True keeps member ``render_index``'s states since its reset, so that
        ``render()`` draws the episode so far; default False (the current state only).
    ``check_actions``
        False skips the check of action values (NaN, range), which synchronises with
        an accelerator on every step; default True.
    """
    return env_class(env_id)(batch_size, device=device, dtype=dtype, seed=seed, **params)
