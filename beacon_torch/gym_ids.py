"""gymnasium's ids of the envs, ``beacon/<id>``, registered without importing torch.

gymnasium finds an env by id once the package that registers it is imported
(``gymnasium.make("beacon_torch:beacon/lorenz-v0")`` imports ``beacon_torch`` first),
and an id's entry points are names resolved only when an env is made. So importing
``beacon_torch`` registers the package's own ids from the table below, and
``beacon_torch.register`` each id added later; the adapter itself
(``beacon_torch.gym``) is imported by gymnasium when an env is made.
"""

from __future__ import annotations

import gymnasium

NAMESPACE = "beacon"

# the package's envs and their episode lengths (gymnasium's max_episode_steps), as
# their classes declare them (a test compares)
BUILT_IN = {
    "lorenz-v0": 500,
    "lorenz-continuous-v0": 500,
    "vortex-v0": 800,
    "burgers-v0": 200,
    "sloshing-v0": 200,
    "shkadov-v0": 400,
    "shkadov-separable-v0": 400,
    "rayleigh-v0": 100,
    "rayleigh-separable-v0": 200,
    "mixing-v0": 100,
    "mixing-continuous-v0": 100,
    "cylinder-v0": 80,
    "ks-v0": 3000,
    "pinball-v0": 100,
    "pinball-periodic-v0": 100,
    "pinball-chaotic-v0": 100,
    "rbc2d-easy-v0": 200,
    "rbc2d-easy-ma-v0": 200,
    "rbc2d-medium-v0": 200,
    "rbc2d-medium-ma-v0": 200,
    "rbc2d-hard-v0": 200,
    "rbc2d-hard-ma-v0": 200,
}


def gym_id(env_id: str) -> str:
    return f"{NAMESPACE}/{env_id}"


def register(env_id: str, episode_length: int) -> None:
    """Register ``beacon/<env_id>`` with gymnasium (nothing if it is registered)."""
    name = gym_id(env_id)
    if name in gymnasium.registry:
        return
    gymnasium.register(
        id=name,
        entry_point="beacon_torch.gym:BeaconGymEnv",
        vector_entry_point="beacon_torch.gym:BeaconVectorEnv",
        kwargs={"registered_id": env_id},
        max_episode_steps=episode_length,
    )


for _env_id, _length in BUILT_IN.items():
    register(_env_id, _length)
