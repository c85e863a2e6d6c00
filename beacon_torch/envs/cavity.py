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
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import numpy as np
import torch

from beacon_torch.core.card import FrameInputs
from beacon_torch.core.physics import Physics
from beacon_torch.core.state import State
from beacon_torch.numerics.grid import NEUMANN, Ghosts
from beacon_torch.numerics.projection import Cavity, Flow

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


def _any_substep(substep: Callable, i, flow: Flow, *inputs) -> Flow:
    """A cavity's substep as the loop over an action's substeps calls it (every
    substep of an action is the same)."""
    return substep(flow, *inputs)


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
