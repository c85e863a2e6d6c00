"""The compiled path of an env's physics: which functions run through ``torch.compile``
and the cache of their compiled versions, and what its inputs must be.

An env hands its substep loops to :meth:`Kernels.loop` (and any other function of
tensors to :meth:`Kernels.__call__`) once, at set-up, and calls what it gets back;
whether that runs eagerly or compiled is decided later by :meth:`Kernels.compile`, so
that ``make(..., compile=True)`` needs nothing of the env's code. Compiled, the base
runs a whole step as one graph: the loops in it become ``while_loop``s, so that an
action of tens or hundreds of substeps is one compiled call whose code does not grow
with the number of substeps, and whose per-call cost (guards, wrapper) is paid once.

The invariants of the compiled inputs live here, with why:

- the recompile budget (:data:`RECOMPILE_LIMIT`): every env runs the one step function,
  so every env, batch size and dtype is an entry of that one function's compiled code;
- standard strides (:func:`standard`) and no aliasing (:func:`step_inputs`): compiled
  code is specialised on its inputs' strides and on which of them share memory, so a
  state that came out permuted (a cavity's batch-last solver) or as a view would
  compile the step again; a step's outputs are made standard inside the step, a state
  given from outside by :func:`step_inputs`;
- a loop's carried values are standard and distinct too (:func:`_unaliased`):
  ``while_loop`` refuses a body that returns its own input.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

import torch

from beacon_torch.numerics import native

# each env, shape and dtype is one entry of the step's compiled code (every env runs
# the one step function, and so shares its code object); past torch's default limit
# (8 entries) the step would silently run eagerly
RECOMPILE_LIMIT = 64


class _Settings:
    """Two of torch's process-wide settings, changed while a compiled kernel runs (and
    compiles) and only then, since an env must not change them for its user:

    - dynamo's recompile limit, raised;
    - ``while_loop`` graphs allowed into torch's on-disk graph caches. Torch bypasses
      those caches for any higher-order operator not vetted for them, so each new
      process would lower and generate a whole step's code again (seconds) though the
      generated code itself is cached. The cache key is the pickled graph, the loop's
      condition and body graphs included, so loops that differ only in their bodies
      get different entries (checked in the tests, as is a warm-cache step against the
      eager one)."""

    depth = 0
    prior: tuple[int, bool] = (0, False)

    def __enter__(self) -> None:
        if self.depth == 0:
            config, loop = _torch_settings()
            self.prior = config.recompile_limit, loop._cacheable
            config.recompile_limit = max(self.prior[0], RECOMPILE_LIMIT)
            loop._cacheable = True
        self.depth += 1

    def __exit__(self, *exc: Any) -> None:
        self.depth -= 1
        if self.depth == 0:
            config, loop = _torch_settings()
            config.recompile_limit, loop._cacheable = self.prior


def _torch_settings():
    # imported on first use: dynamo is not needed by an eager env
    import torch._dynamo
    from torch._higher_order_ops.while_loop import while_loop_op

    return torch._dynamo.config, while_loop_op


_SETTINGS = _Settings()


def member_vectors(members: int, dtype: torch.dtype, device) -> dict:
    """Inductor options for fields whose contiguous axis is the members (the 2-D flows'
    batch-last layout): the widest vectors of this CPU that a row of members fills
    whole. Inductor's default is the widest the CPU has; 8 float32 members on an
    AVX-512 machine then fill half of each vector, and every load and store of every
    kernel is a partial one through a buffer (measured: a compiled transition of the
    cavities and the cylinder 1.3 to 1.6 times slower, a differentiated one up to 2.4
    times). Empty where the default fills its vectors or nothing narrower fits."""
    if torch.device(device).type != "cpu":
        return {}
    from torch._inductor import cpu_vec_isa

    widths = sorted({isa.bit_width() for isa in cpu_vec_isa.valid_vec_isa_list()}, reverse=True)
    row = members * torch.finfo(dtype).bits
    if not widths or row % widths[0] == 0:
        return {}
    fitting = [w for w in widths if row % w == 0]
    return {"cpp.simdlen": fitting[0]} if fitting else {}


class Kernels:
    """The compiled kernels of one env. ``inductor_options`` are the env class's
    defaults for inductor."""

    def __init__(self, inductor_options: dict | None = None, chunk: int = 8) -> None:
        self.inductor_options = dict(inductor_options or {})
        # substeps per compiled call where autograd records (see :meth:`loop`)
        self.chunk = int(chunk)
        # the ``torch.compile`` options, None while the kernels run eagerly
        self.options: dict | None = None
        self._cache: dict[Callable, Callable] = {}

    def compile(self, **kwargs: Any) -> None:
        """Compile every kernel from now on (on its first call for each shape and
        dtype): one fused graph with static shapes (``fullgraph``, ``dynamic=False``)
        unless ``kwargs`` (``torch.compile`` options) say otherwise."""
        given = kwargs.pop("options", {})
        self.options = {"fullgraph": True, "dynamic": False, **kwargs}
        # torch.compile takes a mode or inductor options, not both: a mode asked for
        # replaces the env's default options (options given with it are torch's to refuse)
        options = given if "mode" in kwargs else {**self.inductor_options, **given}
        if options:
            self.options["options"] = options
        self._cache = {}

    @property
    def compiled(self) -> bool:
        """Whether the kernels run compiled (after :meth:`compile`)."""
        return self.options is not None

    def __call__(self, fn: Callable) -> Callable:
        """``fn`` (a function of tensors: a whole step, a substep) as the env runs it:
        itself in eager mode, compiled after :meth:`compile`. Inside a larger compiled
        function it runs inline, as part of that graph. Later envs of the same shapes
        reuse the compiled code (tensors are arguments, not constants)."""
        return _Kernel(self, fn)

    def loop(self, fn: Callable) -> Callable:
        """``fn(i, carried, *inputs) -> carried`` (a substep, ``i`` its index in the
        action: an int, or a 0-dim int64 tensor inside a graph) applied for
        ``i = 0, ..., n - 1``; the returned function takes ``(n, carried, *inputs)``.
        Eagerly it is a Python loop over ``fn``. Compiled and without a graph to keep,
        or inside a compiled step, it is one ``while_loop``: the whole loop in one
        compiled call whose code does not grow with ``n`` (a carried value ``fn``
        hands on unchanged is copied there: the loop may not alias). Compiled where
        autograd records (a ``while_loop`` cannot be differentiated), it is a Python
        loop over chunks of :attr:`chunk` substeps, each chunk one compiled call that
        torch.compile differentiates as one graph, and the remainder substep by
        substep: each compiled call with a graph pays a fixed cost in its wrappers
        (the guards, AOTAutograd's runtime, the autograd engine's node) that is most
        of a small substep's differentiated time, while a chunk's code, and its
        compilation, grows with its length. What ``fn`` reads per substep it takes
        with :func:`at` (an eager int and a traced tensor pick the same values)."""
        return _Loop(self, fn)

    def __getstate__(self) -> dict:
        # compiled code is this process's: a copy of the env (pickled for another
        # process) compiles its own on its first call
        return {**self.__dict__, "_cache": {}}


class _Loop:
    """A substep loop as :meth:`Kernels.loop` returns it."""

    def __init__(self, kernels: Kernels, fn: Callable) -> None:
        self.kernels, self.fn = kernels, fn
        self._step = _Kernel(kernels, fn)
        self._whole = _Kernel(kernels, self._graph)
        self._chunks: dict[int, _Kernel] = {}

    def __call__(self, n: int, carried, *inputs):
        records, inside = _records(carried, inputs), torch.compiler.is_compiling()
        if self.kernels.options is None or (records and inside):
            for i in range(n):
                carried = self._step(i, carried, *inputs)
            return carried
        if records:
            return self._chunked(n, carried, *inputs)
        if inside:
            return self._graph(n, carried, *inputs)
        return self._whole(n, carried, *inputs)

    def _chunked(self, n: int, carried, *inputs):
        # compiled calls take the substep index as a tensor, as inside a loop's graph:
        # an int would be a constant of the compiled code, and each index an entry of
        # its own, past the recompile limit for long actions
        device = _device(carried)
        length = max(1, min(self.kernels.chunk, n))
        chunk = self._chunks.get(length)
        if chunk is None:
            chunk = self._chunks[length] = _Kernel(self.kernels, _Chunk(self.fn, length))
        done = 0
        while done + length <= n:
            carried = chunk(torch.tensor(done, device=device), carried, *inputs)
            done += length
        for i in range(done, n):
            carried = self._step(torch.tensor(i, device=device), carried, *inputs)
        return carried

    def _graph(self, n: int, carried, *inputs):
        from torch._higher_order_ops import while_loop

        fn = self.fn

        def body(i, carried):
            given = torch.utils._pytree.tree_leaves(carried)
            # a carried value handed on unchanged is copied: the loop's body may not
            # return its own input
            out = torch.utils._pytree.tree_map(
                lambda t: t.clone() if any(t is g for g in given) else t, fn(i, carried, *inputs)
            )
            return i + 1, out

        start = torch.zeros((), dtype=torch.int64, device=_device(carried))
        return while_loop(lambda i, carried: i < n, body, (start, _unaliased(carried)))[1]


class _Chunk:
    """``length`` substeps of ``fn`` from the substep ``start`` (a 0-dim tensor): one
    compiled call of a differentiated loop (an object, not a closure, so that an env
    can be pickled)."""

    def __init__(self, fn: Callable, length: int) -> None:
        self.fn, self.length = fn, length

    def __call__(self, start: torch.Tensor, carried, *inputs):
        for j in range(self.length):
            carried = self.fn(start + j, carried, *inputs)
        return carried


def at(t: torch.Tensor, i) -> torch.Tensor:
    """``t[i]`` for a loop's substep index ``i``: an int eagerly, a 0-dim tensor inside
    a compiled loop (where indexing by it would read its value on the host)."""
    return t[i] if isinstance(i, int) else t.index_select(0, i.reshape(1)).squeeze(0)


def _unaliased(tree):
    """``tree`` as a loop may carry it: a tensor that appears in it more than once
    copied (a start may share one zero tensor between two fields; carried values may
    not alias), and each in standard strides (those of the body's results, which a
    loop requires of its inputs too)."""
    seen = []

    def once(t):
        if any(t is s for s in seen):
            return standard(t.clone())
        seen.append(t)
        return standard(t)

    return torch.utils._pytree.tree_map(once, tree)


def standard(t: torch.Tensor) -> torch.Tensor:
    """``t`` in standard (row-major) strides, copied only where they differ: a member
    of size one or a permuted view can be contiguous in torch's sense with other
    strides, on which compiled code is specialised."""
    return t if t.stride() == _strides(t.shape) else t.clone(memory_format=torch.contiguous_format)


def _strides(shape) -> tuple[int, ...]:
    out, step = [], 1
    for size in reversed(shape):
        out.append(step)
        step *= size
    return tuple(reversed(out))


def _records(carried, inputs) -> bool:
    """Whether autograd records the loop (a graph to keep: no ``while_loop`` then)."""
    if not torch.is_grad_enabled():
        return False
    leaves = torch.utils._pytree.tree_leaves((carried, inputs))
    return any(isinstance(t, torch.Tensor) and t.requires_grad for t in leaves)


def _device(tree) -> torch.device:
    return next(t for t in torch.utils._pytree.tree_leaves(tree) if isinstance(t, torch.Tensor)).device


_announced = False


def announce_compilation() -> None:
    """Say once per process, on a terminal, that the first steps compile: a first reset
    or step then takes seconds to a minute (shkadov's reset runs uncontrolled actions,
    so its first one compiles them), which would otherwise look like a hang."""
    global _announced
    if _announced or not sys.stderr.isatty():
        return
    _announced = True
    print(
        "beacon-torch: compiling the physics for this batch (once per process and shape; the first steps take "
        "seconds to a minute; compile=False runs eagerly)",
        file=sys.stderr,
        flush=True,
    )


class _Kernel:
    """A kernel as :meth:`Kernels.__call__` returns it (an object, not a closure, so
    that an env can be pickled)."""

    def __init__(self, kernels: Kernels, fn: Callable) -> None:
        self.kernels, self.fn = kernels, fn

    def __call__(self, *args, **kwargs):
        kernels, fn = self.kernels, self.fn
        # inside a larger compiled function (a whole step), a kernel is traced into
        # that function's graph rather than called as a graph of its own
        if kernels.options is None or torch.compiler.is_compiling():
            return fn(*args, **kwargs)
        compiled = kernels._cache.get(fn)
        if compiled is None:
            announce_compilation()
            native.library()  # built before the trace, which cannot build it
            compiled = kernels._cache[fn] = torch.compile(fn, **kernels.options)
        with _SETTINGS:
            return compiled(*args, **kwargs)


def step_inputs(state: tuple, obs: torch.Tensor) -> tuple[tuple, torch.Tensor]:
    """``state`` (a NamedTuple of tensors) and ``obs`` as a step leaves them: standard
    strides, and no two tensors sharing memory. A compiled step is specialised on its
    inputs' strides and on which of them alias, and a start's views (a slice, a member
    of size one, an observation that is a view of the state) or shared zeros would
    otherwise compile it again on the second step."""
    out, storages = [], set()
    for value in (*state, obs):
        storage = value.untyped_storage().data_ptr()
        out.append(standard(value) if storage not in storages else value.clone(memory_format=torch.contiguous_format))
        storages.add(storage)
    *fields, obs = out
    return type(state)(*fields), obs
