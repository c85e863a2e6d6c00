"""The autograd side of a step: whether it keeps a graph, and activation checkpointing
of a step that recomputes its substeps in the backward pass."""

from __future__ import annotations

import contextlib
import ctypes
import functools
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

    return_freed_blocks()
    return checkpoint(step, *tensors, use_reentrant=False)


@functools.cache
def return_freed_blocks() -> bool:
    """Fix glibc's threshold above which a block is its own mapping, returned to the
    system when freed, at its default of 128 KiB (once per process; False where the C
    library has no ``mallopt``). glibc raises the threshold each time such a block is
    freed; the blocks of a checkpointed action's forward pass then come from the heap,
    and the heap keeps them: measured, the resident memory of a checkpointed episode of
    two cylinder-v0 members grew by 158 MB an action (the live tensors by 0.5 MB), 13 MB
    with the threshold fixed, so that 8 members over 20 actions took 20 GB."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    m_mmap_threshold = -3
    return bool(mallopt(m_mmap_threshold, 128 * 1024))
