import os

import pytest
import torch

import beacon_torch

if os.environ.get("PYTEST_XDIST_WORKER"):
    # one intra-op thread per worker: two workers with two threads each on two cores
    # slow the matrix-heavy 2-D solvers down several times
    torch.set_num_threads(1)

ALL_ENVS = beacon_torch.list_envs()
CONTINUOUS_ENVS = [e for e in ALL_ENVS if not beacon_torch.registry.ENVS[e].discrete]
DISCRETE_ENVS = [e for e in ALL_ENVS if beacon_torch.registry.ENVS[e].discrete]
DETERMINISTIC_ENVS = [e for e in ALL_ENVS if beacon_torch.registry.ENVS[e].deterministic]
# the 2-D cavities take tens of seconds an episode: their whole episodes are run by
# test_scores.py, the behaviour tests that need whole episodes run on the others
EXPENSIVE_ENVS = {"rayleigh-v0", "mixing-v0", "mixing-continuous-v0"}
CHEAP_ENVS = [e for e in ALL_ENVS if e not in EXPENSIVE_ENVS]

# cheaper settings for the behaviour tests that run on every env (the published numbers
# are checked with the defaults in test_scores.py): mixing on a 30 x 30 cavity of the
# same scheme and the same probes, a tenth of the published grid's cost
SMALL_CAVITY = {"L": 0.3, "H": 0.3, "side": 0.2}
FAST = {
    "shkadov-v0": {"random_start": 3},
    "shkadov-separable-v0": {"random_start": 3},
    "mixing-v0": SMALL_CAVITY,
    "mixing-continuous-v0": SMALL_CAVITY,
}


def make(env_id, batch_size=1, **kwargs):
    return beacon_torch.make(env_id, batch_size, **{**FAST.get(env_id, {}), **kwargs})


@pytest.fixture(params=ALL_ENVS)
def env_id(request):
    return request.param


@pytest.fixture(params=CHEAP_ENVS)
def cheap_env_id(request):
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


# The longest tests start first, so that no episode of minutes runs alone at the end
# while the other worker idles. xdist hands the first tests out in turn (odd ones to one
# worker, even ones to the other): the mixing episode (about 4 minutes) takes one
# worker while the other runs the next ones.
SLOW_FIRST = [
    "tests/test_scores.py::test_mixing_constant_actions_score_like_the_published_baseline",
    "tests/test_scores.py::test_shkadov_uncontrolled_mean_and_spread_over_64_random_starts",
    "tests/test_scores.py::test_rayleigh_uncontrolled_score_from_the_published_start",
    "tests/test_reference.py::test_mixing_agrees_within_the_published_solver_tolerance",
    "tests/test_reference.py::test_rayleigh_with_the_published_jacobi_solve_agrees_to_round_off",
    "tests/test_recipes.py::test_multi_agent_ppo_shares_one_policy_and_scores_the_team",
    "tests/test_recipes.py::test_short_training_beats_the_random_policy",
    "tests/test_reference.py::test_rayleigh_with_the_direct_solve_differs_by_the_published_tolerance_only",
    "tests/test_scores.py::test_burgers_uncontrolled_mean_over_256_members",
]


def pytest_collection_modifyitems(items):
    rank = {nodeid: k for k, nodeid in enumerate(SLOW_FIRST)}
    items.sort(key=lambda item: rank.get(item.nodeid, len(SLOW_FIRST)))
