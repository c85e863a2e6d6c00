"""What the two cavity envs (rayleigh-v0, mixing-v0) share: the grid, the probes and
their history, the set-up of the projection solver, the loop over substeps, the
scalar's transport step, the observation and the render call.

A cavity env declares its numbers (cells per unit length, time step, substeps per
action, the pressure increment's boundary conditions, the
published Jacobi tolerance), its transported scalar (``theta``, ``c``) with its ghost
conditions, and one substep of its physics; :meth:`CavityPhysics.run` advances a flow.
A state's first four fields are its flow (:class:`~beacon_torch.numerics.projection.Flow`:
``u``, ``v``, ``p`` and the scalar), which travels as one typed value to the substeps
and back.

Where autograd records an action on the CPU, its substeps run as the forward path runs
them, keeping only the velocities and the scalar after each, and the backward pass is
the substeps' adjoint written out (:class:`_Substeps`, with the env's
``substep_adjoint``): per substep the transport's reverse sweep and its coefficients'
adjoint, the projection (its own adjoint), and the predictor's (the momentum terms' C
adjoint and the pressure gradient's), in the forward's stencil form. No graph of the
substeps is kept: an action holds a few hundred of the fields' copies, where the
recorded substeps held their every intermediate.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import numpy as np
import torch
import torch.nn.functional as F

from beacon_torch.core.card import FrameInputs
from beacon_torch.core.physics import Physics
from beacon_torch.core.state import State
from beacon_torch.numerics import native
from beacon_torch.numerics.grid import NEUMANN, Ghosts
from beacon_torch.numerics.projection import Cavity, Flow
from beacon_torch.numerics.staggered import project_adjoint
from beacon_torch.numerics.transport import sweep_adjoint

N_PROBES = 4
HISTORY = 4  # the 3 previous probe vectors and the current one, oldest first
PROBED = ("scalar", "u", "v")  # the fields sampled at every probe, in this order
N_OBS = len(PROBED) * N_PROBES**2 * HISTORY


def grid(L: float, H: float, cells_per_unit: int) -> tuple[int, int, float, float]:
    """``(nx, ny, dx, dy)`` of an L x H cavity."""
    nx, ny = int(round(L * cells_per_unit)), int(round(H * cells_per_unit))
    return nx, ny, L / nx, H / ny


def probe_indices(n: int, device=None) -> torch.Tensor:
    """``N_PROBES`` evenly spaced ghosted indices along ``n`` cells: n // 8 + (n // 4) k
    (6, 18, 30, 42 for 50 cells; 12, 37, 62, 87 for 100, as published)."""
    return torch.tensor([n // 8 + (n // 4) * k for k in range(N_PROBES)], device=device)


class Probes:
    """Samples the fields ``PROBED`` of a batch-first flow at a ``N_PROBES x N_PROBES``
    grid and keeps the history."""

    def __init__(self, nx: int, ny: int, device=None) -> None:
        self.ix = probe_indices(nx, device)[:, None]
        self.iy = probe_indices(ny, device)[None, :]
        self.size = len(PROBED) * N_PROBES**2

    def sample(self, flow: Flow) -> torch.Tensor:
        """``[B, len(PROBED) * N_PROBES^2]``, field by field."""
        return torch.cat([getattr(flow, k)[:, self.ix, self.iy].flatten(1) for k in PROBED], -1)

    def start(self, flow: Flow) -> torch.Tensor:
        """``[B, HISTORY, size]``: zeros for the steps before, the current sample last
        (the published order: oldest first)."""
        current = self.sample(flow)[:, None]
        return torch.cat((current.new_zeros((current.shape[0], HISTORY - 1, self.size)), current), 1)

    def push(self, history: torch.Tensor, flow: Flow) -> torch.Tensor:
        """The history with the oldest sample dropped and the current one appended."""
        return torch.cat((history[:, 1:], self.sample(flow)[:, None]), 1)


def transport(
    s: torch.Tensor, u: torch.Tensor, v: torch.Tensor, ghosts: Ghosts, offset, cavity: Cavity, kappa, dt: float
) -> torch.Tensor:
    """The ghosted scalar ``s`` (``[nx + 2, ny + 2, B]``) after one substep's transport
    by the face velocities ``u``, ``v``, as the published step leaves it: the ghosts are
    set from the interior (and the wall values of ``offset``) before the sweep and kept
    after it, so that what reads the ghosted array (mixing's reward) sees those."""
    s = ghosts(s[1:-1, 1:-1], offset)
    interior = cavity.sweep(s, u, v, kappa, dt, cavity.dx, cavity.dy)
    return torch.cat((s[:1], torch.cat((s[1:-1, :1], interior, s[1:-1, -1:]), 1), s[-1:]), 0)


def transport_adjoint(
    grad: torch.Tensor,
    s: torch.Tensor,
    new: torch.Tensor,
    u: torch.Tensor,
    v: torch.Tensor,
    ghosts: Ghosts,
    offset,
    cavity: Cavity,
    kappa,
    dt: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """The gradients of :func:`transport`'s ``s`` (its ghosts read nothing: zero),
    ``u``, ``v`` and ``offset`` from ``grad``, that of its result ``new`` (where
    :attr:`Cavity.adjoint`)."""
    ghosted = ghosts(s[1:-1, 1:-1], offset)
    gs, gu, gv = sweep_adjoint(grad, new, ghosted, u, v, kappa, dt, cavity.dx, cavity.dy)
    g_offset = None if offset is None else gs.sum_to_size(offset.shape)
    return F.pad(ghosts.fold(gs), (0, 0, 1, 1, 1, 1)), gu, gv, g_offset


def substep_adjoint(start: Flow, end: Flow, grad: Flow, walls, offset, cavity: Cavity, ghosts: Ghosts, nu, kappa, dt):
    """The adjoint of a cavity's substep (the predictor, the projection, the scalar's
    transport; where :attr:`Cavity.adjoint`), from the fields before (``start``) and
    after it (``end``) and ``grad``, the gradient of the flow it gives: the gradients of
    its flow, of the predictor's source (its ``v_source``: each env says what it read),
    of its ``walls`` and of the scalar's ``offset``."""
    g_s, gu, gv, g_offset = transport_adjoint(
        grad.scalar, start.scalar, end.scalar, end.u, end.v, ghosts, offset, cavity, kappa, dt
    )
    gu, gv, gp = project_adjoint(grad.u + gu, grad.v + gv, grad.p, cavity.solver, dt, cavity.dx, cavity.dy)
    grads, g_source, g_walls = cavity.predict_adjoint(start, walls, nu, dt, gu, gv)
    return Flow(grads.u, grads.v, grads.p + gp, g_s), g_source, g_walls, g_offset


def _any_substep(substep: Callable, i, flow: Flow, *inputs) -> Flow:
    """A cavity's substep as the loop over an action's substeps calls it (every
    substep of an action is the same)."""
    return substep(flow, *inputs)


class _Stored:
    """``length`` substeps of ``substep`` from a flow: the flow after the last, and the
    velocities and scalar after each, stacked (``[length, ...]``; what the substeps'
    adjoint reads; an object, not a closure, so that an env can be pickled)."""

    def __init__(self, substep: Callable, length: int) -> None:
        self.substep, self.length = substep, length

    def __call__(self, flow: Flow, *inputs) -> tuple[Flow, tuple[torch.Tensor, ...]]:
        kept = []
        for _ in range(self.length):
            flow = self.substep(flow, *inputs)
            kept.append((flow.u, flow.v, flow.scalar))
        return flow, tuple(torch.stack(fields) for fields in zip(*kept, strict=True))


class _Reversed:
    """The adjoint of ``length`` substeps: ``adjoint`` applied from the last substep to
    the first, from the fields before the first (``start``: u, v, the scalar) and after
    each (``after``, stacked as :class:`_Stored` gives them), the gradients of the walls'
    and the scalar's offsets summed over the substeps."""

    def __init__(self, adjoint: Callable, length: int) -> None:
        self.adjoint, self.length = adjoint, length

    def __call__(self, start: tuple, after: tuple, grad: Flow, walls, offset, *inputs):
        g_walls = g_offset = None
        fields = lambda j: start if j < 0 else tuple(t[j] for t in after)
        for j in reversed(range(self.length)):
            (u0, v0, s0), (u1, v1, s1) = fields(j - 1), fields(j)
            grad, gw, go = self.adjoint(Flow(u0, v0, None, s0), Flow(u1, v1, None, s1), grad, walls, offset, *inputs)
            g_walls, g_offset = _summed(g_walls, gw), _summed(g_offset, go)
        return grad, g_walls, g_offset


def _summed(total, g):
    """``total + g`` for gradients that may be None (none yet, or none given) or
    tuples of tensors (the walls' two offsets)."""
    if g is None or total is None:
        return total if g is None else g
    return tuple(map(torch.add, total, g)) if isinstance(g, tuple) else total + g


class _Substeps(torch.autograd.Function):
    """An action's substeps with their adjoint written out as the backward pass: the
    forward pass is the substeps without a graph (the forward path's own code), keeping
    the velocities and the scalar after each substep, and the backward pass runs each
    substep's adjoint (:attr:`CavityPhysics.substep_adjoint`) from the last to the
    first, from those fields alone (the pressure enters linearly and needs none).
    Differentiable once; not under ``torch.func`` (the env then records the substeps
    as it does elsewhere)."""

    @staticmethod
    def forward(ctx, physics, n: int, nu, kappa, offset, wall_u, wall_v, u, v, p, s):
        walls = None if wall_u is None else (wall_u, wall_v)
        inputs = (walls, offset, physics.cavity, physics.ghosts, nu, kappa)
        flow, kept = Flow(u, v, p, s), [(u, v, s)]
        for length in physics.adjoint_chunks(n):
            flow, fields = physics.stored[length](flow, *inputs)
            kept.append(fields)
        ctx.physics, ctx.nu, ctx.kappa, ctx.n = physics, nu, kappa, n
        ctx.ends = (offset is not None, wall_u is not None)
        ctx.save_for_backward(*[t for t in (offset, wall_u, wall_v) if t is not None], *(t for f in kept for t in f))
        return tuple(flow)

    @staticmethod
    def backward(ctx, gu, gv, gp, gs):
        physics, saved = ctx.physics, list(ctx.saved_tensors)
        has_offset, has_walls = ctx.ends
        offset = saved.pop(0) if has_offset else None
        walls = (saved.pop(0), saved.pop(0)) if has_walls else None
        kept = [tuple(saved[k : k + 3]) for k in range(0, len(saved), 3)]
        grad, g_walls, g_offset = Flow(gu, gv, gp, gs), None, None
        inputs = (walls, offset, physics.cavity, physics.ghosts, ctx.nu, ctx.kappa)
        chunks = physics.adjoint_chunks(ctx.n)
        for c in reversed(range(len(chunks))):
            # the fields before the chunk: the last of the chunk before, or the action's start
            start = kept[0] if c == 0 else tuple(t[-1] for t in kept[c])
            grad, gw, go = physics.reversed[chunks[c]](start, kept[c + 1], grad, *inputs)
            g_walls, g_offset = _summed(g_walls, gw), _summed(g_offset, go)
        g_walls = g_walls or (None, None)
        return None, None, None, None, g_offset, *g_walls, *grad


class CavityPhysics(Physics):
    """Base of the cavities' physics: the solver set up from the parameters ``L``,
    ``H`` and ``solver``, probes of the scalar and the velocities, their history as
    observation."""

    members_innermost = True

    episode_length: ClassVar[int] = 100

    scalar: ClassVar[str]  # the transported scalar's name in the state
    cells_per_unit: ClassVar[int]
    dt: ClassVar[float]
    substeps: ClassVar[int]  # per action
    poisson_bc: ClassVar[Sequence[str]] = (NEUMANN,) * 4
    jacobi_tol: ClassVar[float]  # the published solve's stopping tolerance (solver="jacobi")
    # (flow, walls, offset, cavity, ghosts, nu, kappa) -> flow: one substep of the
    # solver's batch-last flow, a staticmethod of the physics class
    substep: ClassVar[Callable]
    # (start, end, grad, walls, offset, cavity, ghosts, nu, kappa) -> (gradient of the
    # start's flow, of the walls' offsets or None, of the scalar's offset or None): the
    # substep's adjoint from the fields before and after it (u, v and the scalar), where
    # the grid has one (Cavity.adjoint); None: autograd records the substeps
    substep_adjoint: ClassVar[Callable | None] = None
    # substeps a compiled call of the written-out adjoint runs, each way (None: the
    # kernels' chunk, ``grad_chunk``)
    adjoint_chunk: ClassVar[int | None] = None
    # the written-out adjoint's compiled calls by their number of substeps (None: the
    # grid has no adjoint, or a physics sets itself up without the base's set-up)
    stored: dict | None = None
    reversed: dict | None = None

    def __init_subclass__(cls, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        fields = getattr(cls, "state_type", None) and cls.state_type._fields[:4]
        if fields and fields != ("u", "v", "p", cls.scalar):
            raise TypeError(
                f"{cls.__name__}.state_type must begin with the flow's fields ('u', 'v', 'p', {cls.scalar!r}),"
                f" not {fields}"
            )

    def member_floats(self) -> int:
        return 5 * (self.nx + 2) * (self.ny + 2)  # u, v, p, the scalar and a projection's work

    def setup(self, p) -> None:
        self.nx, self.ny, self.dx, self.dy = self.grid(p)
        tol = self.jacobi_tol if p.solver == "jacobi" else None
        self.cavity = Cavity(
            self.nx,
            self.ny,
            self.dx,
            self.dy,
            self.poisson_conditions(p),
            jacobi_tol=tol,
            dtype=self.dtype,
            device=self.device,
        )
        self.solver = self.cavity.solver
        self.ghosts = self.scalar_ghosts()
        self._substeps = self.kernels.loop(functools.partial(_any_substep, self.substep))
        self.probes = Probes(self.nx, self.ny, self.device)
        if self.substep_adjoint is not None and self.cavity.adjoint:
            self.stored, self.reversed = {}, {}

    def adjoint_chunks(self, n: int) -> list[int]:
        """The substeps of an action as the written-out adjoint runs them, in order: chunks
        of :attr:`adjoint_chunk` substeps a compiled call (else the kernels'
        :attr:`~beacon_torch.compiled.Kernels.chunk`), the rest one by one; the calls of
        each length made on first use."""
        chunk = max(1, self.adjoint_chunk or self.kernels.chunk)
        chunks = [chunk] * (n // chunk) + [1] * (n % chunk)
        for length in set(chunks) - set(self.stored):
            self.stored[length] = self.kernels(_Stored(self.substep, length))
            self.reversed[length] = self.kernels(_Reversed(self.substep_adjoint, length))
        return chunks

    def _adjoint_applies(self, flow: Flow, walls, offset, nu, kappa) -> bool:
        """Whether :meth:`run` differentiates its substeps through :class:`_Substeps`:
        autograd records, the grid has the adjoint, the viscosity and diffusivity are
        constants of the graph, and no ``torch.func`` transform or trace is active."""
        if self.stored is None:
            return False
        tensors = [*flow, *(walls or ()), *([offset] if offset is not None else [])]
        if not native.recording(*tensors) or not native.takes(*flow):
            return False
        if any(isinstance(t, torch.Tensor) and t.requires_grad for t in (nu, kappa)):
            return False
        return not torch.compiler.is_compiling() and torch._C._functorch.peek_interpreter_stack() is None

    def grid(self, p) -> tuple[int, int, float, float]:
        """``(nx, ny, dx, dy)`` of the parameters' cavity."""
        return grid(p.L, p.H, self.cells_per_unit)

    def poisson_conditions(self, p) -> Sequence[str]:
        """The pressure increment's conditions on the left, right, bottom and top."""
        return self.poisson_bc

    def scalar_ghosts(self) -> Ghosts:
        """The ghost map of the scalar (its wall conditions)."""
        raise NotImplementedError

    def run(self, flow: Flow, n: int, nu, kappa, *, walls=None, offset: torch.Tensor | None = None) -> Flow:
        """``n`` substeps from a batch-first ghosted flow with the wall-velocity offsets
        ``walls`` (``Cavity.walls``; None for walls at rest) and the scalar's ghost
        offset: the layout converted once each way."""
        flow = self.cavity.to_solver(flow, self.ghosts, offset)
        if self._adjoint_applies(flow, walls, offset, nu, kappa):
            wall_u, wall_v = walls if walls is not None else (None, None)
            flow = Flow(*_Substeps.apply(self, n, nu, kappa, offset, wall_u, wall_v, *flow))
        else:
            flow = self._substeps(n, flow, walls, offset, self.cavity, self.ghosts, nu, kappa)
        return self.cavity.to_state(flow, walls if walls is not None else self.cavity.walls(like=flow.u))

    def flow(self, state: State) -> Flow:
        """The flow of a state: its first four fields."""
        return Flow(*state[:4])

    def kinetic_energy(self, state: State) -> torch.Tensor:
        """``[batch]``: half the mean squared speed over the interior faces, per unit
        mass (the two components on their own faces)."""
        u, v = state.u[:, 1:-1, 1:-1], state.v[:, 1:-1, 1:-1]
        return 0.5 * ((u**2).mean((-2, -1)) + (v**2).mean((-2, -1)))

    def observe(self, p, state: State) -> torch.Tensor:
        return state.probes.flatten(1)


def cavity_frame(
    name: str,
    actuation: Callable[[Any, State], np.ndarray],
    scalar_range: Callable[[Any, int], tuple[float, float]],
    action_labels: Sequence[str] | None = None,
    size: Callable[[Any, Any], tuple[float, float]] = lambda physics, params: (params.L, params.H),
) -> Callable[..., np.ndarray]:
    """The frame function of a cavity env (its card's ``frame``): the scalar's field and
    the velocity of the last state, titled ``name``, with the bars ``actuation(physics,
    state)`` (named ``action_labels``, else numbered), the colour range
    ``scalar_range(params, member)`` and the flow's length and height ``size(physics,
    params)``."""

    def frame(f: FrameInputs) -> np.ndarray:
        from beacon_torch.render import cavity_frame

        last, physics = f.states[-1], f.physics
        vmin, vmax = scalar_range(f.params, f.member)
        length, height = size(physics, f.params)
        return cavity_frame(
            name,
            getattr(last, physics.scalar)[1:-1, 1:-1].double().numpy(),
            last.u.double().numpy(),
            last.v.double().numpy(),
            length,
            height,
            actuation(physics, last),
            t=physics.dt * physics.substeps * f.step,
            scalar_label=physics.scalar,
            vmin=vmin,
            vmax=vmax,
            action_labels=action_labels,
        )

    return frame
