"""Diagnostics: the physical quantities each env declares (the cylinder's drag and lift,
rayleigh's Nusselt number, ...) come with every step in the TensorDict and, under the
same names with ``blew_up``, in the info of every adapter; they are the quantities the
rewards are made of."""

import gymnasium
import numpy as np
import pytest
import torch

import beacon_torch
from beacon_torch.envs import cylinder
from beacon_torch.sb3 import BeaconVecEnv

from conftest import ALL_ENVS, ENVS, EXPENSIVE_ENVS, FAST, make


@pytest.mark.parametrize("env_id", ALL_ENVS)
def test_every_env_reports_its_diagnostics_in_the_tensordict(env_id):
    cls = ENVS[env_id]
    assert cls.physics.diagnostics, f"{env_id} declares no diagnostics"
    env = make(env_id, 2)
    steps = 1 if env_id in EXPENSIVE_ENVS else 3
    rollout = env.rollout(steps)
    for name in cls.physics.diagnostics:
        for where in (rollout["diagnostics", name], rollout["next", "diagnostics", name]):
            assert where.shape == (2, steps) and where.dtype == env.dtype and torch.isfinite(where).all()
    assert set(env.last_diagnostics) == set(cls.physics.diagnostics)


@pytest.mark.parametrize(
    "env_id, name, of_reward",
    [
        ("burgers-v0", "deviation", lambda r: -r),
        ("sloshing-v0", "surface_deviation", lambda r: -r),  # no control: no actuation cost
        ("shkadov-v0", "film_deviation", lambda r: -r),
        ("rayleigh-v0", "nusselt", lambda r: -r),
        ("mixing-v0", "mixing_deviation", lambda r: -r),
    ],
)
def test_the_diagnostics_are_what_the_reward_is_made_of(env_id, name, of_reward):
    env = make(env_id, 2, dtype="float64")
    env.reset()
    _, reward, _, _ = env.step_members(env.null_action())
    torch.testing.assert_close(env.last_diagnostics[name], of_reward(reward), rtol=1e-12, atol=1e-15)


def test_the_cylinders_drag_and_lift_are_its_coefficients():
    env = make("cylinder-v0", 2, dtype="float64")
    env.reset()
    env.step_members(torch.tensor([[0.5, -0.5], [0.0, 0.0]], dtype=torch.float64))
    d = env.last_diagnostics
    assert torch.equal(d["drag"], cylinder.coefficient(env.state.drag))
    assert torch.equal(d["lift"], cylinder.coefficient(env.state.lift))
    assert d["jet"][0] > 0 and d["jet"][1] == 0  # the top jet's rate relaxes towards the action
    lorenz = beacon_torch.make("lorenz-v0", 1)
    lorenz.reset()
    assert lorenz.last_diagnostics["x"] == lorenz.state.xyz[0, 0]


def test_every_adapter_reports_the_same_info():
    """gymnasium's env and vector env, Stable-Baselines3 and PettingZoo: the env's
    diagnostics and blew_up, by the same names, in reset and step."""
    from beacon_torch.pettingzoo import parallel_env

    names = {*ENVS["burgers-v0"].physics.diagnostics, "blew_up"}
    single = gymnasium.make("beacon/burgers-v0", compile=False)
    _, info = single.reset(seed=0)
    assert set(info) == names
    *_, info = single.step(single.action_space.sample())
    assert set(info) == names and info["blew_up"] is False and isinstance(info["deviation"], float)
    vector = gymnasium.make_vec("beacon/burgers-v0", num_envs=3, compile=False)
    vector.reset(seed=0)
    *_, info = vector.step(vector.action_space.sample())
    assert set(info) == names | {f"_{n}" for n in names} and info["deviation"].shape == (3,)
    sb3 = BeaconVecEnv("burgers-v0", n_envs=3, compile=False)
    sb3.reset()
    assert all(set(i) == names for i in sb3.reset_infos)
    *_, infos = sb3.step(np.zeros((3, 1), dtype=np.float32))
    assert all(set(i) == names | {"TimeLimit.truncated"} for i in infos)
    zoo = parallel_env("shkadov-separable-v0", **FAST["shkadov-separable-v0"])
    _, infos = zoo.reset(seed=0)
    zoo_names = {*ENVS["shkadov-separable-v0"].physics.diagnostics, "blew_up"}
    assert all(set(i) == zoo_names for i in infos.values())
    *_, infos = zoo.step({agent: zoo.action_space(agent).sample() for agent in zoo.agents})
    assert all(set(i) == zoo_names for i in infos.values())


def test_blew_up_says_which_member_a_blow_up_ended():
    venv = gymnasium.make_vec("beacon/burgers-v0", num_envs=2, compile=False)
    venv.reset(seed=0)
    base = venv.unwrapped.env
    base.set_state({k: torch.cat([v[:1], v[1:] * 1e30]) for k, v in base.state._asdict().items()})
    *_, terminated, _, info = venv.step(np.zeros((2, 1), dtype=np.float32))
    assert terminated.tolist() == [False, True] and info["blew_up"].tolist() == [False, True]
    assert np.isfinite(info["deviation"]).all()


def test_eval_writes_the_controlled_episode_beside_no_control_and_the_diagnostics(ppo_run, tmp_path, capsys):
    """Beside the controlled animation: both episodes side by side from the same start,
    and the diagnostics per action, controlled against uncontrolled."""
    import shutil

    from PIL import Image

    from beacon_torch.cli import main as cli

    run = tmp_path / "run"
    shutil.copytree(ppo_run, run)
    assert cli(["eval", str(run), "--num-envs", "2"]) == 0
    out = capsys.readouterr().out
    assert "beside no control" in out and "diagnostics" in out
    with Image.open(run / "controlled.gif") as alone, Image.open(run / "side-by-side.gif") as both:
        assert both.size == (2 * alone.size[0], alone.size[1]) and both.n_frames == alone.n_frames
    with Image.open(run / "diagnostics.png") as figure:
        assert figure.size[1] > 400  # a panel per diagnostic of vortex-v0, and the reward
    # --no-gif: the figure alone, under a free name beside the first
    assert cli(["eval", str(run), "--num-envs", "1", "--no-gif"]) == 0
    assert (run / "diagnostics-2.png").is_file() and not (run / "side-by-side-2.gif").exists()
