"""Regenerate the frames and animations shown in the env pages:
`.venv/bin/python docs/make_images.py [NAME ...]` (all of them, or those named, like
`pinball-v0` or `pinball-periodic-v0.gif`)."""

import sys
from pathlib import Path

import torch
from PIL import Image

import beacon_torch
from beacon_torch import episodes
from beacon_torch.files import create_file
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


def renew(path: Path) -> Path:
    """``path`` cleared for this script's new version of it: its own earlier file is
    removed (a link planted there is removed, not followed)."""
    path.unlink(missing_ok=True)
    return path


def main(wanted: set[str], out: Path = OUT) -> None:
    out.mkdir(exist_ok=True)
    for env_id, steps, params in FRAMES:
        name = f"{env_id.split(':')[-1]}"
        if wanted and name not in wanted:
            continue
        env = beacon_torch.make(env_id, 1, dtype="float64", seed=0, record_history=True, **params)
        policy = episodes.random_policy(env, seed=0)
        env.rollout(steps, policy=policy)
        frame = Image.fromarray(env.render())
        # a new file, refused if the name was taken meanwhile
        print(create_file(renew(out / f"{name}.png"), lambda tmp, frame=frame: frame.save(tmp, format="PNG")))
    if not wanted or "pinball-periodic-v0.gif" in wanted:
        print(pinball_animation(renew(out / "pinball-periodic-v0.gif")))


if __name__ == "__main__":
    main(set(sys.argv[1:]))
