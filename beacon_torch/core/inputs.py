"""What the functional API checks of what it is given (:func:`beacon_torch.step`): the
physics, its parameters, the state, the action, the noise, the counts, the observation
and the stepping mask, each refused in one line naming the argument and what it must
be, as the TorchRL env refuses them.

The checks read shapes, dtypes and devices only, so that they hold under
``torch.func`` and ``torch.compile``; the one check of values, that the state given is
finite (as ``set_state`` requires), reads the host and runs in eager calls alone.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import torch

from beacon_torch import seeds
from beacon_torch.core.physics import Physics
from beacon_torch.core.state import Noise, State
from beacon_torch.core.step import Step, step


def _transformed() -> bool:
    """Whether the call runs under a ``torch.func`` transform or is being compiled:
    nothing may be read on the host then."""
    if torch.compiler.is_compiling():
        return True
    level = getattr(torch._C._functorch, "maybe_current_level", lambda: None)()
    return level is not None


def _shown(value: Any) -> str:
    if isinstance(value, torch.Tensor):
        return f"a {value.dtype} tensor of shape {tuple(value.shape)} on {value.device}"
    return f"a {type(value).__name__}"


def _tensor(name: str, value: Any, what: str, shape: tuple, dtype: torch.dtype | None, physics) -> None:
    """Refuse ``value`` unless it is a tensor of ``shape`` (None in it: any size there)
    on the physics' device, of ``dtype`` (None: a float of the physics' dtype)."""
    kind = f"{dtype}" if dtype is not None else f"{physics.dtype}"
    shown = tuple("*" if n is None else n for n in shape)
    expected = f"{what}: a {kind} tensor of shape {shown} on {physics.device}"
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"{name} must be {expected}, got {_shown(value)}")
    fits = len(value.shape) == len(shape) and all(n is None or n == m for n, m in zip(shape, value.shape, strict=True))
    if not fits:
        raise ValueError(f"{name} must be {expected}, got shape {tuple(value.shape)}")
    if value.dtype != (dtype if dtype is not None else physics.dtype):
        raise TypeError(f"{name} must be {expected}, got dtype {value.dtype}")
    if value.device != physics.device:
        raise ValueError(f"{name} must be {expected}, got a tensor on {value.device}")


def _noise_signature(physics, params) -> dict[str, tuple[tuple, torch.dtype]] | None:
    """The keys, shapes and dtypes of what ``physics.noise`` draws for one action,
    drawn once from a generator of its own (None under a transform, where nothing is
    drawn: the noise is then checked for being a dict of tensors alone)."""
    if _transformed():
        return physics.recalled("noise signature")

    def draw():
        generator = seeds.generator(0, physics.device)
        with torch.no_grad():
            noise = physics.noise(params, generator)
        return {k: (tuple(v.shape), v.dtype) for k, v in noise.items()}

    return physics.remembered("noise signature", draw)


def check_step_inputs(physics, params, state, action, noise, count, observation, stepping) -> None:
    """Refuse, in one line naming it, an argument of :func:`beacon_torch.step` that is
    not what ``physics`` steps (see the module's docstring), and, in eager calls, a
    state that is not finite."""
    if not isinstance(physics, Physics):
        raise TypeError(
            f"physics must be a case's Physics (beacon_torch.functional(env_id) returns it), got {_shown(physics)}"
        )
    name = type(physics).__name__
    members = physics.num_envs
    if not isinstance(params, physics.Params):
        raise TypeError(
            f"{name}: params must be its {physics.Params.__name__} (beacon_torch.functional returns them with the "
            f"physics), got {_shown(params)}"
        )
    for f in dataclasses.fields(params):
        value = getattr(params, f.name)
        if isinstance(value, torch.Tensor):
            if value.device != physics.device:
                raise ValueError(f"{name}: parameter {f.name!r} is on {value.device}, the physics on {physics.device}")
            if value.ndim > 1 or (value.ndim == 1 and value.shape[0] not in (1, members)):
                raise ValueError(
                    f"{name}: parameter {f.name!r} must be one value or one per member ({members}), got shape "
                    f"{tuple(value.shape)}"
                )

    if type(state) is not physics.state_type:
        raise TypeError(f"{name}: state must be its {physics.state_type.__name__} (of tensors), got {_shown(state)}")
    for key, value in state._asdict().items():
        shape = (members, *(None,) * (value.ndim - 1)) if isinstance(value, torch.Tensor) and value.ndim else (members,)
        _tensor(f"{name}: state.{key}", value, f"its {members} members first", shape, None, physics)

    discrete = physics.discrete
    action_dtype = torch.int64 if discrete else None
    what = (
        f"integer indices in [0, {physics.n_actions - 1}], one per member"
        if discrete
        else "values in [-1, 1], one row per member"
    )
    _tensor(f"{name}: action", action, what, (members, *physics.action_shape), action_dtype, physics)

    if noise is not None:
        if not isinstance(noise, dict) or not all(isinstance(v, torch.Tensor) for v in noise.values()):
            raise TypeError(f"{name}: noise must be a dict of tensors (what physics.noise draws), got {_shown(noise)}")
        signature = _noise_signature(physics, params)
        if signature is not None:
            if set(noise) != set(signature):
                missing, extra = sorted(set(signature) - set(noise)), sorted(set(noise) - set(signature))
                raise ValueError(
                    f"{name}: noise must hold what physics.noise draws, {sorted(signature)}; missing {missing}, "
                    f"unknown {extra}"
                )
            for key, (shape, dtype) in signature.items():
                _tensor(f"{name}: noise[{key!r}]", noise[key], "what physics.noise draws", shape, dtype, physics)
    elif _noise_signature(physics, params):
        raise ValueError(f"{name}: draws noise for each action; give noise=physics.noise(params, generator)")

    if count is not None:
        _tensor(f"{name}: count", count, "the actions each member has taken", (members,), torch.int64, physics)
    if stepping is not None:
        _tensor(f"{name}: stepping", stepping, "which members take the action", (members,), torch.bool, physics)
    if observation is not None:
        shape = (members, *(None,) * (observation.ndim - 1)) if isinstance(observation, torch.Tensor) else (members,)
        _tensor(f"{name}: observation", observation, "that of the state", shape, None, physics)

    if not _transformed():
        for key, value in state._asdict().items():
            if not bool(torch.isfinite(value.detach()).all()):
                raise ValueError(f"{name}: state.{key} has values that are not finite in {physics.dtype}")


def checked_step(
    physics: Physics,
    params: Any,
    state: State,
    action: torch.Tensor,
    noise: Noise | None = None,
    count: torch.Tensor | None = None,
    observation: torch.Tensor | None = None,
    stepping: torch.Tensor | None = None,
    *,
    keep_graph: bool = False,
    checkpoint: bool = False,
) -> Step:
    """:func:`step`, what ``beacon_torch.step`` is, with its arguments checked first:
    each one that is not what the physics steps (its params, a state of its type on its
    device and in its dtype with a member per row, an action of the exact shape, the
    noise its ``noise`` draws, int64 counts, a bool stepping mask) is refused in one line
    naming it, and a state that is not finite too where the call is eager. The checks
    read shapes alone under ``torch.func`` and ``torch.compile``, so that they map,
    differentiate and compile the step as before."""
    check_step_inputs(physics, params, state, action, noise, count, observation, stepping)
    return step(
        physics,
        params,
        state,
        action,
        noise,
        count,
        observation,
        stepping,
        keep_graph=keep_graph,
        checkpoint=checkpoint,
    )
