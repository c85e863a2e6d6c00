"""An env's state saved and restored: where every member is, the generators and the
parameters, as the entries of a state dict, and those entries read back and checked."""

from __future__ import annotations

import dataclasses
from typing import Any

import torch

from beacon_torch.core.state import State

# what a state dict holds beside the state's fields (``state.<field>``)
ENTRIES = ("count", "rng", "action_rng", "params")


def entries(
    state: State | None,
    count: torch.Tensor,
    generators: dict[str, torch.Generator],
    params,
    prefix: str = "",
    keep_vars: bool = False,
) -> dict[str, Any]:
    """The entries of an env's state dict: the state of every member
    (``state.<field>``) and the actions taken in their episodes (``count``), once it has
    a state; the generators' states (``rng``, ``action_rng``); the parameters."""
    out: dict[str, Any] = {}
    if state is not None:
        for key, value in state._asdict().items():
            out[f"{prefix}state.{key}"] = value if keep_vars else value.detach()
        out[f"{prefix}count"] = count.clone()
    for key, generator in generators.items():
        out[f"{prefix}{key}"] = generator.get_state()
    out[f"{prefix}params"] = {
        f.name: value.detach().clone() if isinstance(value, torch.Tensor) else value
        for f in dataclasses.fields(params)
        for value in (getattr(params, f.name),)
    }
    return out


def read(
    state_dict: Any,
    name: str,
    fields: tuple[str, ...],
    params,
    generators: dict[str, torch.Generator],
    strict: bool = True,
) -> tuple[dict[str, torch.Tensor], Any, dict[str, torch.Tensor]]:
    """What a state dict of the env ``name`` (its state type's ``fields``, its
    ``params`` and ``generators``) asks it to continue from: the state's fields (empty
    when it holds none), the count, and the generators' states, each checked: the
    parameters must be ``params``; ``strict`` also requires every entry a stepped env's
    state dict has, and no other."""
    if not isinstance(state_dict, dict):
        raise TypeError(f"{name}: a state dict is a dict (env.state_dict()), got {type(state_dict).__name__}")
    state = {key.removeprefix("state."): value for key, value in state_dict.items() if key.startswith("state.")}
    unknown = set(state_dict) - {f"state.{k}" for k in state} - set(ENTRIES)
    missing = [] if state else [f"state.{k}" for k in fields]
    missing += [key for key in ENTRIES if key not in state_dict and (key != "count" or state)]
    if strict and (unknown or missing):
        raise KeyError(
            f"{name}: the state dict has unknown entries {sorted(unknown)} and lacks {missing}; "
            f"load_state_dict(..., strict=False) loads what it holds"
        )
    if "params" in state_dict:
        check_same_params(name, params, state_dict["params"])
    saved = {key: state_dict[key] for key in generators if key in state_dict}
    for key, value in saved.items():
        own = generators[key].get_state()
        if not isinstance(value, torch.Tensor) or value.dtype != torch.uint8 or value.shape != own.shape:
            raise ValueError(
                f"{name}: {key!r} must be a generator state of this device (a uint8 tensor of shape {tuple(own.shape)})"
            )
    return state, state_dict.get("count", 0), saved


def check_same_params(name: str, params, saved: Any) -> None:
    """Refuse the parameters ``saved`` in a state dict that are not ``params``."""
    own = {f.name: getattr(params, f.name) for f in dataclasses.fields(params)}
    if not isinstance(saved, dict) or set(saved) != set(own):
        raise ValueError(f"{name}: the state dict's 'params' are not those of {name} ({sorted(own)})")
    for key, mine in own.items():
        theirs = saved[key]
        if isinstance(mine, torch.Tensor):
            same = (
                isinstance(theirs, (torch.Tensor, int, float))
                and not isinstance(theirs, bool)
                and torch.as_tensor(theirs).numel() in (1, mine.numel())
                and bool((torch.as_tensor(theirs).to(mine.device, mine.dtype) == mine.detach()).all())
            )
        else:
            same = type(theirs) is type(mine) and theirs == mine
        if not same:
            shown = theirs.tolist() if isinstance(theirs, torch.Tensor) and theirs.numel() < 8 else theirs
            raise ValueError(
                f"{name}: the state dict was saved by an env with other parameters ({key} = {shown!r} there, "
                f"{mine.tolist() if isinstance(mine, torch.Tensor) else mine!r} here); make the env with its "
                f"parameters to continue it"
            )
