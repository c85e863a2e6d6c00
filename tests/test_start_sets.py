"""Named start sets: developed, uncontrolled states that train, validation and test
episodes begin from."""

from __future__ import annotations

import pytest
import torch

import beacon_torch
from beacon_torch import starts
from beacon_torch.cli import main as cli


@pytest.mark.parametrize("env_id", ["lorenz-v0", "vortex-v0", "burgers-v0", "sloshing-v0"])
def test_a_start_is_where_the_uncontrolled_env_of_the_sets_seed_stands_after_its_offset(env_id):
    seed, size, _ = starts.SETS["test"]
    env = beacon_torch.make(env_id, size, dtype="float64", starts="test")
    env.reset()
    ref = beacon_torch.make(env_id, size, dtype="float64", seed=seed)
    ref.reset()
    at = starts.offsets("test", ref.episode_length)
    for step in range(int(at.max()) + 1):
        if step:
            ref.step_members(ref.null_action())
        for k in (at == step).nonzero()[:, 0].tolist():
            for got, want in zip(env.state, ref.state, strict=True):
                assert torch.equal(got[k], want[k])
    # every start begins a whole episode
    assert (env.state_dict()["count"] == 0).all()


def test_the_three_sets_are_disjoint_even_without_noise_and_fixed():
    length = beacon_torch.make("lorenz-v0").episode_length
    offsets = {name: set(starts.offsets(name, length).tolist()) for name in starts.SETS}
    assert all(0 <= k < length for ks in offsets.values() for k in ks)
    assert not (offsets["train"] & offsets["validation"] or offsets["train"] & offsets["test"])
    assert not offsets["validation"] & offsets["test"]
    # lorenz has no noise: its starts differ only by their offsets, and all of them do
    obs = {
        name: beacon_torch.make("lorenz-v0", size, dtype="float64", starts=name).reset()["observation"]
        for name, (_, size, _) in starts.SETS.items()
    }
    test, validation = obs["test"], obs["validation"]
    assert torch.cdist(test, validation).min() > 0 and torch.cdist(test, obs["train"]).min() > 0
    # the same episodes for every evaluation, whatever the env's own seed
    again = beacon_torch.make("lorenz-v0", 8, dtype="float64", seed=99, starts="test").reset()["observation"]
    assert torch.equal(again, test)


def test_members_take_the_sets_states_in_order_and_a_partial_reset_keeps_the_others():
    env = beacon_torch.make("burgers-v0", 10, dtype="float64", starts="test")
    first = env.reset()["observation"].clone()
    assert torch.equal(first[8:], first[:2])  # member i takes state i modulo the set's 8
    env.rollout(5)
    moved = env.observation.clone()
    mask = torch.zeros(10, dtype=torch.bool)
    mask[3] = True
    env.reset_members(mask)
    assert torch.equal(env.observation[3], first[3])
    assert torch.equal(env.observation[~mask], moved[~mask])


def test_train_starts_are_drawn_from_the_envs_generator():
    a, b, c = (beacon_torch.make("lorenz-v0", 16, dtype="float64", seed=s, starts="train") for s in (1, 1, 2))
    oa, ob, oc = (env.reset()["observation"] for env in (a, b, c))
    assert torch.equal(oa, ob) and not torch.equal(oa, oc)
    pool = starts.states(a, "train")
    assert pool[0].shape[0] == starts.SETS["train"][1]
    # each member's start is one of the pool's states
    assert all(bool((pool.xyz == row).all(-1).any()) for row in a.state.xyz)


def test_start_sets_refuse_what_they_cannot_hold():
    with pytest.raises(ValueError, match="starts must be one of train, validation, test"):
        beacon_torch.make("lorenz-v0", 2, starts="holdout")
    env = beacon_torch.make("burgers-v0", 2, amp=[1.0, 2.0], starts="test")
    with pytest.raises(ValueError, match="parameters shared by the members; amp differs"):
        env.reset()


def test_eval_runs_a_shipped_policy_from_the_test_starts_by_default(tmp_path, capsys):
    from beacon_torch import pretrained
    from beacon_torch.training.evaluation import evaluate_policy

    assert cli(["eval", "--pretrained", "ppo/lorenz-v0", "--out", str(tmp_path), "--no-gif"]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert "the test set's starts" in line and (tmp_path / "ppo" / "lorenz-v0-diagnostics.png").is_file()
    held_out = evaluate_policy("lorenz-v0", pretrained.load("ppo/lorenz-v0"), starts="test")
    assert f"score {held_out['score_mean']:.6g}" in line and f"uncontrolled {held_out['uncontrolled']:.6g}" in line
    assert (
        cli(["eval", "--pretrained", "ppo/lorenz-v0", "--starts", "own", "--out", str(tmp_path / "own"), "--no-gif"])
        == 0
    )
    line = capsys.readouterr().out.strip().splitlines()[-1]
    own = evaluate_policy("lorenz-v0", pretrained.load("ppo/lorenz-v0"))
    assert "the env's own start" in line and f"score {own['score_mean']:.6g}" in line


def test_a_recipe_trains_from_the_train_starts_and_refuses_the_held_out_ones(tmp_path, capsys):
    from beacon_torch.training.config import PPOConfig, configure, parse
    from beacon_torch.training.env import recipe_env
    from beacon_torch.training.run import load_checkpoint
    from recipes import ppo

    tiny = dict(frames=200, n_rollout=200, num_envs=4, epochs=1, progress=False, out=str(tmp_path))
    cfg = configure(PPOConfig, "lorenz-v0", starts="train", **tiny)
    env = recipe_env(cfg, None)
    pool = starts.states(env.base_env, "train")
    env.reset()
    assert env.base_env.starts == "train"
    assert all(bool((pool.xyz == row).all(-1).any()) for row in env.base_env.state.xyz)
    ppo.main(cfg)
    assert load_checkpoint(tmp_path)["config"]["starts"] == "train"
    for held_out in ("validation", "test"):
        with pytest.raises(SystemExit):
            parse(PPOConfig, ["--env", "lorenz-v0", "--starts", held_out])
        assert "--starts" in capsys.readouterr().err
