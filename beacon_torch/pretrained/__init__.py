"""Trained policies shipped with the library: the best seed of each (algorithm, env)
pair of the recorded campaign (docs/results.md).

    import beacon_torch.pretrained as pretrained

    pretrained.available()                       # ["ppo/burgers-v0", ...]
    policy = pretrained.load("ppo", "burgers-v0")
    env = beacon_torch.make("burgers-v0", 8)
    rollout = env.rollout(200, policy)           # deterministic actions

A policy is a TorchRL module that reads the env's observation key and writes its
action key, deterministic by default (the mean of a PPO policy, the greedy action of a
DQN one; TorchRL's ``set_exploration_type`` samples a PPO policy instead). It takes the
raw observations of ``beacon_torch.make``: the observation normalisation a training used
is folded into the network's first layer. A file holds tensors, numbers and strings
only, read with ``torch.load(weights_only=True)``.
"""

from __future__ import annotations

from pathlib import Path

import torch
from tensordict.nn import TensorDictModule
from torch import nn

from beacon_torch.registry import env_class
from beacon_torch.training import networks
from beacon_torch.training.env import make_env
from beacon_torch.training.run import load_checkpoint

HERE = Path(__file__).resolve().parent


def path_of(algo: str, env_id: str) -> Path:
    return HERE / f"{algo}-{env_id}.pt"


def available() -> list[str]:
    """The shipped policies, as ``"algo/env_id"``."""
    return sorted(f"{p.stem.split('-', 1)[0]}/{p.stem.split('-', 1)[1]}" for p in HERE.glob("*.pt"))


def _first_layer(module: nn.Module, n_obs: int) -> nn.Linear:
    return next(layer for layer in module.modules() if isinstance(layer, nn.Linear) and layer.in_features == n_obs)


def export(run: str | Path, path: str | Path, **record) -> Path:
    """Write the policy of a run folder's checkpoint as a shipped file: its network
    with the observation normalisation folded into the first layer, and ``record``
    (numbers and strings: score, seed, ...) next to it."""
    state = load_checkpoint(run)
    env = make_env(state["env"], 1, norm_steps=0)
    policy = networks.policy(env, state["policy"]["network"], state["policy"]["hidden"])
    policy.load_state_dict(state["modules"]["actor"])
    loc, scale = state["obs_norm"]["loc"].reshape(-1), state["obs_norm"]["scale"].reshape(-1)
    first = _first_layer(policy, loc.numel())
    with torch.no_grad():
        # W ((x - loc) / scale) + b = (W / scale) x + (b - (W / scale) loc)
        first.weight.div_(scale.to(first.weight.dtype))
        first.bias.sub_(first.weight @ loc.to(first.weight.dtype))
    out = {
        "env": state["env"],
        "algo": state["algo"],
        "network": state["policy"]["network"],
        "hidden": state["policy"]["hidden"],
        "frames": state["frames"],
        "weights": policy.state_dict(),
        **record,
    }
    torch.save(out, path)
    return Path(path)


def info(algo: str, env_id: str) -> dict:
    """What a shipped file records besides the weights (transitions, seed, score...)."""
    return {k: v for k, v in _read(algo, env_id).items() if k != "weights"}


def _read(algo: str, env_id: str) -> dict:
    env_class(env_id)  # an unknown id: the registry's error
    path = path_of(algo, env_id)
    if not path.is_file():
        raise ValueError(f"no pretrained {algo} policy for {env_id}; available: {', '.join(available()) or 'none'}")
    return torch.load(path, weights_only=True, map_location="cpu")


def load(algo: str, env_id: str, *, device="cpu") -> TensorDictModule:
    """The shipped ``algo`` policy of ``env_id`` (see the module's docstring)."""
    shipped = _read(algo, env_id)
    env = make_env(env_id, 1, norm_steps=0)
    policy = networks.policy(env, shipped["network"], shipped["hidden"])
    policy.load_state_dict(shipped["weights"])
    return policy.to(device).eval()
