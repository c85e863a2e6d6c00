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
    if _plain_first_pass(leaves):
        out_spec = []
        out = _Recomputed.apply(step, spec, out_spec, *leaves)
        release_free_memory()
        return tree_unflatten(list(out), out_spec[0])
    traced = [i for i, x in enumerate(leaves) if isinstance(x, torch.Tensor) and x.requires_grad]
    if traced:
        # the backward pass reaches these inputs right after recomputing the action
        passed = _ReleaseAfterBackward.apply(*(leaves[i] for i in traced))
        for i, x in zip(traced, passed if isinstance(passed, tuple) else (passed,), strict=True):
            leaves[i] = x
    out = checkpoint(step, *tree_unflatten(leaves, spec), use_reentrant=False)
    release_free_memory()
    return out


def _plain_first_pass(leaves: list) -> bool:
    """Whether an action can run its first pass without a graph (:class:`_Recomputed`):
    every tensor that requires grad is one of its inputs' leaves (none hides in an
    object, such as the parameters' dataclass) and no ``torch.func`` transform is active
    (whose tensors a Function of this kind does not map)."""
    import dataclasses

    if torch._C._functorch.peek_interpreter_stack() is not None:
        return False
    for x in leaves:
        if dataclasses.is_dataclass(x) and not isinstance(x, type):
            if any(isinstance(v, torch.Tensor) and v.requires_grad for v in vars(x).values()):
                return False
        elif not isinstance(x, torch.Tensor | int | float | bool | str | None):
            return False
    return True


class _Recomputed(torch.autograd.Function):
    """An action whose forward pass runs without a graph (the compiled one-call step,
    where the env is compiled) and whose backward pass runs it again with one, then
    differentiates that: a checkpoint whose first pass costs a plain forward step. (The
    non-reentrant ``torch.utils.checkpoint`` runs its first pass with the graph, its
    saved tensors dropped: on the recomputed 2-D flows two forward passes with the graph
    per differentiated action.)"""

    @staticmethod
    def forward(ctx, step, spec, out_spec, *leaves):
        from torch.utils._pytree import tree_flatten, tree_unflatten

        ctx.step, ctx.spec = step, spec
        ctx.tensors = [i for i, x in enumerate(leaves) if isinstance(x, torch.Tensor)]
        ctx.others = [None if i in ctx.tensors else x for i, x in enumerate(leaves)]
        ctx.save_for_backward(*(leaves[i] for i in ctx.tensors))
        out, tree = tree_flatten(step(*tree_unflatten(list(leaves), spec)))
        if not all(isinstance(o, torch.Tensor) for o in out):
            raise TypeError("a recomputed action returns tensors only")
        out_spec.append(tree)
        return tuple(out)

    @staticmethod
    def backward(ctx, *grads):
        from torch.utils._pytree import tree_flatten, tree_unflatten

        leaves = list(ctx.others)
        for i, x in zip(ctx.tensors, ctx.saved_tensors, strict=True):
            leaves[i] = x.detach().requires_grad_(x.requires_grad)
        wanted = [i for i in ctx.tensors if leaves[i].requires_grad]
        with torch.enable_grad():
            out, _ = tree_flatten(ctx.step(*tree_unflatten(leaves, ctx.spec)))
        pairs = [(o, g) for o, g in zip(out, grads, strict=True) if g is not None and o.requires_grad]
        found = torch.autograd.grad(
            [o for o, _ in pairs], [leaves[i] for i in wanted], [g for _, g in pairs], allow_unused=True
        )
        release_free_memory()
        given = dict(zip(wanted, found, strict=True))
        return (None, None, None, *(given.get(i) for i in range(len(leaves))))


class _ReleaseAfterBackward(torch.autograd.Function):
    """The identity, whose backward pass releases the free memory."""

    @staticmethod
    def forward(ctx, *tensors):
        return tuple(t.view_as(t) for t in tensors)

    @staticmethod
    def backward(ctx, *grads):
        release_free_memory()
        return grads


# free bytes the C library may keep in its heap before they go back to the system: the
# recomputed actions of mixing-continuous, the pinball and the cylinder settle at 0.25 to
# 0.8 GB of free heap, which each next action reuses; handing it back after every action
# made the next one fault all its pages in again (a fifth of a differentiated transition
# of mixing-continuous-v0 spent in the kernel)
KEEP_FREE = 1 << 30


class _MallInfo2(ctypes.Structure):
    """glibc's ``struct mallinfo2``: ``fordblks`` is the free bytes of its heap."""

    _names = "arena ordblks smblks hblks hblkhd usmblks fsmblks uordblks fordblks keepcost"
    _fields_ = [(name, ctypes.c_size_t) for name in _names.split()]


@functools.cache
def _libc() -> tuple[Callable | None, Callable | None]:
    """glibc's ``malloc_trim`` and ``mallinfo2`` (None where the C library lacks one)."""
    try:
        libc = ctypes.CDLL(None)
    except OSError:
        return None, None
    trim = getattr(libc, "malloc_trim", None)
    info = getattr(libc, "mallinfo2", None)  # glibc 2.33 and later
    if info is not None:
        info.restype = _MallInfo2
    return trim, info


def free_heap_bytes() -> int | None:
    """The bytes the C library holds free in its heap (None where it does not say)."""
    info = _libc()[1]
    return None if info is None else int(info().fordblks)


def release_free_memory(keep: int | None = None) -> None:
    """Give the C library's free blocks back to the system (glibc's ``malloc_trim``; a
    no-op elsewhere) once they exceed ``keep`` bytes (default :data:`KEEP_FREE`; always
    where the library cannot say how many it holds). The blocks of a checkpointed
    action's forward pass are freed when it returns, but glibc may keep them in its
    heap, where the next action does not reuse them all: measured on the code of
    2026-11-25, the resident memory of an eager checkpointed episode of two cylinder-v0
    members grew by 158 MB an action while its live tensors grew by 0.5 MB, and 8
    members over 20 actions took 20 GB."""
    trim = _libc()[0]
    if trim is None:
        return
    free = free_heap_bytes()
    if free is None or free > (KEEP_FREE if keep is None else keep):
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
