"""Regenerate the frames and animations shown in the env pages:
`.venv/bin/python docs/make_images.py [NAME ...]` (all of them, or those named, like
`pinball-v0` or `pinball-periodic-v0.gif`)."""

import sys
from pathlib import Path

import torch
from PIL import Image

import beacon_torch
from beacon_torch import episodes
from beacon_torch.render import save_animation

OUT = Path(__file__).parent / "img"

FRAMES = (
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


def boat_tailing(env, start: int):
    """No rotation for ``start`` actions, then the rear cylinders at the bound, their outer
    sides moving downstream (the top one clockwise, the bottom one anticlockwise): the
    boat-tailing of Raibaudo et al. and Cornejo Maceda et al., which bends the outer shear
    layers towards the wake's axis."""
    turned = torch.tensor([[0.0, -1.0, 1.0]], dtype=env.dtype)

    def policy(td):
        action = turned if int(env.step_count[0]) >= start else torch.zeros_like(turned)
        return td.set(env.action_key, action.clone())

    return policy


def pinball_animation(path: Path) -> Path:
    """An episode of the periodic level: the shedding for 30 actions, then boat-tailing."""
    env = beacon_torch.make("pinball-periodic-v0", 1, dtype="float64", record_history=True)
    env.reset()
    frames = [env.render()]

    def grab(step: int) -> None:
        frames.append(env.render())

    episodes.episode(env, boat_tailing(env, start=30), frame_hook=grab)
    return save_animation(frames[::2], path, fps=8)


if __name__ == "__main__":
    OUT.mkdir(exist_ok=True)
    wanted = set(sys.argv[1:])
    for env_id, steps, params in FRAMES:
        name = f"{env_id.split(':')[-1]}"
        if wanted and name not in wanted:
            continue
        env = beacon_torch.make(env_id, 1, dtype="float64", seed=0, record_history=True, **params)
        policy = episodes.random_policy(env, seed=0)
        env.rollout(steps, policy=policy)
        path = OUT / f"{name}.png"
        Image.fromarray(env.render()).save(path)
        print(path)
    if not wanted or "pinball-periodic-v0.gif" in wanted:
        gif = OUT / "pinball-periodic-v0.gif"
        gif.unlink(missing_ok=True)  # regenerated: the animation is this script's own file
        print(pinball_animation(gif))
