"""The states of the batch since each member's last reset, kept for rendering
(trajectories, space-time diagrams) when an env is made with ``record_history=True``."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from beacon_torch.core.state import State


def _kept(state: State) -> State:
    return type(state)(*(v.detach().clone() for v in state))


class History:
    """What ``render`` draws: member ``index``'s states since its episode started
    (``enabled``), or just its current state.

    The whole batch is kept, so that any member can be drawn (a vector env renders
    each of its copies) and ``index`` may change at any time. Members start their
    episodes at different steps after partial resets: ``start`` holds, per member, the
    position of its episode's first state, and states older than every member's start
    are dropped, so the memory stays within one episode of the batch."""

    def __init__(self, enabled: bool = False, index: int = 0) -> None:
        self.enabled = bool(enabled)
        self.index = index
        self.states: list[State] = []
        self.start: torch.Tensor | None = None

    def __len__(self) -> int:
        """The number of states drawn for member ``index``."""
        if not self.enabled or self.start is None:
            return 0
        return len(self.states) - int(self.start[self.index])

    def reset(self, state: State, mask: torch.Tensor | None) -> None:
        """After a reset of the members in ``mask`` (all when None)."""
        if not self.enabled:
            return
        if mask is None or self.start is None or not self.states:
            self.states = [_kept(state)]
            self.start = torch.zeros(state[0].shape[0], dtype=torch.int64)
            return
        # the members not reset are where the last state left them: that state becomes
        # the reset members' first one instead of a repeated entry for the others
        self.states[-1] = _kept(state)
        self.start[mask.cpu()] = len(self.states) - 1
        drop = int(self.start.min())
        if drop:
            del self.states[:drop]
            self.start -= drop

    def append(self, state: State) -> None:
        if self.enabled:
            self.states.append(_kept(state))

    def frames(self, state: State) -> list[State]:
        """The states of member ``index`` to draw, on the CPU: the recorded ones, else
        the current one."""
        i = self.index
        states = self.states[int(self.start[i]) :] if self.enabled and self.states else [state]
        return [type(s)(*(v[i].detach().cpu() for v in s)) for s in states]
