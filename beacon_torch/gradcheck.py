"""Gradients of an env checked against central differences.

The reward summed over a few steps from a given state is differentiated with respect to
the action sequence (along a random direction) and to one physical parameter, and both
derivatives are compared with central differences of the same sum. Run in float64 at a
generic point: a state reached by random actions and actions away from the box's edges,
so that no limiter, max or abs of the scheme sits on its kink (see docs/gradients.md).
``tests/test_gradients.py`` checks every continuous env this way on small settings;
``validation/gradcheck.py`` on the published ones.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from tensordict import TensorDict

from beacon_torch import seeds
from beacon_torch.base import FlowEnv
from beacon_torch.base import make as make_env
from beacon_torch.core.card import GradCheck
from beacon_torch.core.state import State, map_state
from beacon_torch.registry import env_spec


@dataclass(frozen=True)
class Derivative:
    """One derivative: by automatic differentiation and by central differences."""

    autograd: float
    central: float

    @property
    def relative_error(self) -> float:
        return abs(self.autograd - self.central) / abs(self.central)


def summed_reward(env: FlowEnv, start: State, actions: torch.Tensor, seed: int = 11) -> torch.Tensor:
    """The reward of every member summed over ``actions`` (``[steps, *action batch]``)
    from the state ``start``; the env's noise is drawn from ``seed`` every time, so
    that two calls differ only by what they are given."""
    env.set_seed(seed)
    env.set_state(start)
    total = 0.0
    for a in actions:
        td = env.step(TensorDict({env.action_key: a}, batch_size=env.batch_size))
        total = total + td["next", env.reward_key].sum()
    return total


def generic_start(env: FlowEnv, n: int, seed: int = 5) -> State:
    """The state after a reset and ``n`` random actions of amplitude 0.5."""
    gen = seeds.generator(seed)
    env.reset()
    with torch.no_grad():
        for _ in range(n):
            a = torch.rand(env.full_action_spec[env.action_key].shape, generator=gen, dtype=env.dtype) - 0.5
            env.step(TensorDict({env.action_key: a.to(env.device)}, batch_size=env.batch_size))
    return map_state(lambda v: v.detach().clone(), env.state)


def check(
    make: Callable[..., FlowEnv], name: str, value: float, *, warmup: int, steps: int, h: float = 1e-6, seed: int = 7
) -> dict[str, Derivative]:
    """The derivatives of the reward summed over ``steps`` random actions, after
    ``warmup`` random actions, with respect to the actions (along a random direction)
    and to the parameter ``name`` at ``value``; ``make(**params)`` builds the env
    (float64, one member) with the given parameters and any keyword of ``make``.
    ``h`` is the relative step of the differences."""
    theta = torch.tensor(value, dtype=torch.float64, requires_grad=True)
    env = make(**{name: theta}, differentiable=True)
    if env.dtype != torch.float64:
        raise ValueError(f"{env.env_id}: check gradients in float64, got {env.dtype}")
    start = generic_start(env, warmup)
    gen = seeds.generator(seed)
    shape = (steps, *env.full_action_spec[env.action_key].shape)
    actions = (0.6 * torch.rand(shape, generator=gen, dtype=torch.float64) - 0.3).to(env.device).requires_grad_()
    total = summed_reward(env, start, actions)
    grad_actions, grad_theta = torch.autograd.grad(total, (actions, theta))

    direction = torch.randn(shape, generator=gen, dtype=torch.float64).to(env.device)
    with torch.no_grad():
        plus = summed_reward(env, start, actions + h * direction)
        minus = summed_reward(env, start, actions - h * direction)
    along = Derivative(float((grad_actions * direction).sum()), float((plus - minus) / (2 * h)))

    # the parameter: two envs at value -+ dv started from the same state
    dv = h * abs(value)
    plus, minus = make(**{name: value + dv}), make(**{name: value - dv})
    with torch.no_grad():
        fd = (summed_reward(plus, start, actions.detach()) - summed_reward(minus, start, actions.detach())) / (2 * dv)
    return {"actions": along, name: Derivative(float(grad_theta), float(fd))}


def check_env(env_id: str, case: GradCheck | None = None) -> dict[str, Derivative]:
    """:func:`check` of the env ``env_id`` (one member, float64) on ``case``, by default
    the one its card declares (``gradcheck``)."""
    case = case or env_spec(env_id).card.gradcheck
    if case is None:
        raise ValueError(f"{env_id} declares no gradient check (its actions are discrete)")

    def make(**kwargs):
        return make_env(env_id, num_envs=1, dtype=torch.float64, seed=3, **case.params, **kwargs)

    return check(make, case.param, case.value, warmup=case.warmup, steps=case.steps)
