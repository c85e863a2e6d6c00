"""Trained policies shipped with the library: the best seed of each (algorithm, env)
pair of the recorded campaign (docs/results.md).

    import beacon_torch.pretrained as pretrained

    pretrained.available()                       # ["ppo/burgers-v0", ...]
    policy = pretrained.load("ppo/burgers-v0")
    env = beacon_torch.make("burgers-v0", 8)
    rollout = env.rollout(200, policy)           # deterministic actions

A pair is named ``ALGO/ENV`` here as everywhere (runs go to ``runs/ALGO/ENV``); its
file is ``ALGO/ENV.pt`` in this folder. A policy is a TorchRL module that reads the env's observation key and writes its
action key, deterministic by default (the mean of a PPO policy, the greedy action of a
DQN one; TorchRL's ``set_exploration_type`` samples a PPO policy instead); a continuous
action, mean or sample, comes clipped to the env's action box. It takes the
raw observations of ``beacon_torch.make``: the observation normalisation a training used
is folded into the network's first layer. A file holds tensors, numbers and strings
only, read with ``torch.load(weights_only=True)`` and checked (known env and network,
finite weights); ``load`` reads only the shipped files, ``load_file`` a file you name.
Its weights come frozen (``requires_grad`` off, as for evaluation); call
``policy.requires_grad_(True)`` to fine-tune it.
"""

from __future__ import annotations

from pathlib import Path

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn

from beacon_torch import received
from beacon_torch.files import save_tensors
from beacon_torch.registry import ENVS, env_spec
from beacon_torch.training import networks
from beacon_torch.training.env import make_env
from beacon_torch.training.run import CHECKPOINT, MAX_HIDDEN, load_checkpoint

HERE = Path(__file__).resolve().parent


def path_of(name: str) -> Path:
    """Where the policy ``ALGO/ENV`` is shipped."""
    algo, env_id = split_name(name)
    return HERE / algo / f"{env_id}.pt"


def split_name(name: str) -> tuple[str, str]:
    """``"ppo/burgers-v0"`` as ``("ppo", "burgers-v0")``, the env id checked."""
    algo, sep, env_id = name.partition("/") if isinstance(name, str) else ("", "", "")
    if not sep or not algo or "/" in env_id:
        raise ValueError(f"a trained pair is named ALGO/ENV, like 'ppo/burgers-v0'; got {name!r}")
    env_spec(env_id)  # an unknown id: the registry's error
    return algo, env_id


def available() -> list[str]:
    """The shipped policies, as ``"ALGO/ENV"``."""
    return sorted(f"{p.parent.name}/{p.stem}" for p in HERE.glob("*/*.pt"))


def _first_layer(module: nn.Module, n_obs: int) -> nn.Linear:
    return next(layer for layer in module.modules() if isinstance(layer, nn.Linear) and layer.in_features == n_obs)


def export(run: str | Path, path: str | Path, **record) -> Path:
    """Write the policy of a run folder's checkpoint as a shipped file: its network
    with the observation normalisation folded into the first layer, and ``record``
    (numbers and strings: score, seed, ...) next to it."""
    state = load_checkpoint(run)
    params = state["config"].get("params", {})
    env = make_env(state["env"], 1, norm_steps=0, params=params)
    policy = networks.policy(env, state["policy"]["network"], state["policy"]["hidden"])
    network = f"a {state['policy']['network']} of width {state['policy']['hidden']} on {state['env']}"
    received.load_into(policy, state["modules"]["actor"], f"{Path(run) / CHECKPOINT}: the actor's weights", network)
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
        "params": params,
        "frames": state["frames"],
        "weights": policy.state_dict(),
        **record,
    }
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    return save_tensors(out, path)


def info(name: str) -> dict:
    """What the shipped file of ``ALGO/ENV`` records besides the weights (transitions,
    seed, score...)."""
    return {k: v for k, v in _read(shipped(name))[0].items() if k != "weights"}


def shipped(name: str) -> Path:
    """The file of a shipped policy: ``name`` must be one of :func:`available` (so that
    no name reaches outside the package's folder)."""
    algo, env_id = split_name(name)
    if name not in available():
        raise ValueError(f"no pretrained {algo} policy for {env_id}; available: {', '.join(available()) or 'none'}")
    path = path_of(name)
    if path.is_symlink():
        raise ValueError(f"{path}: a symbolic link is refused as a shipped policy")
    return path


