"""Batched incompressible flow on a staggered grid, for rayleigh and mixing: the
projection method assembled for one rectangular cavity (:class:`Cavity`) from the
numerics it is made of, each in its own module: the grid's boundaries and ghosts
(:mod:`~beacon_torch.numerics.grid`), the Poisson solvers
(:mod:`~beacon_torch.numerics.poisson`), the staggered operators
(:mod:`~beacon_torch.numerics.staggered`) and the scalar transport
(:mod:`~beacon_torch.numerics.transport`), whose names this module also gives.

Layout: every field is ``[X, Y, B]``, batch last (:mod:`~beacon_torch.numerics.grid`).
Envs keep their state batch first
with ghost layers (``[B, nx + 2, ny + 2]``, what probes and rendering read). The flow
travels as one typed value, a :class:`Flow`, from the env's state to the substeps and
back; its layout is converted once each way per action, by :meth:`Cavity.to_solver` and
:meth:`Cavity.to_state`.

What the solver carries (no ghost values):
- ``u``: x-velocity on the x-faces ``0..nx`` of the ``nx`` cells (faces 0 and nx are the
  left and right walls), ``[nx + 1, ny, B]``;
- ``v``: y-velocity on the y-faces ``0..ny`` (bottom and top walls), ``[nx, ny + 1, B]``;
- pressure and scalars (temperature, concentration): cell-centred, ``[nx, ny, B]``.

One substep of the published scheme: an explicit predictor with centred fluxes
(face-averaged velocities) and the current pressure, a projection with the pressure
increment from a direct Poisson solve (or, to compare with the published code to
round-off, its Jacobi iterations), then the published in-place sweep of explicit
centred transport of the scalar by the corrected velocity (:class:`Sweep`). Everything
is out of place, so the graph survives when gradients are wanted.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
import torch.nn.functional as F

from beacon_torch.numerics.grid import (
    GRADIENT,
    NEUMANN,
    PERIODIC,
    VALUE,
    ZERO,
    ZERO_FACE,
    ZERO_GHOST,
    Ghosts,
    edge_offset,
)
from beacon_torch.numerics.poisson import FEW_MEMBERS, JacobiSolver, PoissonSolver, laplacian_1d
from beacon_torch.numerics.staggered import (
    Axis,
    Stretched,
    divergence,
    predict,
    predict_adjoint,
    project,
    project_adjoint,
    tendency,
)
from beacon_torch.numerics.transport import Explicit, Sweep

__all__ = [
    "GRADIENT",
    "NEUMANN",
    "PERIODIC",
    "VALUE",
    "ZERO",
    "ZERO_FACE",
    "ZERO_GHOST",
    "FEW_MEMBERS",
    "Cavity",
    "Flow",
    "Ghosts",
    "JacobiSolver",
    "PoissonSolver",
    "Sweep",
    "divergence",
    "edge_offset",
    "laplacian_1d",
    "predict",
    "predict_adjoint",
    "project",
    "project_adjoint",
    "tendency",
]


class Flow(NamedTuple):
    """A cavity's flow: the velocities, the pressure and the transported scalar.

    Batch first, as an env's state holds it (its first four fields, in this order):
    ``u``, ``v`` and ``scalar`` ghosted ``[B, nx + 2, ny + 2]``, ``p`` ``[B, nx, ny]``.
    Batch last, as the substeps carry it (:meth:`Cavity.to_solver`): ``u``
    ``[nx + 1, ny, B]`` and ``v`` ``[nx, ny + 1, B]`` on their faces, ``p``
    ``[nx, ny, B]`` (the stencils gather the velocities' ghosts), ``scalar``
    ``[nx + 2, ny + 2, B]`` with its ghost layer, refreshed from the interior."""

    u: torch.Tensor
    v: torch.Tensor
    p: torch.Tensor
    scalar: torch.Tensor


class Cavity:
    """The grid of one rectangular cavity: sizes, the pressure-increment solver
    (``poisson_bc`` on left, right, bottom, top), the ghost maps of the velocities and
    the scalar transport sweep. ``jacobi_tol`` None solves for the increment directly;
    a number runs the published Jacobi iterations to that tolerance instead.

    ``dy`` is the rows' height, or an :class:`~beacon_torch.numerics.staggered.Axis`
    of rows of unequal heights (a wall-refined channel); ``dx`` is a number.

    A ``poisson_bc`` of PERIODIC on the left and right makes the x axis wrap around (a
    channel between the bottom and top walls): faces 0 and nx are then one face, carried
    twice with one value, and the predictor works on the grid widened by one wrapped
    cell on each side, so that the closed cavity's stencils reach every face; the
    scalar's transport is then :class:`Explicit` (no ordered sweep), so that the flow
    stays invariant under translation."""

    def __init__(
        self,
        nx: int,
        ny: int,
        dx: float,
        dy: float,
        poisson_bc: Sequence[str] = (NEUMANN,) * 4,
        *,
        jacobi_tol: float | None = None,
        dtype,
        device,
    ) -> None:
        self.nx, self.ny, self.dx, self.dy = nx, ny, dx, dy
        if isinstance(dy, Axis):
            if jacobi_tol is not None:
                raise ValueError("the published Jacobi solve is for equal cells; a stretched y axis is solved directly")
            # rows of unequal heights: the operators' spacing and the solve's from the axis
            along_y = lambda t: t.to(dtype=dtype, device=device, copy=True)[None, :, None]
            self.dy = Stretched(along_y(dy.widths), along_y(dy.gaps), 1)
            lx = laplacian_1d(nx, dx, *poisson_bc[:2])
            ly = dy.laplacian(*poisson_bc[2:])
            self.solver = PoissonSolver.stretched(lx, None, ly, dy.widths, bc=poisson_bc, dtype=dtype, device=device)
        elif jacobi_tol is None:
            self.solver = PoissonSolver(nx, ny, dx, dy, poisson_bc, dtype=dtype, device=device)
        else:
            self.solver = JacobiSolver(nx, ny, dx, dy, poisson_bc, jacobi_tol, dtype=dtype, device=device)
        self.periodic = poisson_bc[0] == PERIODIC
        self.sweep = Explicit() if self.periodic else Sweep(nx, ny, device, dtype)
        kw = dict(periodic=self.periodic, dtype=dtype, device=device)
        self.u_ghosts = Ghosts.u_faces(nx, ny, **kw)
        self.v_ghosts = Ghosts.v_faces(nx, ny, **kw)
        # the x positions of a ghosted cell field that a predictor's source covers
        self.source_x = slice(None) if self.periodic else slice(1, -1)
        if self.periodic:
            kw = dict(dtype=dtype, device=device)
            wall_rows = Ghosts._cell_axis(ny, VALUE, VALUE)
            # faces -1..nx+1, cells -2..nx+1 and -1..nx: a closed cavity of nx + 2 cells
            self.u_wide = Ghosts.periodic_wide(nx, 1, 2, *wall_rows, **kw)
            self.v_wide = Ghosts.periodic_wide(nx, 2, 2, None, [0.0, *[1.0] * (ny - 1), 0.0], **kw)
            self.p_wide = Ghosts.periodic_wide(nx, 1, 1, None, [1.0] * ny, **kw)

    def walls(
        self, u_bottom=0.0, u_top=0.0, v_left=0.0, v_right=0.0, *, like: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The ghost offsets of the tangential wall velocities (numbers or ``[B]``):
        ``(u offset [1, ny + 2, B'], v offset [nx + 2, 1, B'])``."""
        return (
            edge_offset(self.ny + 2, 1, u_bottom, u_top, like),
            edge_offset(self.nx + 2, 0, v_left, v_right, like),
        )

    def predict(
        self, flow: Flow, walls, nu, dt: float, v_source: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """:func:`predict` on the solver's (batch-last) flow, with the wall ghost offsets
        ``walls`` (:meth:`walls`; None for walls at rest). ``v_source`` covers the cells
        ``source_x`` of a ghosted field (the interior; with a periodic x, the ghosts
        too)."""
        off_u, off_v = walls if walls is not None else (None, None)
        if not self.periodic:
            u, v = self.u_ghosts(flow.u, off_u), self.v_ghosts(flow.v, off_v)
            return predict(u, v, flow.p, nu, dt, self.dx, self.dy, v_source)
        if off_v is not None:
            raise ValueError("a periodic channel has no side walls to move")
        u, v, p = self.u_wide(flow.u, off_u), self.v_wide(flow.v), self.p_wide(flow.p)
        u_star, v_star = predict(u, v, p, nu, dt, self.dx, self.dy, v_source)
        return u_star[1:-1], v_star[1:-1]

    @property
    def adjoint(self) -> bool:
        """Whether a substep's adjoint is written out for this grid (:meth:`predict_adjoint`,
        :func:`project_adjoint`, the transport's): between walls, on equal cells, with the
        direct solve and the C kernels."""
        return (
            not self.periodic
            and not isinstance(self.dy, Stretched)
            and isinstance(self.solver, PoissonSolver)
            and self.solver.native
            and self.sweep.native
        )

    def predict_adjoint(
        self, flow: Flow, walls, nu, dt: float, gu: torch.Tensor, gv: torch.Tensor
    ) -> tuple[Flow, torch.Tensor, tuple[torch.Tensor, torch.Tensor] | None]:
        """The gradients of :meth:`predict`'s flow (its ``u``, ``v`` and ``p``; the
        scalar's zero), its source and its ``walls`` from ``gu`` and ``gv``, those of its
        results (where :attr:`adjoint`)."""
        off_u, off_v = walls if walls is not None else (None, None)
        u, v = self.u_ghosts(flow.u, off_u), self.v_ghosts(flow.v, off_v)
        du, dv, gp, g_source = predict_adjoint(u, v, gu, gv, nu, dt, self.dx, self.dy)
        g_walls = None if walls is None else (du.sum_to_size(off_u.shape), dv.sum_to_size(off_v.shape))
        grads = Flow(self.u_ghosts.fold(du), self.v_ghosts.fold(dv), gp, torch.zeros_like(flow.scalar))
        return grads, g_source, g_walls

    def to_solver(self, flow: Flow, ghosts: Ghosts, offset: torch.Tensor | None = None) -> Flow:
        """The batch-last flow the substeps carry, from a batch-first ghosted one; the
        scalar's ghosts from its interior by ``ghosts`` (its wall conditions) and
        ``offset`` (its prescribed wall values, or None)."""
        last = lambda f: f.movedim(0, -1).contiguous()
        return Flow(
            u=last(flow.u[:, 1:, 1:-1]),
            v=last(flow.v[:, 1:-1, 1:]),
            p=last(flow.p),
            scalar=ghosts(last(flow.scalar[:, 1:-1, 1:-1]), offset),
        )

    # the methods that took and gave dicts of fields, now a Flow: said by the error
    RENAMED = {"fields": "to_solver", "stored": "to_state"}

    def __getattr__(self, name: str):
        if name in Cavity.RENAMED:
            raise AttributeError(
                f"Cavity.{name} is now Cavity.{Cavity.RENAMED[name]}, which takes and gives a Flow (u, v, p, scalar) "
                f"instead of a dict of fields"
            )
        raise AttributeError(f"'Cavity' object has no attribute {name!r}")

    def to_state(self, flow: Flow, walls) -> Flow:
        """Back to the batch-first ghosted flow of a state, with the velocities' wall
        ghosts of ``walls`` (:meth:`walls`)."""
        first = lambda f: f.movedim(-1, 0).contiguous()
        u, v = flow.u, flow.v
        # the stored layout has one ghost position before the first face, none after
        u_full = F.pad(self.u_ghosts(u, walls[0]), (0, 0, 0, 0, 1, 0))
        v_full = F.pad(self.v_ghosts(v, walls[1]), (0, 0, 1, 0))
        # the ghost maps zero the wall faces for the predictor; keep what projection left
        u_full[1:, 1:-1] = u
        v_full[1:-1, 1:] = v
        return Flow(u=first(u_full), v=first(v_full), p=first(flow.p), scalar=first(flow.scalar))
