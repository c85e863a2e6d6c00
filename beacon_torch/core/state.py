"""An env's state and what is done to it member by member.

A state is a NamedTuple of tensors, batch first, declared at the top of its env's
module as its ``state_type``. NamedTuples are pytrees: ``torch.compile``,
``while_loop``, ``torch.func`` and ``torch.utils.checkpoint`` carry them as they carry
tuples, with no conversion.
"""

from __future__ import annotations

import torch

State = tuple

# the random numbers of one action, by name (none for deterministic physics)
Noise = dict[str, torch.Tensor]


def map_state(fn, state: State) -> State:
    """``fn`` applied to every tensor of ``state``, in a state of the same type."""
    return type(state)(*(fn(value) for value in state))


def select(mask: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per batch member (leading dimension), ``a`` where ``mask`` is true, else ``b``."""
    return torch.where(mask.view(mask.shape + (1,) * (a.ndim - 1)), a, b)


def where_members(mask: torch.Tensor, a: State, b: State) -> State:
    """Per batch member, take the state ``a`` where ``mask`` is true and ``b`` elsewhere."""
    return type(a)(*(select(mask, va, vb) for va, vb in zip(a, b, strict=True)))


def finite_members(t: torch.Tensor) -> torch.Tensor:
    """``[batch]`` bool: the members whose values in ``t`` are all finite."""
    return torch.isfinite(t).flatten(1).all(1) if t.ndim > 1 else torch.isfinite(t)
