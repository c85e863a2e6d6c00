"""Per-step agreement with the published code: its recorded rollouts (seeded open-loop
actions, float64, its own start states) replayed through our envs."""

import pytest

from beacon_torch import reference

# the cavities' whole episodes take minutes: a prefix here, the whole episodes in
# validation/reference_rollouts.py (recorded in validation/results/reference_rollouts.md)
PREFIX = 30


def test_every_deterministic_env_has_a_recorded_rollout():
    assert reference.env_ids() == ["lorenz-v0", "mixing-v0", "rayleigh-v0", "sloshing-v0", "vortex-v0"]
    with pytest.raises(ValueError, match="no published rollout of 'burgers-v0'"):
        reference.record("burgers-v0")


def test_lorenz_replays_the_published_rollout_exactly():
    agreement = reference.replay("lorenz-v0")
    assert agreement.steps == 500
    assert (agreement.rewards == agreement.published).all()
    assert agreement.first_observation_error == 0.0
    # 25 time units of a chaotic system: round-off grows to about 1e-4 by the end
    assert agreement.last_observation_error < 1e-3


@pytest.mark.parametrize("env_id", ["vortex-v0", "sloshing-v0"])
def test_whole_episodes_agree_with_the_published_code_to_round_off(env_id):
    agreement = reference.replay(env_id)
    assert agreement.steps == len(reference.record(env_id)["actions"])
    assert agreement.first_observation_error == 0.0
    assert agreement.running_error.max() < 1e-9, agreement.summary()
    assert agreement.last_observation_error < 1e-12, agreement.summary()


@pytest.mark.slow(seconds=60)
def test_rayleigh_with_the_published_jacobi_solve_agrees_to_round_off():
    agreement = reference.replay("rayleigh-v0", PREFIX, solver="jacobi")
    assert agreement.first_observation_error == 0.0
    assert agreement.running_error.max() < 1e-9, agreement.summary()


@pytest.mark.slow(seconds=30)
def test_rayleigh_with_the_direct_solve_differs_by_the_published_tolerance_only():
    # docs/envs/rayleigh.md: the published Jacobi solve stops at 1e-8 on the squared
    # update, which leaves about 1e-4 of the increment; the direct solve is exact
    agreement = reference.replay("rayleigh-v0", PREFIX)
    assert agreement.first_observation_error == 0.0
    assert agreement.running_error.max() < 2e-4, agreement.summary()


@pytest.mark.slow(seconds=60)
def test_mixing_agrees_within_the_published_solver_tolerance():
    # docs/envs/mixing.md: the published Jacobi solve stops at 1e-4 on the squared update
    agreement = reference.replay("mixing-v0", PREFIX)
    assert agreement.first_observation_error == 0.0
    assert agreement.running_error.max() < 2e-3, agreement.summary()


@pytest.mark.slow(seconds=20)
def test_mixing_with_the_published_jacobi_solve_agrees_to_round_off():
    # the ghost ring the reward averages over is the one set before the last transport,
    # its corners zero, as in the published step
    agreement = reference.replay("mixing-v0", 5, solver="jacobi")
    assert agreement.running_error.max() < 1e-12, agreement.summary()
