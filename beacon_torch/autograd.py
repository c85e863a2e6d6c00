"""The autograd side of a step: whether it keeps a graph, and activation checkpointing
of a step that recomputes its substeps in the backward pass."""

from __future__ import annotations

import contextlib
from collections.abc import Callable

import torch


def graph_mode(differentiable: bool) -> contextlib.AbstractContextManager:
    """The autograd mode of a step: the caller's in differentiable mode, none else."""
    return contextlib.nullcontext() if differentiable else torch.no_grad()


def checkpointed(step: Callable, rng: torch.Generator, *tensors):
    """``step(*tensors)`` under activation checkpointing: the memory of a differentiated
    episode becomes one state per action. The recomputation in the backward pass must
    draw the same noise as the step did, from the env's generator ``rng``, and leave
    the generator where the episode has since taken it."""
    from torch.utils.checkpoint import checkpoint

    drawn_from = rng.get_state()
    calls = []

    def run(*tensors):
        if not calls:
            calls.append(1)
            return step(*tensors)
        now = rng.get_state()
        rng.set_state(drawn_from)
        try:
            return step(*tensors)
        finally:
            rng.set_state(now)

    return checkpoint(run, *tensors, use_reentrant=False)
