import pytest
import torch

import beacon_torch

ALL_ENVS = beacon_torch.list_envs()
CONTINUOUS_ENVS = [e for e in ALL_ENVS if not beacon_torch.registry.ENVS[e].discrete]
DISCRETE_ENVS = [e for e in ALL_ENVS if beacon_torch.registry.ENVS[e].discrete]
DETERMINISTIC_ENVS = [e for e in ALL_ENVS if beacon_torch.registry.ENVS[e].deterministic]

# cheaper settings for the behaviour tests that run on every env (the published numbers
# are checked with the defaults in test_scores.py)
FAST = {
    "shkadov-v0": {"random_start": 3},
    "shkadov-separable-v0": {"random_start": 3},
}


def make(env_id, batch_size=1, **kwargs):
    return beacon_torch.make(env_id, batch_size, **{**FAST.get(env_id, {}), **kwargs})


@pytest.fixture(params=ALL_ENVS)
def env_id(request):
    return request.param


def run_actions(env, actions):
    """Step ``env`` from a reset through ``actions`` (a list of action batches);
    return the stacked observations and rewards."""
    td = env.reset()
    obs, rew = [], []
    for a in actions:
        td[env.action_key] = a
        td = env.step(td)["next"]
        obs.append(td[env.observation_key].clone())
        rew.append(td[env.reward_key].clone())
    return torch.stack(obs, 1), torch.stack(rew, 1)
