"""Bad input, anywhere a user gives it: one clear error that names it."""

import numpy as np
import pytest
import torch

import beacon_torch
from beacon_torch.cli import main as cli

from conftest import run_actions


@pytest.mark.parametrize("option", ["differentiable", "record_history", "check_actions", "grad_checkpoint"])
@pytest.mark.parametrize("value", ["no", 1, None, 0.0])
def test_on_off_options_take_booleans_only(option, value):
    with pytest.raises(TypeError, match=f"{option} must be True or False"):
        beacon_torch.make("lorenz-v0", **{option: value})
    assert beacon_torch.make("lorenz-v0", **{option: np.bool_(False)}).history is not None


@pytest.mark.parametrize(
    "seed, exc", [(-1, ValueError), (2**64, ValueError), (1.5, TypeError), ("7", TypeError), (True, TypeError)]
)
def test_seeds_are_integers_of_64_bits(seed, exc):
    with pytest.raises(exc, match="seed must be an integer"):
        beacon_torch.make("lorenz-v0", seed=seed)
    env = beacon_torch.make("lorenz-v0", seed=2**64 - 1)
    with pytest.raises(exc, match="seed must be an integer"):
        env.set_seed(seed)


@pytest.mark.parametrize("device", ["cuda", "mps", "nonsense"])
def test_an_unusable_device_is_named(device):
    if device == "cuda" and torch.cuda.is_available():
        pytest.skip("a CUDA device is present")
    with pytest.raises(ValueError, match=f"device '{device}'"):
        beacon_torch.make("lorenz-v0", device=device)
    assert cli(["run", "lorenz-v0", "--device", device, "--num-envs", "1"]) == 2


def test_reset_masks_are_bool_with_one_entry_per_member():
    env = beacon_torch.make("vortex-v0", 3)
    env.reset()
    with pytest.raises(TypeError, match="'_reset' mask must be a bool tensor"):
        env.reset(env.reset().set("_reset", torch.ones(3, 1, dtype=torch.int64)))
    from tensordict import TensorDict

    with pytest.raises(ValueError, match="one entry per member"):
        env._reset(TensorDict({"_reset": torch.ones(4, 1, dtype=torch.bool)}, batch_size=[]))


def test_set_state_refuses_non_finite_values_and_counts_outside_the_episode():
    env = beacon_torch.make("vortex-v0", 2)
    env.reset()
    state = {k: v.clone() for k, v in env.state._asdict().items()}
    with pytest.raises(ValueError, match="count must be in"):
        env.set_state(state, count=env.episode_length)
    with pytest.raises(ValueError, match="count must be in"):
        env.set_state(state, count=-1)
    state["ay"][1, 0] = float("nan")
    with pytest.raises(ValueError, match="state.ay has values that are not finite in torch.float32"):
        env.set_state(state)


def test_render_index_names_the_members():
    env = beacon_torch.make("vortex-v0", 2)
    env.render_index = 1
    for bad in (2, -1, 0.5, True):
        with pytest.raises(ValueError, match="render_index must be a member's index in \\[0, 2\\)"):
            env.render_index = bad
    assert env.render_index == 1


def test_an_action_that_requires_grad_warns_once_on_a_plain_env():
    env = beacon_torch.make("vortex-v0", 2)
    td = env.reset()
    td["action"] = torch.zeros(2, 2, requires_grad=True)
    with pytest.warns(UserWarning, match="gradient is dropped"):
        td = env.step(td)["next"]
    td["action"] = torch.zeros(2, 2, requires_grad=True)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env.step(td)


def test_compile_options_as_the_quick_start_shows_step():
    env = beacon_torch.make("lorenz-v0", 2, compile={"mode": "default"}, seed=0)
    eager = beacon_torch.make("lorenz-v0", 2, seed=0)
    g = torch.Generator().manual_seed(0)
    actions = [env.random_action(g) for _ in range(3)]
    torch.testing.assert_close(run_actions(env, actions), run_actions(eager, actions))


@pytest.mark.parametrize(
    "setting, value, words",
    [
        ("actor_lr", float("nan"), "'actor_lr' must be finite and > 0"),
        ("gamma", 5.0, "'gamma' must be finite and in (0, 1]"),
        ("clip", -1.0, "'clip' must be finite and > 0"),
        ("entropy", -0.1, "'entropy' must be finite and >= 0"),
        ("frames", 100, "frames (100) must be at least one collected batch"),
    ],
)
def test_training_settings_out_of_their_domain_are_refused(setting, value, words):
    from beacon_torch.training.config import PPOConfig, configure

    with pytest.raises(ValueError) as err:
        configure(PPOConfig, "lorenz-v0", **{setting: value})
    assert words in str(err.value)


def test_bench_needs_positive_steps_and_repeats(capsys):
    for option in ("--steps", "--repeats"):
        assert cli(["bench", "--envs", "lorenz-v0", option, "0"]) == 2
        assert f"{option} must be a positive integer" in capsys.readouterr().err


def test_absurd_batch_sizes_are_refused_before_any_allocation():
    with pytest.raises(ValueError, match="beyond what one env holds"):
        beacon_torch.make("lorenz-v0", 10**12)


def test_cli_paths_that_cannot_be_written_are_one_line(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("a file where a folder should go")
    assert cli(["run", "lorenz-v0", "--num-envs", "1", "--out", str(blocker / "sub")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and str(blocker) in err


def test_a_member_stepped_after_its_episode_goes_on_as_documented():
    env = beacon_torch.make("lorenz-v0", 2, rho=[28.0, 1e6], seed=0)
    td = env.reset()
    for _ in range(env.episode_length):
        td["action"] = torch.ones(2, dtype=torch.int64)
        out = env.step(td)["next"]
        td = out
    assert out["truncated"].all() and out["terminated"][1] and not out["terminated"][0]
    td["action"] = torch.ones(2, dtype=torch.int64)
    again = env.step(td)["next"]
    assert again["truncated"].all() and int(env.step_count[0]) == env.episode_length + 1
    assert torch.isfinite(again["observation"]).all()
    assert again["terminated"][1] and again["reward"][1] == env.physics.blowup_reward


def test_reset_takes_a_seed_and_a_rollout_without_a_policy_reproduces():
    first, second = (beacon_torch.make("burgers-v0", 2, seed=3).rollout(20) for _ in range(2))
    assert torch.equal(first["action"], second["action"]) and torch.equal(
        first["next", "reward"], second["next", "reward"]
    )
    env = beacon_torch.make("burgers-v0", 2, seed=9)
    env.reset(seed=3)  # as make(..., seed=3)
    again = env.rollout(20, auto_reset=False, tensordict=env.current())
    assert torch.equal(first["next", "reward"], again["next", "reward"])
    with pytest.raises(TypeError, match="unknown keyword\\(s\\) \\['sed'\\]"):
        env.reset(sed=5)
    # the random actions leave the physics' stream as it is: the inlet noise of a
    # rollout without a policy is that of the same steps under other actions
    other = beacon_torch.make("burgers-v0", 2, seed=3)
    other.reset()
    for _ in range(20):
        other.step_members(other.null_action())
    rolled = beacon_torch.make("burgers-v0", 2, seed=3)
    rolled.rollout(20)
    assert torch.equal(other.rng.get_state(), rolled.rng.get_state())
