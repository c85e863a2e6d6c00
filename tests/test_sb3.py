"""Stable-Baselines3 on the batched envs (beacon_torch.sb3)."""

import gymnasium
import numpy as np
import pytest
import torch

pytest.importorskip("stable_baselines3")
from stable_baselines3 import PPO
from stable_baselines3.common.env_checker import check_env
from stable_baselines3.common.vec_env import DummyVecEnv, VecCheckNan, VecMonitor, VecNormalize

import beacon_torch
import beacon_torch.gym
from beacon_torch.sb3 import BeaconVecEnv

from conftest import FAST


def test_sb3_check_env_accepts_the_single_env():
    check_env(gymnasium.make("beacon/burgers-v0").unwrapped, warn=False)
    check_env(gymnasium.make("beacon/lorenz-v0").unwrapped, warn=False)


@pytest.mark.parametrize("env_id", ["lorenz-v0", "vortex-v0", "burgers-v0", "shkadov-separable-v0"])
def test_vec_env_is_the_batched_env(env_id):
    kw = FAST.get(env_id, {})
    venv = BeaconVecEnv(env_id, 4, dtype="float64", seed=0, **kw)
    ref = beacon_torch.make(env_id, 4, dtype=torch.float64, seed=0, **kw)
    td = ref.reset()
    np.testing.assert_array_equal(venv.reset(), td[ref.observation_key].numpy())
    g = torch.Generator().manual_seed(0)
    for _ in range(5):
        action = ref.random_action(g)
        obs, reward, done, infos = venv.step(action.numpy())
        td[ref.action_key] = action
        td = ref.step(td)["next"]
        np.testing.assert_array_equal(obs, td[ref.observation_key].numpy())
        team = td[ref.reward_key].reshape(4, -1).double().mean(-1).float()
        np.testing.assert_array_equal(reward, team.numpy())
        assert reward.dtype == np.float32 and done.dtype == bool and len(infos) == 4
        assert not done.any()


def test_vec_env_resets_a_copy_within_the_step_that_ends_it():
    """SB3's convention: the returned observation is the new episode's first, the last
    one is in the infos, with whether the time limit cut the episode."""
    venv = BeaconVecEnv("lorenz-v0", 3)
    first = venv.reset()
    ones = np.ones(3, dtype=np.int64)
    for _ in range(499):
        obs, reward, done, infos = venv.step(ones)
        assert not done.any() and not any(info["TimeLimit.truncated"] for info in infos)
    last = venv.env.observation.numpy().copy()
    obs, reward, done, infos = venv.step(ones)
    assert done.all()
    np.testing.assert_array_equal(obs, first)
    for i, info in enumerate(infos):
        assert info["TimeLimit.truncated"] is True
        assert info["terminal_observation"].shape == first.shape[1:]
        assert not np.array_equal(info["terminal_observation"], last[i])  # the 500th step's
    assert (venv.env.step_count == 0).all()


def test_vec_env_blow_up_is_a_termination_not_a_time_limit():
    venv = BeaconVecEnv("burgers-v0", 2, amp=[10.0, 1e8])
    venv.reset()
    for _ in range(5):
        obs, reward, done, infos = venv.step(np.ones((2, 1), dtype=np.float32))
        if done[1]:
            break
    assert done[1] and not done[0]
    assert reward[1] == venv.env.physics.blowup_reward
    assert infos[1]["TimeLimit.truncated"] is False and np.isfinite(infos[1]["terminal_observation"]).all()
    assert "terminal_observation" not in infos[0]
    assert np.isfinite(obs).all() and venv.env.step_count[1] == 0


def test_vec_env_seeding():
    """seed(s) fixes the next reset's random stream (shkadov's random starts draw from
    it); it applies to that reset only."""

    def run(env_id, seed, **kw):
        venv = BeaconVecEnv(env_id, 3, **kw)
        venv.seed(seed)
        obs = [venv.reset()]
        obs += [venv.step(np.zeros((3, *venv.action_space.shape), dtype=np.float32))[0] for _ in range(30)]
        return np.stack(obs)

    kw = FAST["shkadov-v0"]
    np.testing.assert_array_equal(run("shkadov-v0", 5, **kw), run("shkadov-v0", 5, **kw))
    assert not np.array_equal(run("shkadov-v0", 5, **kw), run("shkadov-v0", 6, **kw))
    venv = BeaconVecEnv("shkadov-v0", 2, **FAST["shkadov-v0"])
    venv.seed(1)
    first = venv.reset()
    assert venv._seeds == [None, None]
    assert not np.array_equal(first, venv.reset())  # unseeded: the stream goes on


