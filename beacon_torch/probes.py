"""Point probes of 2-D fields and the stacked probe history the cavity envs observe."""

from __future__ import annotations

import torch

N_PROBES = 4
HISTORY = 4  # the 3 previous probe vectors and the current one, oldest first


def probe_indices(n: int, device=None) -> torch.Tensor:
    """``N_PROBES`` evenly spaced ghosted indices along ``n`` cells: n // 8 + (n // 4) k
    (6, 18, 30, 42 for 50 cells; 12, 37, 62, 87 for 100, as published)."""
    return torch.tensor([n // 8 + (n // 4) * k for k in range(N_PROBES)], device=device)


class Probes:
    """Samples fields of a state at a ``N_PROBES x N_PROBES`` grid and keeps the history."""

    def __init__(self, keys: tuple[str, ...], nx: int, ny: int, device=None) -> None:
        self.keys = keys
        self.ix = probe_indices(nx, device)[:, None]
        self.iy = probe_indices(ny, device)[None, :]
        self.size = len(keys) * N_PROBES**2

    def sample(self, state: dict[str, torch.Tensor]) -> torch.Tensor:
        """``[B, len(keys) * N_PROBES^2]``, field by field."""
        return torch.cat([state[k][:, self.ix, self.iy].flatten(1) for k in self.keys], -1)

    def start(self, state: dict[str, torch.Tensor]) -> torch.Tensor:
        """``[B, HISTORY, size]``: zeros for the steps before, the current sample last
        (the published order: oldest first)."""
        current = self.sample(state)[:, None]
        return torch.cat((current.new_zeros((current.shape[0], HISTORY - 1, self.size)), current), 1)

    def push(self, history: torch.Tensor, state: dict[str, torch.Tensor]) -> torch.Tensor:
        """The history with the oldest sample dropped and the current one appended."""
        return torch.cat((history[:, 1:], self.sample(state)[:, None]), 1)
