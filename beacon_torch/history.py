"""The states of one batch member since its last reset, kept for rendering
(trajectories, space-time diagrams) when an env is made with ``record_history=True``."""

from __future__ import annotations

import torch

State = dict[str, torch.Tensor]


class History:
    """What ``render`` draws: member ``index``'s states since its episode started
    (``enabled``), or just its current state."""

    def __init__(self, enabled: bool = False, index: int = 0) -> None:
        self.enabled = bool(enabled)
        self.index = index
        self.states: list[State] = []

    def __len__(self) -> int:
        return len(self.states)

    def member(self, state: State) -> State:
        return {k: v[self.index].detach().clone() for k, v in state.items()}

    def reset(self, state: State, mask: torch.Tensor | None) -> None:
        """After a reset: start again if the rendered member was among those reset."""
        if self.enabled and (mask is None or bool(mask[self.index])):
            self.states = [self.member(state)]

    def append(self, state: State) -> None:
        if self.enabled:
            self.states.append(self.member(state))

    def frames(self, state: State) -> list[State]:
        """The states to draw, on the CPU: the recorded ones, else the current one."""
        states = self.states if self.enabled and self.states else [self.member(state)]
        return [{k: v.cpu() for k, v in s.items()} for s in states]
