"""Regenerate the frames shown in the env pages: `.venv/bin/python docs/make_images.py`."""

from pathlib import Path

from PIL import Image

import beacon_torch
from beacon_torch import episodes

OUT = Path(__file__).parent / "img"

if __name__ == "__main__":
    OUT.mkdir(exist_ok=True)
    cases = (
        ("lorenz-v0", 300, {}),
        ("vortex-v0", 300, {}),
        ("burgers-v0", 100, {}),
        ("sloshing-v0", 60, {}),
        ("shkadov-v0", 100, {"random_start": 0}),
        ("rayleigh-v0", 5, {}),
        ("mixing-v0", 10, {}),
        ("beacon_torch.envs.cylinder:cylinder-v0", 10, {}),
        ("ks-v0", 100, {}),
        ("pinball-v0", 10, {}),
    )
    for env_id, steps, params in cases:
        env = beacon_torch.make(env_id, 1, dtype="float64", seed=0, record_history=True, **params)
        policy = episodes.random_policy(env, seed=0)
        env.rollout(steps, policy=policy)
        path = OUT / f"{env_id.split(':')[-1]}.png"
        Image.fromarray(env.render()).save(path)
        print(path)
