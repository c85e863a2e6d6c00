"""Per-env training settings: the paper's PPO table (../shared/SPEC.md, table 2 and the
per-env text) as the defaults, in one place; any field can be overridden."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace


@dataclass(frozen=True)
class PPOConfig:
    frames: int = 200_000  # total transitions
    n_rollout: int = 2000  # transitions collected between two updates
    minibatches: int = 2
    epochs: int = 32
    gamma: float = 0.99
    gae_lambda: float = 0.99
    actor_lr: float = 5e-4
    critic_lr: float = 5e-3
    clip: float = 0.2
    entropy: float = 0.01
    grad_clip: float = 0.1
    hidden: int = 64
    num_envs: int = 8  # members of the batched env collecting together


# (n_rollout, epochs, total transitions, overrides) of the paper's table
PPO = {
    "shkadov-v0": PPOConfig(n_rollout=3200, frames=200_000),
    "rayleigh-v0": PPOConfig(n_rollout=1000, frames=600_000, entropy=0.001),
    "mixing-v0": PPOConfig(n_rollout=2000, frames=100_000),
    "lorenz-v0": PPOConfig(n_rollout=10_000, frames=2_000_000, entropy=0.005),
    "burgers-v0": PPOConfig(n_rollout=4000, frames=500_000),
    "sloshing-v0": PPOConfig(n_rollout=2000, epochs=16, frames=200_000, critic_lr=1e-3),
    "vortex-v0": PPOConfig(n_rollout=4000, frames=1_000_000, critic_lr=1e-3),
}
# the variants train like their base env
VARIANT_OF = {
    "lorenz-continuous-v0": "lorenz-v0",
    "mixing-continuous-v0": "mixing-v0",
    "shkadov-separable-v0": "shkadov-v0",
}


def ppo_config(env_id: str, **overrides) -> PPOConfig:
    """The paper's PPO settings of ``env_id`` with ``overrides`` (field=value)."""
    base = PPO.get(VARIANT_OF.get(env_id, env_id), PPOConfig())
    known = {f.name for f in fields(PPOConfig)}
    unknown = set(overrides) - known
    if unknown:
        raise ValueError(f"unknown PPO setting(s) {sorted(unknown)}; known: {sorted(known)}")
    cfg = replace(base, **overrides)
    for name in ("frames", "n_rollout", "minibatches", "epochs", "num_envs", "hidden"):
        if getattr(cfg, name) < 1:
            raise ValueError(f"PPO setting '{name}' must be a positive integer, got {getattr(cfg, name)}")
    if cfg.n_rollout % cfg.num_envs:
        raise ValueError(f"n_rollout ({cfg.n_rollout}) must be a multiple of num_envs ({cfg.num_envs})")
    return cfg