def test_vec_env_attributes_methods_and_errors():
    venv = BeaconVecEnv("vortex-v0", 3, re=[50.0, 60.0, 70.0])
    assert venv.get_attr("re") == [50.0, 60.0, 70.0]
    assert venv.get_attr("re", indices=[2]) == [70.0]
    assert venv.get_attr("render_mode") == [None] * 3
    assert venv.get_attr("episode_length", 0) == [venv.env.episode_length]
    assert venv.env_is_wrapped(gymnasium.Wrapper) == [False] * 3
    assert len(venv.env_method("set_seed", 4)) == 3
    venv.set_attr("render_index", 1)
    assert venv.env.render_index == 1
    with pytest.raises(AttributeError, match="no_such"):
        venv.get_attr("no_such")
    with pytest.raises(ValueError, match="all 3"):
        venv.set_attr("render_index", 1, indices=[0])
    with pytest.raises(ValueError, match="all 3"):
        venv.env_method("set_seed", 4, indices=[1])
    with pytest.raises(IndexError, match="outside"):
        venv.get_attr("re", indices=[3])
    with pytest.raises(ValueError, match=r"\(3, 2\)"):
        venv.step(np.zeros((2, 2), dtype=np.float32))
    with pytest.raises(ValueError, match="render_mode"):
        BeaconVecEnv("vortex-v0", 2, render_mode="human")


def test_vec_env_renders_each_copy():
    venv = BeaconVecEnv("lorenz-v0", 2, render_mode="rgb_array", rho=[28.0, 35.0])
    venv.reset()
    for _ in range(20):
        venv.step(np.array([0, 2]))
    frames = venv.get_images()
    assert len(frames) == 2 and all(f.ndim == 3 and f.dtype == np.uint8 for f in frames)
    assert not np.array_equal(frames[0], frames[1])
    np.testing.assert_array_equal(venv.env_method("render", indices=[1])[0], frames[1])
    assert venv.render().ndim == 3  # SB3 tiles the copies' frames
    assert BeaconVecEnv("lorenz-v0", 2).get_images() == [None, None]


def test_sb3_ppo_trains_on_the_vec_env_with_its_wrappers(tmp_path, monkeypatch):
    """SB3's PPO, unmodified, through VecMonitor, VecNormalize and VecCheckNan (which
    raises on any non-finite observation, reward or action): it runs, the networks
    change, and the monitor sees whole episodes."""
    monkeypatch.setenv("SB3_LOGDIR", str(tmp_path))  # SB3 makes a log folder even when silent
    torch.manual_seed(0)
    venv = VecCheckNan(VecNormalize(VecMonitor(BeaconVecEnv("burgers-v0", 8, seed=0))), raise_exception=True)
    model = PPO("MlpPolicy", venv, n_steps=64, batch_size=128, n_epochs=2, seed=0, device="cpu")
    before = [p.detach().clone() for p in model.policy.parameters()]
    model.learn(4096)
    assert model.num_timesteps >= 4096
    assert any(not torch.equal(a, b) for a, b in zip(before, model.policy.parameters(), strict=True))
    assert len(model.ep_info_buffer) >= 16  # burgers episodes are 200 actions long
    for info in model.ep_info_buffer:
        assert info["l"] == venv.unwrapped.env.episode_length and np.isfinite(info["r"])


def test_vec_env_matches_sb3_dummy_vec_env_of_single_envs():
    """The batched copies give what SB3's own DummyVecEnv of gymnasium envs gives."""
    dummy = DummyVecEnv([lambda: gymnasium.make("beacon/vortex-v0") for _ in range(3)])
    venv = BeaconVecEnv("vortex-v0", 3)
    np.testing.assert_array_equal(dummy.reset(), venv.reset())
    g = np.random.default_rng(0)
    for _ in range(6):
        action = g.uniform(-1, 1, (3, 2)).astype(np.float32)
        a, b = dummy.step(action), venv.step(action)
        for x, y in zip(a[:3], b[:3], strict=True):
            np.testing.assert_array_equal(x, y)
