"""The uncontrolled scores of the published implementation (SPEC.md), in float64."""

import pytest
import torch

import beacon_torch
from beacon_torch import evaluate


def uncontrolled(env_id, batch_size, seed=None, **params):
    env = beacon_torch.make(env_id, batch_size, dtype=torch.float64, seed=seed, **params)
    rollout = evaluate.episode(env, evaluate.null_policy(env))
    assert rollout.shape == (batch_size, env.episode_length)
    assert rollout["next", "truncated"][:, -1].all()
    assert not rollout["next", "done"][:, :-1].any()
    return evaluate.scores(rollout)


@pytest.mark.parametrize("env_id", ["lorenz-v0", "lorenz-continuous-v0"])
def test_lorenz_uncontrolled_score_is_exactly_207(env_id):
    score = uncontrolled(env_id, 16)
    assert score.tolist() == [207.0] * 16


def test_vortex_uncontrolled_score_low_cycle():
    score = uncontrolled("vortex-v0", 4)
    assert torch.all((score - 0.006075).abs() <= 0.02 * 0.006075), score


def test_vortex_uncontrolled_score_high_cycle():
    score = uncontrolled("vortex-v0", 2, a0=0.05 + 0.05j, y0=0.05 + 0.05j)
    assert torch.all((score - 19.23).abs() <= 0.02 * 19.23), score


def test_vortex_per_member_initial_states_score_like_separate_runs():
    low = complex(-0.00385, -0.00378), complex(0.00118, -0.00131)
    high = 0.05 + 0.05j, 0.05 + 0.05j
    score = uncontrolled("vortex-v0", 2, a0=[low[0], high[0]], y0=[low[1], high[1]])
    assert score[0].item() == pytest.approx(0.006075, rel=0.02)
    assert score[1].item() == pytest.approx(19.23, rel=0.02)


def test_random_policy_is_reproducible_from_its_seed():
    env = beacon_torch.make("lorenz-v0", 8, dtype=torch.float64)
    a = evaluate.scores(evaluate.episode(env, evaluate.random_policy(env, seed=3)))
    b = evaluate.scores(evaluate.episode(env, evaluate.random_policy(env, seed=3)))
    assert torch.equal(a, b)
    assert a.unique().numel() > 1  # members draw different actions


def test_burgers_uncontrolled_mean_over_256_members():
    score = uncontrolled("burgers-v0", 256, seed=0)
    assert abs(score.mean().item() + 3.25) <= 0.03 * 3.25, score.mean()
    # the published spread: std 0.28, range -4.07..-2.48 over 200 episodes
    assert 0.2 < score.std().item() < 0.4
    assert score.unique().numel() == 256  # every member draws its own inlet noise


SLOSHING_REFERENCE = -2.157
SLOSHING_OURS = -2.2803  # see docs/envs/sloshing.md: 5.7 % from the reference


@pytest.mark.xfail(strict=True, reason="open discrepancy with the published implementation (docs/envs/sloshing.md)")
def test_sloshing_uncontrolled_score_matches_the_published_one():
    score = uncontrolled("sloshing-v0", 1)
    assert abs(score.item() - SLOSHING_REFERENCE) <= 0.02 * abs(SLOSHING_REFERENCE)


def test_sloshing_uncontrolled_score_is_the_documented_one():
    score = uncontrolled("sloshing-v0", 2)
    assert score[0] == score[1]
    assert score[0].item() == pytest.approx(SLOSHING_OURS, rel=1e-4)


def test_shkadov_uncontrolled_mean_over_16_random_starts():
    score = uncontrolled("shkadov-v0", 16, seed=0)
    assert abs(score.mean().item() + 2.32) <= 0.05 * 2.32, score.mean()
    assert ((score > -2.8) & (score < -1.9)).all(), score
    assert score.unique().numel() == 16


def test_rayleigh_developed_state_has_the_published_nusselt_number():
    from beacon_torch.envs.rayleigh import nusselt

    env = beacon_torch.make("rayleigh-v0", 1, dtype=torch.float64)
    env.reset()
    assert nusselt(env.state["theta"], env.dy).item() == pytest.approx(2.16, rel=0.01)


def test_rayleigh_uncontrolled_score():
    score = uncontrolled("rayleigh-v0", 2)
    assert score[0] == score[1]
    assert score[0].item() == pytest.approx(-216.3, rel=0.02)


def test_mixing_constant_actions_score_like_the_published_baseline():
    env = beacon_torch.make("mixing-v0", 4, dtype=torch.float64)
    actions = torch.arange(4)
    rollout = evaluate.episode(env, lambda td: td.set("action", actions))
    score = evaluate.scores(rollout)
    assert score[0].item() == pytest.approx(-17.48, rel=0.02)
    assert (score.max() - score.min()).item() <= 0.01 * abs(score.mean().item())
