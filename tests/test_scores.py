"""The uncontrolled scores of the published implementation (SPEC.md), in float64."""

import pytest
import torch

import beacon_torch
from beacon_torch import evaluate


def uncontrolled(env_id, batch_size, **params):
    env = beacon_torch.make(env_id, batch_size, dtype=torch.float64, **params)
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
