"""Gymnasium interop: registration, the single env, the vector env."""

import gymnasium
import numpy as np
import pytest
import torch

import beacon_torch
import beacon_torch.gym

from conftest import FAST


def test_gym_env_reproduces_the_uncontrolled_score():
    env = gymnasium.make("beacon/lorenz-v0", dtype="float64")
    obs, _ = env.reset(seed=0)
    assert obs.dtype == np.float64
    total, steps, truncated = 0.0, 0, False
    while not truncated:
        obs, reward, terminated, truncated, _ = env.step(1)
        assert not terminated
        total += reward
        steps += 1
    assert (total, steps) == (207.0, 500)


def test_gym_parameters_pass_through_and_are_validated():
    env = gymnasium.make("beacon/vortex-v0", re=60.0)
    assert env.unwrapped.env.params.re == 60.0
    with pytest.raises(ValueError, match="'re'"):
        gymnasium.make("beacon/vortex-v0", re=-1.0)


def test_gym_bad_actions():
    env = gymnasium.make("beacon/vortex-v0").unwrapped
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"\(2,\)"):
        env.step(np.zeros(3, dtype=np.float32))
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.array([np.nan, 0.0], dtype=np.float32))
    env = gymnasium.make("beacon/lorenz-v0").unwrapped
    env.reset(seed=0)
    with pytest.raises(TypeError, match="integer"):
        env.step(0.5)
    with pytest.raises(ValueError, match=r"\[0, 2\]"):
        env.step(3)


@pytest.mark.parametrize("env_id", ["lorenz-v0", "vortex-v0", "burgers-v0", "shkadov-separable-v0"])
def test_vector_env_is_the_batched_env(env_id):
    kw = FAST.get(env_id, {})
    venv = gymnasium.make_vec(f"beacon/{env_id}", num_envs=4, dtype="float64", **kw)
    assert isinstance(venv.unwrapped, beacon_torch.gym.BeaconVectorEnv)
    obs, _ = venv.reset(seed=0)
    assert obs.shape == (4, *venv.single_observation_space.shape)
    ref = beacon_torch.make(env_id, 4, dtype=torch.float64, seed=0, **kw)
    td = ref.reset()
    venv.action_space.seed(0)
    for _ in range(5):
        actions = venv.action_space.sample()
        obs, reward, terminated, truncated, _ = venv.step(actions)
        td[ref.action_key] = torch.as_tensor(actions)
        td = ref.step(td)["next"]
        np.testing.assert_array_equal(obs, td[ref.observation_key].numpy())
        team = td[ref.reward_key].reshape(4, -1).double().mean(-1)
        np.testing.assert_allclose(reward, team.numpy(), rtol=1e-12)
    assert reward.shape == terminated.shape == truncated.shape == (4,)


def test_vector_env_autoresets_on_the_next_step():
    venv = gymnasium.make_vec("beacon/lorenz-v0", num_envs=3)
    first, _ = venv.reset(seed=0)
    ones = np.ones(3, dtype=np.int64)
    for _ in range(499):
        obs, reward, terminated, truncated, _ = venv.step(ones)
        assert not truncated.any()
    obs, reward, terminated, truncated, _ = venv.step(ones)
    assert truncated.all() and not terminated.any()
    obs, reward, terminated, truncated, _ = venv.step(ones)
    np.testing.assert_array_equal(obs, first)
    np.testing.assert_array_equal(reward, 0.0)
    assert not (terminated | truncated).any()


def test_vector_env_partial_reset_mask():
    venv = gymnasium.make_vec("beacon/vortex-v0", num_envs=3)
    first, _ = venv.reset(seed=0)
    for _ in range(4):
        obs, *_ = venv.step(np.zeros((3, 2), dtype=np.float32))
    again, _ = venv.reset(options={"reset_mask": np.array([False, True, False])})
    np.testing.assert_array_equal(again[1], first[1])
    np.testing.assert_array_equal(again[[0, 2]], obs[[0, 2]])


# ---------------------------------------------------------------- the lean path
def test_gym_env_blow_up_terminates_with_the_penalty():
    env = gymnasium.make("beacon/burgers-v0", amp=1e8).unwrapped
    last, _ = env.reset(seed=0)
    for _ in range(5):
        obs, reward, terminated, truncated, _ = env.step(np.ones(1, dtype=np.float32))
        assert np.isfinite(obs).all() and np.isfinite(reward)
        if terminated:
            break
        last = obs
    assert terminated and reward == env.env.physics.blowup_reward
    np.testing.assert_array_equal(obs, last)  # the last finite observation is kept


