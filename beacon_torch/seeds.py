"""Where every random stream of the library gets its seed: a seed drawn for an env made
without one, the generator a seed gives, and the seeds of the streams derived from an
env's (its random actions, the workers of a collection), so that no two places draw or
derive seeds their own way."""

from __future__ import annotations

import torch

# mixed into an env's seed for its random actions' generator: a stream apart from the physics'
ACTION_STREAM = 0x9E3779B97F4A7C15
# a prime apart between the seeds of a collection's worker envs
WORKER_STRIDE = 7919


def fresh() -> int:
    """A seed for an env made without one, drawn from torch's global generator (so that
    ``torch.manual_seed`` makes such envs reproducible too)."""
    return int(torch.empty((), dtype=torch.int64).random_().item()) % 2**63


def generator(seed: int, device: str | torch.device = "cpu") -> torch.Generator:
    """A generator of its own on ``device``, seeded by ``seed``."""
    return torch.Generator(device=device).manual_seed(seed)


def actions(seed: int) -> int:
    """The seed of an env's random actions (TorchRL's ``rand_action``), from its own."""
    return seed ^ ACTION_STREAM


def worker(seed: int, k: int) -> int:
    """The seed of worker ``k`` of a collection whose env has ``seed``."""
    return seed + WORKER_STRIDE * (k + 1)
