"""The autograd side of a step: whether it keeps a graph, and activation checkpointing
of a step that recomputes its substeps in the backward pass."""

from __future__ import annotations

import contextlib
from collections.abc import Callable

import torch


def graph_mode(differentiable: bool) -> contextlib.AbstractContextManager:
    """The autograd mode of a step: the caller's in differentiable mode, none else."""
    return contextlib.nullcontext() if differentiable else torch.no_grad()


def checkpointed(step: Callable, *tensors):
    """``step(*tensors)`` under activation checkpointing: the memory of a differentiated
    episode becomes one state per action. The step draws nothing itself (its noise is
    among ``tensors``), so its recomputation in the backward pass is the same step."""
    from torch.utils.checkpoint import checkpoint

    return checkpoint(step, *tensors, use_reentrant=False)
