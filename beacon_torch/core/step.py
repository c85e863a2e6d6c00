"""One action of a batch of members, as one function of the physics, its parameters and
the state: what every path of an env runs (eagerly, compiled as one call, and keeping
the autograd graph) and what :func:`beacon_torch.step` hands to users of ``torch.func``.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import torch

from beacon_torch.autograd import checkpointed
from beacon_torch.compiled import standard
from beacon_torch.core.state import Noise, State, finite_members, map_state, select, where_members


class Step(NamedTuple):
    """What one action leaves, per member."""

    state: State
    observation: torch.Tensor  # [batch, n_obs] ([batch, n_agents, n_obs])
    reward: torch.Tensor  # [batch] ([batch, n_agents])
    terminated: torch.Tensor  # [batch] bool: the member left its bounds (blow-up)
    truncated: torch.Tensor  # [batch] bool: the episode's last action was taken
    count: torch.Tensor  # [batch] int64: the actions taken in the episode
    valid: torch.Tensor  # () bool: whether every action value was admissible
    diagnostics: dict[str, torch.Tensor]  # the physics' diagnostics of the new state


def settle(
    new: State,
    old: State,
    obs: torch.Tensor,
    old_obs: torch.Tensor,
    reward: torch.Tensor,
    inside: torch.Tensor,
    blowup_reward: float,
):
    """The outcome of a step for every member: where the new state, observation and
    reward are finite and ``inside`` the physical bounds, they stand; elsewhere the
    member keeps its last state and observation and gets ``blowup_reward``. Returns
    ``(state, observation, reward, ok)``. A kernel of its own: compiled, its few dozen
    small operations are one call, which at small batches costs less than they do."""
    ok = finite_members(obs) & finite_members(reward) & inside
    for value in new:
        if value.is_floating_point() or value.is_complex():
            ok = ok & finite_members(value)
    new = where_members(ok, new, old)
    obs = select(ok, obs, old_obs)
    reward = select(ok, reward, torch.full_like(reward, blowup_reward))
    return new, obs, reward, ok


def advance_settled(physics, params, state, observation, action, count, noise, start, checkpoint, inside=None):
    """The physics from ``start`` and :func:`settle` against ``state``: a member whose
    result is not finite, leaves its bounds or is not ``inside`` keeps ``state`` and
    ``observation``. Returns ``(state, observation, reward, ok)``. A kernel of its own
    too (``physics.settled_action``), which a physics whose action is small runs as one
    compiled call where autograd records it (``Physics.grad_whole_action``)."""
    if checkpoint and torch.is_grad_enabled():
        new, reward = checkpointed(physics.advance, params, start, action, count, noise)
    else:
        new, reward = physics.advance(params, start, action, count, noise)
    bounds = ~physics.out_of_bounds(params, new)
    return physics.settle(
        new,
        state,
        physics.observe(params, new),
        observation,
        reward,
        bounds if inside is None else bounds & inside,
        float(physics.blowup_reward),
    )


def step(
    physics,
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
    """One action of every member of ``state`` under the physics ``physics`` (a
    :class:`~beacon_torch.core.physics.Physics`, which imports this module) with the
    parameters ``params`` (an instance of ``physics.Params``, per-member values
    ``[batch]``): returns a :class:`Step`.

    ``action`` is ``[batch, *action_shape]`` (int64 indices if discrete); values out of
    range are clipped (continuous) or kept in range (discrete), and ``valid`` says
    whether all were admissible (the env refuses them otherwise). ``noise`` is what
    ``physics.noise(params, generator)`` drew for this action (None: none),
    ``count`` the actions already taken in each member's episode (None: zeros),
    ``observation`` that of ``state`` (None: observed here), ``stepping`` which members
    take the action (None: all; the others are left as they were, with zero reward).

    A member whose new state, observation or reward is not finite, or that leaves its
    physical bounds, keeps its last state and observation, gets the physics'
    ``blowup_reward`` and is terminated; the others go on. ``keep_graph`` (the
    differentiable env) makes that containment hold for gradients too, which costs a
    host read per step; ``checkpoint`` recomputes the action's substeps in the
    backward pass instead of keeping them. Without ``keep_graph`` the function reads
    nothing on the host: it is one compiled graph, and ``torch.func.vmap`` maps it.
    """
    if noise is None:
        noise = {}
    if count is None:
        count = torch.zeros(physics.batch_size, dtype=torch.int64, device=physics.device)
    if observation is None:
        observation = physics.observe(params, state)

    # the action as the physics takes it
    action, valid = physics.action_values(action)

    # the physics, and the blow-ups contained: the members that blew up keep their state
    if keep_graph and physics.grad_whole_action and physics.kernels.compiled:
        # one differentiated graph: its partitioner, not a checkpoint, decides what is kept
        new, obs, reward, ok = physics.settled_action(
            physics, params, state, observation, action, count, noise, state, False
        )
    else:
        new, obs, reward, ok = advance_settled(
            physics, params, state, observation, action, count, noise, state, checkpoint
        )

    # A member that blew up keeps its last state, but its own backward pass would still
    # multiply a zero gradient by an infinite derivative (0 * inf = NaN), which would
    # reach the gradients of every other member through whatever they share (a policy, a
    # shared parameter). With a graph to keep, such a step is taken again, with the same
    # noise, from inputs where the members that blew up are given a copy of a sound
    # member's (detached) state, action and parameters: their discarded result is then
    # finite, and they contribute zero.
    if keep_graph and not bool(ok.all()):
        if bool(ok.any()):
            donor = int(ok.nonzero()[0, 0])
            stand_in = lambda t: select(ok, t, t[donor : donor + 1].detach().expand_as(t))
            members = physics.num_envs
            per_member = {
                f.name: stand_in(getattr(params, f.name))
                for f in dataclasses.fields(params)
                if isinstance(getattr(params, f.name), torch.Tensor)
                and getattr(params, f.name).ndim >= 1
                and getattr(params, f.name).shape[0] == members
            }
            sound = dataclasses.replace(params, **per_member)
            start, taken = map_state(stand_in, state), stand_in(action)
            new, obs, reward, ok = advance_settled(
                physics, sound, state, observation, taken, count, noise, start, checkpoint, inside=ok
            )
        else:
            # nothing to differentiate but the states kept: a reward that still depends,
            # with a zero derivative, on what the step was given (finite: the state kept
            # is the last finite one), so that a backward pass finds the graph it expects
            zero = sum((t * 0).reshape(t.shape[0], -1).sum(1) for t in (action, *state) if t.requires_grad)
            reward = torch.full_like(reward.detach(), float(physics.blowup_reward))
            if isinstance(zero, torch.Tensor):
                reward = reward + zero.reshape(-1, *(1,) * (reward.ndim - 1)).to(reward.dtype)
            new, obs = state, observation

    # the bookkeeping: the members outside ``stepping`` as they were, the counters
    after = count + 1
    if stepping is not None:
        new = where_members(stepping, new, state)
        obs = select(stepping, obs, observation)
        reward = select(stepping, reward, torch.zeros_like(reward))
        ok = ok | ~stepping
        after = torch.where(stepping, after, count)
    # in standard strides, as the next step's compiled inputs are (a cavity's fields
    # come out of its batch-last solver permuted)
    new = map_state(standard, new)
    terminated, truncated = ~ok, after >= physics.episode_length
    return Step(new, standard(obs), reward, terminated, truncated, after, valid, physics.diagnose(params, new))
