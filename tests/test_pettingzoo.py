"""PettingZoo's parallel API for the multi-agent layout."""

import numpy as np
import pytest
import torch

pytest.importorskip("pettingzoo")

from pettingzoo.test import parallel_api_test

import beacon_torch
from beacon_torch.pettingzoo import BeaconParallelEnv, multi_agent_envs, parallel_env

FAST = {"random_start": 3}  # few uncontrolled actions at each reset


def test_pettingzoos_own_api_test_passes():
    parallel_api_test(parallel_env("shkadov-separable-v0", compile=False, **FAST), num_cycles=30)


def test_pettingzoos_own_api_test_passes_on_the_convection_segments():
    env = parallel_env("rayleigh-separable-v0", compile=False, period=0.1)
    assert env.possible_agents[0] == "segment_0" and len(env.possible_agents) == 10
    parallel_api_test(env, num_cycles=5)


def test_the_agents_are_the_jets_of_the_batched_env():
    """Per-agent rewards and observations are those of the TorchRL env's agents; their
    mean reward is the single-agent env's."""
    env = parallel_env("shkadov-separable-v0", n_jets=3, dtype="float64", compile=False, **FAST)
    ref = beacon_torch.make("shkadov-separable-v0", 1, n_jets=3, dtype="float64", **FAST)
    obs, _ = env.reset(seed=3)
    ref.set_seed(3)
    ref_obs = ref.reset_members()
    assert env.agents == ["jet_0", "jet_1", "jet_2"]
    for i, agent in enumerate(env.agents):
        np.testing.assert_array_equal(obs[agent], ref_obs[0, i].numpy())
    actions = {"jet_0": np.array([0.5]), "jet_1": np.array([-0.2]), "jet_2": np.array([0.0])}
    obs, rewards, terms, truncs, _ = env.step(actions)
    ref_obs, ref_reward, *_ = ref.step_members(torch.tensor([[[0.5], [-0.2], [0.0]]], dtype=torch.float64))
    assert [rewards[a] for a in env.possible_agents] == ref_reward[0].tolist()
    assert not any(terms.values()) and not any(truncs.values())


def test_an_episode_ends_for_every_agent_at_its_length():
    env = parallel_env("shkadov-separable-v0", n_jets=2, compile=False, **FAST)
    env.reset(seed=0)
    steps = 0
    while env.agents:
        _, _, terms, truncs, _ = env.step({a: env.action_space(a).sample() for a in env.agents})
        steps += 1
    assert steps == env.env.episode_length and all(truncs.values()) and not any(terms.values())
    with pytest.raises(RuntimeError, match="reset"):
        env.step({})


def test_single_agent_envs_and_missing_actions_are_refused():
    assert multi_agent_envs() == [
        "rayleigh-separable-v0",
        "rbc2d-easy-ma-v0",
        "rbc2d-hard-ma-v0",
        "rbc2d-medium-ma-v0",
        "shkadov-separable-v0",
    ]
    with pytest.raises(ValueError, match="one agent"):
        BeaconParallelEnv("shkadov-v0")
    env = parallel_env("shkadov-separable-v0", n_jets=2, compile=False)
    env.reset()
    with pytest.raises(ValueError, match="jet_1"):
        env.step({"jet_0": np.zeros(1)})
    assert parallel_env("shkadov-separable-v0", render_mode="rgb_array", compile=False).metadata["render_modes"]
