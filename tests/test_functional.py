"""The functional API: a registered env's physics as pure functions of the parameters
and the state, what ``torch.func`` users map and differentiate. Checked against the
TorchRL env, which steps the same function with its own parameters."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from torch.func import grad, jacrev, vmap

import beacon_torch
from beacon_torch.registry import env_spec, list_envs

MEMBERS = 3


def same(a, b) -> bool:
    return all(torch.equal(x, y) for x, y in zip(a, b, strict=True))


@pytest.mark.parametrize("env_id", list_envs())
def test_a_functional_rollout_is_the_envs_bit_for_bit(env_id):
    """From the same seed, the functional start, steps, rewards, flags and diagnostics
    are the TorchRL env's, in float64, noise and random starts included."""
    cls = env_spec(env_id)
    settings = dict(cls.card.test_settings)
    steps = 2 if cls.card.costly else 6
    env = beacon_torch.make(env_id, MEMBERS, dtype="float64", seed=4, **settings)
    physics, params = beacon_torch.functional(env_id, MEMBERS, dtype="float64", **settings)
    assert isinstance(physics, beacon_torch.Physics) and not isinstance(physics, torch.nn.Module)
    generator = torch.Generator().manual_seed(4)
    actions = torch.Generator().manual_seed(1)

    env.reset()
    state = physics.initial_state(params, generator)
    obs, count = physics.observe(params, state), torch.zeros(MEMBERS, dtype=torch.int64)
    assert same(state, env.state) and torch.equal(obs, env.observation)
    for _ in range(steps):
        action = physics.random_action(actions)
        out = beacon_torch.step(physics, params, state, action, physics.noise(params, generator), count, obs)
        obs_env, reward, terminated, truncated = env.step_members(action)
        assert same(out.state, env.state), env_id
        assert torch.equal(out.observation, obs_env) and torch.equal(out.reward, reward)
        assert torch.equal(out.terminated, terminated) and torch.equal(out.truncated, truncated)
        assert all(torch.equal(out.diagnostics[k], v) for k, v in env.last_diagnostics.items())
        state, obs, count = out.state, out.observation, out.count


def test_functional_takes_parameters_and_refuses_options():
    physics, params = beacon_torch.functional("burgers-v0", 2, amp=5.0)
    assert params.amp.tolist() == [5.0, 5.0] and physics.num_envs == 2 and physics.dtype == torch.float32
    with pytest.raises(TypeError, match="'differentiable' is an option of the env \\(make\\), not of its physics"):
        beacon_torch.functional("burgers-v0", differentiable=True)
    with pytest.raises(ValueError, match="unknown env id 'nope-v0'"):
        beacon_torch.functional("nope-v0")


def episode_return(physics, params, state, actions, noises):
    """The members' rewards summed over ``actions`` from ``state``: a pure function."""
    total = torch.zeros((), dtype=physics.dtype)
    obs, count = physics.observe(params, state), None
    for action, noise in zip(actions, noises, strict=True):
        out = beacon_torch.step(physics, params, state, action, noise, count, obs)
        state, obs, count = out.state, out.observation, out.count
        total = total + out.reward.sum()
    return total


def test_vmap_over_parameter_values_is_one_call_per_value():
    """``torch.func.vmap`` maps a whole episode over a batch of parameter values (here
    the inflow velocity of burgers-v0, noise included): each value's return is the one
    computed alone."""
    physics, params = beacon_torch.functional("burgers-v0", 2, dtype="float64")
    generator = torch.Generator().manual_seed(0)
    actions = [0.5 * physics.random_action(generator) for _ in range(4)]
    noises = [physics.noise(params, generator) for _ in range(4)]
    targets = torch.tensor([[0.4, 0.5], [0.6, 0.45], [0.5, 0.55]], dtype=torch.float64)

    def returns(u_target):
        p = dataclasses.replace(params, u_target=u_target)
        start = physics.initial_state(p, None)
        return episode_return(physics, p, start, actions, noises)

    mapped = vmap(returns)(targets)
    alone = torch.stack([returns(t) for t in targets])
    torch.testing.assert_close(mapped, alone, rtol=1e-12, atol=1e-12)
    assert len(set(mapped.tolist())) == 3


@pytest.mark.parametrize("env_id, name, value", [("vortex-v0", "re", 50.0), ("sloshing-v0", "g", 9.81)])
def test_grad_of_an_episode_is_the_differentiable_envs(env_id, name, value):
    """``torch.func.grad`` (and ``jacrev``, per member) of an episode's return with
    respect to a physics parameter is the gradient the differentiable env gives."""
    physics, params = beacon_torch.functional(env_id, 2, dtype="float64")
    start = physics.initial_state(params, None)
    generator = torch.Generator().manual_seed(2)
    actions = [0.6 * physics.random_action(generator) for _ in range(5)]
    noises = [{} for _ in actions]
    theta = torch.full((2,), value, dtype=torch.float64)

    def of(theta):
        return episode_return(physics, dataclasses.replace(params, **{name: theta}), start, actions, noises)

    by_grad = grad(of)(theta)
    by_jacrev = jacrev(of)(theta)

    traced = theta.clone().requires_grad_()
    env = beacon_torch.make(env_id, 2, dtype="float64", differentiable=True, **{name: traced})
    env.set_state(start)
    total = sum(env.step_members(a)[1].sum() for a in actions)
    (by_env,) = torch.autograd.grad(total, traced)
    torch.testing.assert_close(by_grad, by_env, rtol=1e-10, atol=0.0)
    torch.testing.assert_close(by_jacrev, by_env, rtol=1e-10, atol=0.0)
    assert bool((by_env != 0).all())


def test_the_step_contains_a_blow_up_as_the_env_does():
    """A member whose state leaves its bounds keeps its last state, gets the physics'
    blow-up reward and is terminated; the other member goes on."""
    physics, params = beacon_torch.functional("sloshing-v0", 2, dtype="float64")
    state = physics.initial_state(params, None)
    state = state._replace(h=torch.stack((state.h[0], torch.full_like(state.h[1], 3.0))))
    out = beacon_torch.step(physics, params, state, torch.zeros(2, 1, dtype=torch.float64))
    assert out.terminated.tolist() == [False, True]
    assert out.reward[1].item() == physics.blowup_reward and torch.equal(out.state.h[1], state.h[1])
    assert out.count.tolist() == [1, 1] and bool(out.valid)
