"""Behaviour specific to the 2-D cavities (rayleigh, mixing)."""

import pytest
import torch

import beacon_torch
from beacon_torch.envs.rayleigh import C, RayleighParams, developed_convection, normalise
from beacon_torch.numerics.staggered import divergence

from conftest import run_actions


def test_segment_normalisation():
    g = torch.Generator().manual_seed(0)
    a = 2 * torch.rand((64, 10), generator=g, dtype=torch.float64) - 1
    t = normalise(a)
    assert t.mean(-1).abs().max() < 1e-15
    assert t.abs().max() <= C + 1e-12
    small = torch.tensor([[0.1, -0.1] * 5], dtype=torch.float64)
    torch.testing.assert_close(normalise(small), C * small)
    # one segment at the top: it is scaled back to C exactly
    peak = torch.tensor([[1.0] + [-1.0] * 9], dtype=torch.float64)
    assert normalise(peak).abs().max().item() == pytest.approx(C)


@pytest.mark.parametrize("env_id", ["rayleigh-v0", "mixing-v0"])
def test_flow_stays_divergence_free(env_id):
    env = beacon_torch.make(env_id, 2, dtype=torch.float64, seed=0)
    g = torch.Generator().manual_seed(0)
    run_actions(env, [env.random_action(g)])
    flow = env.physics.cavity.to_solver(env.physics.flow(env.state), env.physics.ghosts)
    div = divergence(flow.u, flow.v, env.physics.dx, env.physics.dy)
    if env_id == "mixing-v0":
        # the increment's zero ghost on the lid leaves, as published, the top cells
        # their own divergence
        div = div[:, :-1]
    assert div.abs().max() < 1e-10


def test_rayleigh_observation_stacks_the_probe_history():
    env = beacon_torch.make("rayleigh-v0", 1, dtype=torch.float64)
    # oldest first, as published: the reset observation is zeros but its last 48
    obs0 = env.reset()["observation"]
    assert obs0.shape == (1, 192) and (obs0[:, :144] == 0).all() and (obs0[:, 144:] != 0).any()
    obs, _ = run_actions(env, [env.null_action()] * 2)
    torch.testing.assert_close(obs[:, 1, 96:144], obs[:, 0, 144:])
    torch.testing.assert_close(obs[:, 1, 48:96], obs0[:, 144:])


def test_continuous_mixing_corners_are_the_discrete_actions():
    discrete = beacon_torch.make("mixing-v0", 4, dtype=torch.float64)
    continuous = beacon_torch.make("mixing-continuous-v0", 4, dtype=torch.float64)
    corners = torch.tensor([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]], dtype=torch.float64)
    obs_d, rew_d = run_actions(discrete, [torch.arange(4)])
    obs_c, rew_c = run_actions(continuous, [corners])
    assert torch.equal(obs_d, obs_c) and torch.equal(rew_d, rew_c)


def test_mixing_initial_patch_and_reward():
    env = beacon_torch.make("mixing-v0", 1, dtype=torch.float64)
    env.reset()
    c = env.state.c[0]
    assert c.sum().item() == 2500.0 and c[25:75, 25:75].min() == 1.0
    # the first reward is the distance from the mixed value, near -mean|c0 1_patch - 0.25|
    _, rew = run_actions(env, [env.null_action()])
    expected = -(2500 * 0.75 + (102 * 102 - 2500) * 0.25) / (102 * 102)
    assert rew.item() == pytest.approx(expected, rel=0.05)


def test_a_start_is_developed_for_parameters_without_a_stored_one():
    # the first moments of what start="generated" develops for a smaller cavity: the
    # plates' temperatures diffuse in from the ghosts, the flow stays finite
    params = RayleighParams(L=0.4, H=0.3, n_sgts=2, start="generated")
    flow = developed_convection(params, time=0.1)
    assert flow.theta.shape == (22, 17) and flow.u.shape == (22, 17) and flow.p.shape == (20, 15)
    assert all(bool(torch.isfinite(f).all()) for f in flow)
    assert flow.theta[1:-1, 1].min() > 0.05 and flow.theta[1:-1, -2].max() < -0.05


def test_a_cavity_state_begins_with_its_flow():
    from typing import NamedTuple

    from beacon_torch.envs.rayleigh import RayleighPhysics

    class Swapped(NamedTuple):
        v: torch.Tensor
        u: torch.Tensor
        p: torch.Tensor
        theta: torch.Tensor

    with pytest.raises(TypeError, match=r"state_type must begin with the flow's fields \('u', 'v', 'p', 'theta'\)"):
        type("SwappedPhysics", (RayleighPhysics,), {"state_type": Swapped})
