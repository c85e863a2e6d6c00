"""Recorded trajectories: every env's float64 rollout of a fixed, seeded action sequence
(from a seeded start, its noise included) against the one recorded in
``tests/data/trajectories.json``, so that a refactor cannot change the physics unseen.

On the machine that recorded them the rollouts agree bit for bit; elsewhere floating
point reductions may be vectorised differently, so the test allows round-off. The
machine's name (its vendor's family, threads, torch) does not tell one CPU model from
another, nor does one record say which machine each env was recorded on, so round-off
is allowed everywhere: it is far below any change of the physics. After a deliberate
change of the physics, record them again and say why in the commit:

    .venv/bin/python tests/test_trajectories.py
"""

import json
import sys
from pathlib import Path

import pytest
import torch

import beacon_torch
from beacon_torch.files import machine  # what the bits depend on beyond the code

RECORDED = Path(__file__).parent / "data" / "trajectories.json"
ENVS = beacon_torch.registry.ENVS
MEMBERS = 2
SEED = 11
# ks-v0's rollout grows a machine's round-off more than the other envs': an Intel Xeon
# differed from the recording's machine by 2.1e-9 (3.7e-9 relative) after its 10 actions
ROUND_OFF = {"ks-v0": dict(rtol=1e-7, atol=1e-8)}


def rollout(env_id: str) -> dict[str, list]:
    """Observations and rewards of ``MEMBERS`` members over a few random actions (two of
    a cavity), float64, the env's test settings."""
    spec = ENVS[env_id]
    env = beacon_torch.make(env_id, MEMBERS, dtype=torch.float64, seed=SEED, **spec.card.test_settings)
    g = torch.Generator().manual_seed(SEED)
    obs = [env.reset_members().tolist()]
    rewards = []
    for _ in range(2 if spec.card.costly else 10):
        o, r, _, _ = env.step_members(env.random_action(g))
        obs.append(o.tolist())
        rewards.append(r.tolist())
    return {"observations": obs, "rewards": rewards}


def recorded() -> dict:
    return json.loads(RECORDED.read_text())


@pytest.mark.slow(seconds=5)
@pytest.mark.parametrize("env_id", sorted(ENVS))
def test_trajectories_are_the_recorded_ones(env_id):
    data = recorded()
    expected, got = data["envs"][env_id], rollout(env_id)
    for part in ("observations", "rewards"):
        x = torch.tensor(got[part], dtype=torch.float64)
        y = torch.tensor(expected[part], dtype=torch.float64)
        torch.testing.assert_close(
            x,
            y,
            **ROUND_OFF.get(env_id, dict(rtol=1e-10, atol=1e-12)),
            msg=lambda m, part=part: f"{env_id} {part} changed beyond round-off: {m}",
        )


def test_every_env_is_recorded():
    assert sorted(recorded()["envs"]) == sorted(ENVS)


if __name__ == "__main__":
    torch.set_num_threads(1)  # as each worker of the test suite runs
    RECORDED.parent.mkdir(exist_ok=True)
    data = {
        "note": "written by tests/test_trajectories.py; float64",
        "machine": machine(),
        "envs": {env_id: rollout(env_id) for env_id in sorted(ENVS)},
    }
    RECORDED.write_text(json.dumps(data) + "\n")
    print(f"recorded {len(data['envs'])} envs in {RECORDED}", file=sys.stderr)
