import pytest
import torch

import beacon_torch

ALL_ENVS = beacon_torch.list_envs()
CONTINUOUS_ENVS = [e for e in ALL_ENVS if not beacon_torch.registry.ENVS[e].discrete]
DISCRETE_ENVS = [e for e in ALL_ENVS if beacon_torch.registry.ENVS[e].discrete]


@pytest.fixture(params=ALL_ENVS)
def env_id(request):
    return request.param


def run_actions(env, actions):
    """Step ``env`` from a reset through ``actions`` (a list of action batches);
    return the stacked observations and rewards."""
    td = env.reset()
    obs, rew = [], []
    for a in actions:
        td["action"] = a
        td = env.step(td)["next"]
        obs.append(td["observation"].clone())
        rew.append(td["reward"].clone())
    return torch.stack(obs, 1), torch.stack(rew, 1)
