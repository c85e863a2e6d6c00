"""rayleigh-separable-v0: the periodic channel's solver, the agents' layout and the
validation against Vignon et al. (2023)."""

import math

import pytest
import torch

import beacon_torch
from beacon_torch.envs.rayleigh import BEACON, VIGNON
from beacon_torch.numerics.grid import NEUMANN, PERIODIC
from beacon_torch.numerics.poisson import PoissonSolver

F64 = dict(dtype="float64", compile=False)
QUICK = {"period": 0.1}  # ten substeps an action


def test_periodic_poisson_solve_is_exact():
    solver = PoissonSolver(12, 8, 0.3, 0.2, (PERIODIC, PERIODIC, NEUMANN, NEUMANN), dtype=torch.float64)
    rhs = torch.randn(12, 8, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    rhs -= rhs.mean((0, 1))  # the solvable part
    phi = solver.solve(rhs)
    assert torch.allclose(solver.apply(phi), rhs, atol=1e-10)
    # the operator wraps: the first and last columns are neighbours
    assert solver.lx[0, -1] > 0 and solver.lx[-1, 0] > 0


def test_channel_is_invariant_under_a_shift_by_one_segment():
    """The flow shifted by one segment, with the actions relabelled, steps to the
    shifted flow: each agent then sees and earns what its neighbour did."""
    env = beacon_torch.make("rayleigh-separable-v0", 2, **QUICK, **F64)
    env.reset()
    state = env.state
    shift = env.physics.nx // env.n_agents

    def roll(f):
        if f.shape[1] == env.physics.nx:  # the pressure has no ghosts
            return f.roll(shift, 1)
        out = f.clone()
        out[:, 1:-1] = f[:, 1:-1].roll(shift, 1)
        return out

    first = type(state)(*(f[:1] for f in state))
    pair = type(state)(*(torch.cat((f, roll(f))) for f in first))
    env.set_state(pair._replace(probes=pair.probes[:1].expand_as(pair.probes).clone()))
    action = torch.linspace(-1, 1, env.n_agents, dtype=torch.float64)[None, :, None]
    action = torch.cat((action, action.roll(1, 1)))
    td = env.step(_action_td(env, action))
    obs, reward = td["next", "agents", "observation"], td["next", "agents", "reward"]
    torch.testing.assert_close(obs[1], obs[0].roll(1, 0), atol=1e-10, rtol=0)
    torch.testing.assert_close(reward[1], reward[0].roll(1, 0), atol=1e-10, rtol=0)


def _action_td(env, action):
    td = env.full_action_spec.zero()
    td["agents", "action"] = action
    return td


def test_agents_see_their_window_and_share_the_global_reward():
    env = beacon_torch.make("rayleigh-separable-v0", 1, window=3, beta=0.5, **QUICK, **F64)
    td = env.reset()
    obs = td["agents", "observation"][0]  # [agents, 3 fields x 3 segments x 3 columns x 8 rows]
    blocks = obs.reshape(env.n_agents, 3, 3, -1)
    # agent i's middle block is agent i + 1's left one (the channel wraps)
    torch.testing.assert_close(blocks[:, :, 1], blocks.roll(-1, 0)[:, :, 0])
    td = env.step(_action_td(env, torch.zeros(1, env.n_agents, 1, dtype=torch.float64)))
    reward = td["next", "agents", "reward"][0, :, 0]
    # beta = 1/2: each reward is minus the mean of the agent's own and the whole Nusselt
    # numbers, and the agents' own ones average to the whole
    torch.testing.assert_close(reward.mean(), -env.last_diagnostics["nusselt"][0])
    assert reward.std() > 0


def test_beacon_geometry_agents_next_to_the_walls_see_zeros():
    env = beacon_torch.make("rayleigh-separable-v0", 1, **BEACON, window=3, **F64)
    obs = env.reset()["agents", "observation"][0].reshape(env.n_agents, 3, 3, -1)
    assert (obs[0, :, 0] == 0).all() and (obs[-1, :, 2] == 0).all()
    assert (obs[1, :, 0] != 0).any()
    assert env.physics.nx == 50 and env.episode_length == 200


def test_layout_errors_are_one_line():
    with pytest.raises(ValueError, match="'window'"):
        beacon_torch.make("rayleigh-separable-v0", 1, window=4)
    with pytest.raises(ValueError, match="'period'"):
        beacon_torch.make("rayleigh-separable-v0", 1, period=0.015)
    with pytest.raises(ValueError, match="'resolution'"):
        beacon_torch.make("rayleigh-separable-v0", 1, resolution=60)


def test_vignon_case_is_the_default():
    env = beacon_torch.make("rayleigh-separable-v0", 1, compile=False)
    p = env.params
    assert (p.L, p.H, p.sides, p.period) == (VIGNON["L"], VIGNON["H"], VIGNON["sides"], VIGNON["period"])
    assert math.isclose(float(p.pr), 0.7) and math.isclose(float(p.ra), 1e4)
    assert (env.physics.nx, env.physics.ny, env.physics.substeps) == (200, 64, 150)


def test_the_page_shows_the_recorded_validation_within_two_percent():
    from pathlib import Path

    from beacon_torch import received
    from validation import rayleigh_channel as validation

    page = (Path(__file__).resolve().parents[1] / "docs" / "envs" / "rayleigh-separable.md").read_text()
    newest = sorted(validation.RECORDS.glob("channel_validation-*.json"))[-1]
    rows = received.json_file(newest, "a channel validation record")["rows"]
    assert validation.table(rows) in page
    (default,) = [r for r in rows if r["resolution"] == 32]
    assert (default["nx"], default["ny"]) == (200, 64) and abs(default["probe_error"]) < 0.02
    # the flow's own Nusselt number converges with the grid
    first, second, third = (r["nusselt"] for r in rows)
    assert abs(third - second) < abs(second - first)


def test_the_page_shows_the_recorded_trials():
    from pathlib import Path

    page = (Path(__file__).resolve().parents[1] / "docs" / "envs" / "rayleigh-separable.md").read_text()
    from experiments import rayleigh_separable_trials

    assert rayleigh_separable_trials.table() in page