class _Box(nn.Module):
    """Clips actions to the box ``[low, high]``."""

    def __init__(self, low: torch.Tensor, high: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("low", low.clone())
        self.register_buffer("high", high.clone())

    def forward(self, action: torch.Tensor) -> torch.Tensor:
        return torch.maximum(torch.minimum(action, self.high), self.low)


def _read(path: Path, env_id: str | None = None) -> tuple[dict, TensorDictModule, int]:
    """A policy file, checked, and its policy: tensors and plain values only (nothing
    in it runs), read within bounds (``beacon_torch.received``), a known env and
    network whose weights have the shapes of that network, finite once cast to its
    dtype; ``env_id``: the env it must have been trained on. Returns the file's
    record, the policy and its number of observations."""
    built = {}

    def check(record) -> None:
        if not isinstance(record, dict) or not all(k in record for k in ("env", "network", "hidden", "weights")):
            raise ValueError(f"{path}: not a policy file (it needs 'env', 'network', 'hidden' and 'weights')")
        if (
            not all(isinstance(record[k], str) for k in ("env", "network"))
            or record["env"] not in ENVS
            or record["network"] not in networks.NETWORKS
        ):
            raise ValueError(f"{path}: unknown env {record['env']!r} or network {record['network']!r}")
        if (
            not isinstance(record["hidden"], int)
            or isinstance(record["hidden"], bool)
            or not 1 <= record["hidden"] <= MAX_HIDDEN
        ):
            raise ValueError(
                f"{path}: the network's width must be an integer in [1, {MAX_HIDDEN}], got {record['hidden']!r}"
            )
        weights = record["weights"]
        if not isinstance(weights, dict) or not all(isinstance(v, torch.Tensor) for v in weights.values()):
            raise ValueError(f"{path}: 'weights' must be a dict of tensors")
        if env_id is not None and record["env"] != env_id:
            raise ValueError(f"{path}: a policy of {record['env']}, not of {env_id}")
        params = record.get("params", {})
        try:
            ENVS[record["env"]].check(params)
        except (TypeError, ValueError) as err:
            raise ValueError(f"{path}: its env parameters: {err}") from None
        env = make_env(record["env"], 1, norm_steps=0, **params)
        policy = networks.policy(env, record["network"], record["hidden"])
        # the weights are compared with the network's before any is copied, and checked
        # in the network's dtype (1e300 in float64 is infinite in float32)
        received.load_into(
            policy, weights, f"{path}: the weights", f"a {record['network']} of width {record['hidden']}"
        )
        if not env.base_env.discrete:
            # a shipped policy acts inside the box whatever its actor: Stable-Baselines3's
            # has an unbounded mean (training clips the action in the env), and a user
            # may step the physics without the env's clip
            low, high = networks.action_bounds(env)
            key = networks.Keys.of(env).action
            policy = TensorDictSequential(policy, TensorDictModule(_Box(low, high), in_keys=[key], out_keys=[key]))
        built["policy"], built["n_obs"] = policy, networks.n_observations(env)

    return received.torch_file(path, "policy file", check), built["policy"], built["n_obs"]


def load(name: str, env_id: str | None = None, *, device="cpu") -> TensorDictModule:
    """The shipped policy ``ALGO/ENV``, e.g. ``"ppo/burgers-v0"``, also spelt
    ``load("ppo", "burgers-v0")`` (see the module's docstring)."""
    if env_id is not None:
        if not isinstance(name, str) or "/" in name:
            raise ValueError(f"load(ALGO, ENV) takes the algorithm alone first, like 'ppo'; got {name!r}")
        name = f"{name}/{env_id}"
    return load_file(shipped(name), split_name(name)[1], device=device)


def load_file(path: str | Path, env_id: str | None = None, *, device="cpu") -> TensorDictModule:
    """The policy of a file written by :func:`export` (one you trained, or received):
    read as data, checked, and refused if it was trained on another env than
    ``env_id`` (when given)."""
    path = Path(path)
    record, policy, n_obs = _read(path, env_id)
    env_id = record["env"]
    first = _first_layer(policy, n_obs)

    def check(module, args):
        # a policy given another env's observations: say so, not a matrix error
        if args and isinstance(args[0], torch.Tensor):
            if args[0].shape[-1] != n_obs:
                raise ValueError(
                    f"this policy was trained on {env_id} ({n_obs} observations); it was given {args[0].shape[-1]}"
                )
            if args[0].dtype != module.weight.dtype:
                raise TypeError(
                    f"this policy computes in {module.weight.dtype} and was given {args[0].dtype} observations: "
                    f"make the env with dtype={str(module.weight.dtype).removeprefix('torch.')!r}, or convert "
                    f"the policy (policy.to(torch.float64))"
                )

    first.register_forward_pre_hook(check)
    # frozen: its actions carry no graph into an env that is not differentiable (which
    # would warn that their gradient is dropped); requires_grad_(True) to fine-tune
    return policy.to(device).eval().requires_grad_(False)