def run_python(code: str, tmp_path):
    import subprocess
    import sys

    script = tmp_path / "script.py"
    script.write_text(code)
    return subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True, timeout=300)


def test_gym_ids_need_no_import_of_ours(tmp_path):
    """gymnasium's own 'module:id' spelling imports us; importing beacon_torch is enough
    for the plain ids (gymnasium 1 has no plugin entry points to do it at its import)."""
    proc = run_python(
        "import sys, gymnasium\n"
        "env = gymnasium.make('beacon_torch:beacon/lorenz-v0', compile=False)\n"
        "assert env.reset(seed=0)[0].shape == (6,)\n"
        "assert 'beacon_torch.gym' in sys.modules\n"
        "import beacon_torch\n"
        "env = gymnasium.make('beacon/vortex-v0', compile=False)\n"
        "print('ok', env.spec.max_episode_steps)\n",
        tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == ["ok", "800"]


@pytest.mark.parametrize("env_id", beacon_torch.list_envs())
def test_gym_specs_know_the_episode_length(env_id):
    spec = gymnasium.spec(f"beacon/{env_id}")
    assert spec.max_episode_steps == beacon_torch.registry.env_spec(env_id).physics.episode_length


def test_vector_env_keeps_the_benchmark_episode_length():
    venv = gymnasium.make_vec("beacon/lorenz-v0", 2, compile=False)  # the spec's length passes through
    assert venv.env.episode_length == 500
    with pytest.raises(ValueError, match="500 actions long"):
        gymnasium.make_vec("beacon/lorenz-v0", 2, max_episode_steps=100, compile=False)


def test_torchrl_gym_env_builds_our_ids():
    """TorchRL's GymEnv passes gymnasium options our env does not take (frameskip) and
    retries without them on Python's own error words: ours say them."""
    from torchrl.envs import GymEnv
    from torchrl.envs.utils import check_env_specs

    env = GymEnv("beacon/lorenz-v0", compile=False)
    check_env_specs(env)
    rollout = env.rollout(5)
    assert rollout.shape == (5,) and rollout["next", "reward"].shape == (5, 1)
    with pytest.raises(TypeError, match="unexpected keyword argument 'frameskip'"):
        beacon_torch.make("lorenz-v0", frameskip=1)


def test_async_vector_env_without_a_main_guard_as_documented(tmp_path):
    """Making an env imports TorchRL, which sets multiprocessing to spawn; gymnasium's
    async vector env in a script without a main guard then needs the documented context."""
    code = (
        "import multiprocessing, gymnasium, beacon_torch\n"
        "beacon_torch.make('lorenz-v0')\n"
        "assert multiprocessing.get_start_method() == 'spawn'\n"
        "venv = gymnasium.make_vec('beacon/lorenz-v0', 2, vectorization_mode='async', "
        "vector_kwargs={'context': 'fork'}, compile=False)\n"
        "obs, _ = venv.reset(seed=0)\n"
        "obs, *_ = venv.step(venv.action_space.sample())\n"
        "venv.close()\n"
        "print('ok', obs.shape)\n"
    )
    proc = run_python(code, tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == ["ok", "(2,", "6)"]


def test_record_video_writes_an_episode(tmp_path):
    """gymnasium's RecordVideo on our frames (the 'video' extra: moviepy)."""
    pytest.importorskip("moviepy")
    env = gymnasium.make("beacon/lorenz-v0", render_mode="rgb_array", max_episode_steps=10, compile=False)
    env = gymnasium.wrappers.RecordVideo(env, str(tmp_path / "videos"), episode_trigger=lambda episode: True)
    env.reset(seed=0)
    truncated = False
    while not truncated:
        *_, truncated, _ = env.step(1)
    env.close()
    (video,) = (tmp_path / "videos").glob("*.mp4")
    assert video.stat().st_size > 1000


def test_the_gymnasium_ids_registered_at_import_are_the_envs():
    from beacon_torch import gym_ids
    from beacon_torch.registry import ENVS, ORIGIN

    own = {env_id: spec.physics.episode_length for env_id, spec in ENVS.items() if env_id not in ORIGIN}
    assert gym_ids.BUILT_IN == own
