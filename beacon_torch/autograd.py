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


def checkpointed(step: Callable, *inputs):
    """``step(*inputs)`` under activation checkpointing: the memory of a differentiated
    episode becomes one state per action. The step draws nothing itself (its noise is
    among ``inputs``), so its recomputation in the backward pass is the same step. The
    memory an action's forward pass and its recomputation free is handed back to the
    system after each (:func:`release_free_memory`)."""
    from torch.utils._pytree import tree_flatten, tree_unflatten
    from torch.utils.checkpoint import checkpoint

    leaves, spec = tree_flatten(inputs)
    traced = [i for i, x in enumerate(leaves) if isinstance(x, torch.Tensor) and x.requires_grad]
    if traced:
        # the backward pass reaches these inputs right after recomputing the action
        passed = _ReleaseAfterBackward.apply(*(leaves[i] for i in traced))
        for i, x in zip(traced, passed if isinstance(passed, tuple) else (passed,), strict=True):
            leaves[i] = x
    out = checkpoint(step, *tree_unflatten(leaves, spec), use_reentrant=False)
    release_free_memory()
    return out


class _ReleaseAfterBackward(torch.autograd.Function):
    """The identity, whose backward pass releases the free memory."""

    @staticmethod
    def forward(ctx, *tensors):
        return tuple(t.view_as(t) for t in tensors)

    @staticmethod
    def backward(ctx, *grads):
        release_free_memory()
        return grads


@functools.cache
def _malloc_trim():
    try:
        return ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):  # a C library without it
        return None


def release_free_memory() -> None:
    """Give the C library's free blocks back to the system (glibc's ``malloc_trim``; a
    no-op elsewhere). The blocks of a checkpointed action's forward pass are freed when
    it returns, but glibc keeps them in its heap, where the next action does not reuse
    them all: measured, the resident memory of a checkpointed episode of two cylinder-v0
    members grew by 158 MB an action while its live tensors grew by 0.5 MB, and 8
    members over 20 actions took 20 GB."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


@contextlib.contextmanager
def saved_storages():
    """Within the block, the bytes autograd saves for the backward pass: yields a dict
    of the storages it saved (each counted once) to their sizes."""
    storages: dict[int, int] = {}

    def pack(t: torch.Tensor) -> torch.Tensor:
        storage = t.untyped_storage()
        storages[storage.data_ptr()] = storage.nbytes()
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        yield storages


# names that moved to another layer: (module, name) of each, said by the error
MOVED = {"horizon_bytes": "beacon_torch.training.env"}


def __getattr__(name: str):
    if name in MOVED:
        raise AttributeError(
            f"beacon_torch.autograd.{name} has moved: import it from {MOVED[name]} "
            f"(it builds envs, which the core does not)"
        )
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
