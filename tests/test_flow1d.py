"""Behaviour specific to the 1-D flow environments: steady states, actuators, initial
states and their cache, the multi-agent shkadov."""

import pytest
import torch

import beacon_torch
from beacon_torch import cache, episodes
from beacon_torch.envs import shkadov, sloshing

from conftest import run_actions


def test_burgers_steady_state_without_noise_or_action():
    env = beacon_torch.make("burgers-v0", 2, dtype=torch.float64, sigma=0.0)
    obs, rew = run_actions(env, [env.null_action()] * 3)
    assert torch.equal(env.state.u, torch.full_like(env.state.u, 0.5))
    assert (rew == 0).all() and (obs == 0.5).all()


def test_burgers_inlet_noise_is_one_draw_per_action_and_actuator_acts_downstream():
    env = beacon_torch.make("burgers-v0", 1, dtype=torch.float64, seed=3)
    run_actions(env, [env.null_action()])
    u = env.state.u[0]
    assert u[0] != 0.5 and abs(u[0] - 0.5) <= 0.1
    # a positive action lowers u at the actuator (the source enters as -amp * a)
    env = beacon_torch.make("burgers-v0", 1, dtype=torch.float64, sigma=0.0)
    run_actions(env, [torch.ones(1, 1, dtype=torch.float64)])
    u = env.state.u[0]
    assert u[env.physics.ctrl] < 0.5 and (u[: env.physics.ctrl - 5] == 0.5).all()


def test_sloshing_rest_is_steady_and_excitation_moves_the_tank():
    h = torch.ones(1, 200, dtype=torch.float64)
    gh, gq = sloshing.with_walls(h, torch.zeros_like(h))
    fh, fq = sloshing.shallow_water_rhs(gh, gq, torch.zeros(1, dtype=torch.float64), 9.81, 0.0125)
    assert (fh == 0).all() and (fq == 0).all()
    env = beacon_torch.make("sloshing-v0", 1, dtype=torch.float64)
    env.reset()
    h0 = env.state.h[0]
    assert (h0 - 1).abs().max() > 0.05 and torch.isfinite(h0).all()
    # the published generator's signal, not clipped to the action box
    assert sloshing.excitation(0.0) == 2.0 and sloshing.excitation(0.5) == pytest.approx(1.5)


def test_sloshing_actuation_cost_enters_the_reward():
    a = beacon_torch.make("sloshing-v0", 1, dtype=torch.float64, alpha=0.0)
    b = beacon_torch.make("sloshing-v0", 1, dtype=torch.float64, alpha=0.01)
    action = torch.full((1, 1), 0.5, dtype=torch.float64)
    _, ra = run_actions(a, [action])
    _, rb = run_actions(b, [action])
    assert (ra - rb).item() == pytest.approx(0.01 * 5.0 * 0.5)


def test_excited_state_is_cached_on_disk(tmp_path, monkeypatch):
    monkeypatch.setenv("BEACON_TORCH_CACHE", str(tmp_path))
    monkeypatch.setattr(cache, "_memory", {})
    env = beacon_torch.make("sloshing-v0", 1, g=9.0)
    env.reset()  # the start is made at the first reset
    files = list(tmp_path.glob("sloshing-excited-*.pt"))
    assert len(files) == 1
    monkeypatch.setattr(cache, "_memory", {})
    monkeypatch.setattr(sloshing, "excited_state", lambda *a, **k: pytest.fail("recomputed"))
    again = beacon_torch.make("sloshing-v0", 1, g=9.0)
    assert torch.equal(again.reset()["observation"], env.observation)


def test_shkadov_flat_film_is_steady_and_jets_remove_flow_rate():
    n = 100
    h = torch.ones(1, n, dtype=torch.float64)
    dh, dq = shkadov.shkadov_rhs(h, h.clone(), torch.zeros(1, n - 2, dtype=torch.float64), 0.1, 0.2)
    torch.testing.assert_close(dq, torch.zeros_like(dq), rtol=0, atol=1e-7)
    assert (dh == 0).all()
    prof = shkadov.jet_profiles([50], n, torch.float64, "cpu")
    assert prof[0, 50] == 1.0 and prof[0, 40] == 0.0 and prof[0, 60] == 0.0 and prof[0, 39] == 0.0
    state = shkadov.flat_state(1, n, 1, torch.float64, "cpu")
    noise = shkadov.inlet_noise(None, 1, torch.float64)
    out = shkadov.run_action(state, torch.ones(1, 1, dtype=torch.float64), prof[:, 1:-1], 0.1, 0.2, noise)
    assert out.q[0, 50] < 1.0


def test_developed_film_generator_is_reproducible():
    a = shkadov.developed_film(0.1, time=0.5)
    b = shkadov.developed_film(0.1, time=0.5)
    assert torch.equal(a.h, b.h) and a.h.shape == (2900,)
    c = shkadov.developed_film(0.1, time=0.5, seed=1)
    assert not torch.equal(a.h, c.h)


def test_shkadov_ships_its_developed_film():
    key = dict(delta=0.1)
    assert (cache.PACKAGE_DATA / cache.file_name("shkadov-film", shkadov.START_VERSION, key)).is_file()
    env = beacon_torch.make("shkadov-v0", 1, random_start=0, dtype=torch.float64)
    env.reset()
    h = env.state.h[0]
    # a developed film: waves of order 0.3 downstream, still flat near the inlet
    assert (h[:200] - 1).abs().max() < 0.01 and (h[700:] - 1).abs().max() > 0.2


def test_shkadov_random_starts_differ_per_member_and_follow_the_seed():
    env = beacon_torch.make("shkadov-v0", 4, random_start=20, seed=1, dtype=torch.float64)
    obs = env.reset()["observation"]
    assert len({tuple(o.tolist()) for o in obs}) > 1
    again = beacon_torch.make("shkadov-v0", 4, random_start=20, seed=1, dtype=torch.float64)
    assert torch.equal(again.reset()["observation"], obs)
    fixed = beacon_torch.make("shkadov-v0", 2, random_start=0, dtype=torch.float64)
    obs = fixed.reset()["observation"]
    assert torch.equal(obs[0], obs[1])


def test_separable_shkadov_is_shkadov_seen_per_jet():
    kw = dict(random_start=5, seed=2, dtype=torch.float64)
    joint = beacon_torch.make("shkadov-v0", 2, **kw)
    agents = beacon_torch.make("shkadov-separable-v0", 2, **kw)
    g = torch.Generator().manual_seed(0)
    actions = [joint.random_action(g) for _ in range(4)]
    obs_j, rew_j = run_actions(joint, actions)
    obs_a, rew_a = run_actions(agents, [a[..., None] for a in actions])
    assert obs_a.shape == (2, 4, 5, 10) and rew_a.shape == (2, 4, 5, 1)
    torch.testing.assert_close(obs_a.reshape(2, 4, 50), obs_j, rtol=0, atol=0)
    torch.testing.assert_close(rew_a.mean((-2, -1)), rew_j[..., 0], rtol=1e-12, atol=1e-15)


def test_separable_shkadov_observation_does_not_grow_with_jets():
    env = beacon_torch.make("shkadov-separable-v0", 2, n_jets=20, random_start=0)
    r = env.rollout(2)
    assert r["agents", "observation"].shape == (2, 2, 20, 10)
    assert r["agents", "action"].shape == (2, 2, 20, 1)
    assert env.full_observation_spec["agents", "observation"].shape == (2, 20, 10)
    score = episodes.scores(r)
    assert score.shape == (2,)
