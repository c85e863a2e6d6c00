"""mixing-v0: mix a passive scalar in a cavity by moving its walls (BEACON paper,
section "Mixing").

Lid-driven cavity flow with a passive concentration c:

    div u = 0
    u_t + (u.grad) u = -grad p + lap u / Re
    c_t + u.grad c = lap c / Pe

on the shared staggered-grid projection solver (``beacon_torch.numerics.projection``),
100 cells per unit length, dt = 0.002, 250 substeps per action, 100 actions. Each
discrete action drives one pair of opposite walls in opposite directions at u_max;
``mixing-continuous-v0`` sets both pairs' speeds continuously. The reward is minus the
mean distance of c from its perfectly mixed value.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from beacon_torch.base import FlowEnv, State
from beacon_torch.numerics.projection import (
    GRADIENT,
    NEUMANN,
    ZERO_GHOST,
    Cavity,
    Ghosts,
    project,
)
from beacon_torch.params import param
from beacon_torch.probes import HISTORY, N_PROBES, Probes

CELLS_PER_UNIT = 100
DT = 0.002
SUBSTEPS = 250
UNROLL = 5  # substeps per call of the (compiled) kernel; divides SUBSTEPS
EPISODE_LENGTH = 100
# wall velocities (u_bottom, u_top, v_left, v_right) of the discrete actions, in u_max
LIDS = ((1.0, -1.0, 0.0, 0.0), (-1.0, 1.0, 0.0, 0.0), (0.0, 0.0, -1.0, 1.0), (0.0, 0.0, 1.0, -1.0))
# the pressure increment: zero normal gradient but on the top wall, where its ghost is 0
POISSON_BC = (NEUMANN, NEUMANN, NEUMANN, ZERO_GHOST)
JACOBI_TOL = 1e-4  # the published solve's stopping tolerance (solver="jacobi")


@dataclass(frozen=True)
class MixingParams:
    L: float = param(1.0, low=0.2, high=4.0, per_member=False, doc="cavity length")
    H: float = param(1.0, low=0.2, high=4.0, per_member=False, doc="cavity height")
    re: float = param(100.0, low=1.0, high=1e3, doc="Reynolds number (viscosity 1 / re)")
    pe: float = param(1e4, low=1.0, high=1e8, doc="Peclet number (diffusivity 1 / pe)")
    side: float = param(0.5, low=0.02, high=4.0, per_member=False, doc="side of the initial square patch")
    c0: float = param(1.0, low=0.0, high=1e3, low_open=True, doc="initial concentration in the patch")
    solver: str = param("direct", kind="choice", choices=("direct", "jacobi"), doc="pressure increment: direct solve, or the published Jacobi iterations (exact comparisons)")

    def __post_init__(self):
        if self.side > min(self.L, self.H):
            raise ValueError(f"parameter 'side' = {self.side:g} must fit in the cavity ({self.L:g} x {self.H:g})")


def grid(p: MixingParams) -> tuple[int, int, float, float]:
    nx, ny = int(round(p.L * CELLS_PER_UNIT)), int(round(p.H * CELLS_PER_UNIT))
    return nx, ny, p.L / nx, p.H / ny


def substep(fields: State, walls, cavity: Cavity, c_ghosts: Ghosts, nu, kappa) -> State:
    """One projection substep on the solver's batch-last fields with the wall-velocity
    ghost offsets ``walls`` (:meth:`Cavity.walls`)."""
    dx, dy = cavity.dx, cavity.dy
    u, v = cavity.predict(fields, walls, nu, DT)
    u, v, p = project(u, v, fields["p"], cavity.solver, DT, dx, dy)
    # the published step sets the ghosts from the interior before its transport and
    # leaves them so after it: the reward, a mean over the ghosted array, sees those
    c = c_ghosts(fields["c"][1:-1, 1:-1])
    interior = cavity.sweep(c, u, v, kappa, DT, dx, dy)
    c = torch.cat((c[:1], torch.cat((c[1:-1, :1], interior, c[1:-1, -1:]), 1), c[-1:]), 0)
    return {"u": u, "v": v, "p": p, "c": c}


class MixingEnv(FlowEnv):
    """Batched mixing-v0 (4 discrete actions: which walls move, which way)."""

    env_id = "mixing-v0"
    Params = MixingParams
    episode_length = EPISODE_LENGTH
    discrete = True
    inductor_options = {"cpp_wrapper": True}
    compile_fullgraph = False

    @classmethod
    def sizes(cls, p) -> tuple[int, int]:
        return 3 * N_PROBES**2 * HISTORY, 4

    def setup(self) -> None:
        p = self.params
        self.nx, self.ny, self.dx, self.dy = grid(p)
        tol = JACOBI_TOL if p.solver == "jacobi" else None
        self.cavity = Cavity(self.nx, self.ny, self.dx, self.dy, POISSON_BC, jacobi_tol=tol, dtype=self.dtype, device=self.device)
        self.solver = self.cavity.solver
        self._c_ghosts = Ghosts.cells(self.nx, self.ny, *(GRADIENT,) * 4, corners=False, dtype=self.dtype, device=self.device)
        self._substeps = self.kernels(substep, unroll=UNROLL)
        self._probes = Probes(("c", "u", "v"), self.nx, self.ny, self.device)
        self._lids = torch.tensor(LIDS, dtype=self.dtype, device=self.device)

    # derived from the parameters at each use, so that every differentiated step has
    # its own graph to them
    @property
    def u_max(self):
        return self.member(self.params.re) * 0.01 / self.params.L  # the published scaling: 1 at the defaults

    @property
    def nu(self):
        return 1.0 / self.member(self.params.re, 0)  # per member, against the batch-last fields

    @property
    def kappa(self):
        return 1.0 / self.member(self.params.pe, 0)

    @property
    def target(self):
        p = self.params
        return p.side**2 * self.member(p.c0, 2) / (p.L * p.H)

    def walls(self, action: torch.Tensor) -> torch.Tensor:
        """``[B, 4]`` wall speeds (u_bottom, u_top, v_left, v_right) of an action batch,
        in units of u_max."""
        return self._lids[action]

    def null_action(self) -> torch.Tensor:
        return torch.zeros(self.batch_size, dtype=torch.int64, device=self.device)

    def initial_state(self, mask: torch.Tensor | None) -> State:
        p = self.params
        B, nx, ny = self.n_envs, self.nx, self.ny
        zeros = lambda *shape: torch.zeros((B, *shape), dtype=self.dtype, device=self.device)  # noqa: E731
        c = zeros(nx + 2, ny + 2)
        # the published patch spans ghosted indices i0 .. i0 + n - 1, i.e. one cell off
        # the centre towards the origin (25..74 of 0..101 at the defaults)
        n_side = int(round(p.side / self.dx)), int(round(p.side / self.dy))
        i0, j0 = int(round((nx - n_side[0]) / 2)), int(round((ny - n_side[1]) / 2))
        c[:, i0 : i0 + n_side[0], j0 : j0 + n_side[1]] = 1.0
        c = c * self.member(p.c0, 2)
        state = {"u": zeros(nx + 2, ny + 2), "v": zeros(nx + 2, ny + 2), "p": zeros(nx, ny), "c": c}
        state["probes"] = self._probes.start(state)
        state["walls"] = zeros(4)
        return state

    def advance(self, state: State, action: torch.Tensor, count: torch.Tensor):
        walls = self.walls(action)
        lids = (walls * self.u_max).T
        offsets = self.cavity.walls(*lids, like=lids)
        fields = self.cavity.fields(state, {"c": (self._c_ghosts, None)})
        nu, kappa = self.nu, self.kappa
        for _ in range(SUBSTEPS // UNROLL):
            fields = self._substeps(fields, offsets, self.cavity, self._c_ghosts, nu, kappa)
        new = self.cavity.stored(fields, offsets)
        new["probes"] = self._probes.push(state["probes"], new)
        new["walls"] = walls
        return new, -(new["c"] - self.target).abs().mean((-2, -1))

    def observe(self, state: State) -> torch.Tensor:
        return state["probes"].flatten(1)

    def render_frame(self, history: list[State]) -> np.ndarray:
        from beacon_torch.render import cavity_frame

        last = history[-1]
        c0 = float(self.params.c0[self.render_index])
        return cavity_frame(
            "mixing",
            last["c"][1:-1, 1:-1].double().numpy(),
            last["u"].double().numpy(),
            last["v"].double().numpy(),
            self.params.L,
            self.params.H,
            last["walls"].double().numpy(),
            t=DT * SUBSTEPS * (len(history) - 1),
            scalar_label="c",
            vmin=0.0,
            vmax=c0,
            action_labels=["u_b", "u_t", "v_l", "v_r"],
        )


class MixingContinuousEnv(MixingEnv):
    """mixing-continuous-v0: a in [-1, 1]^2 drives the bottom/top walls at
    (+a0, -a0) u_max and the right/left walls at (+a1, -a1) u_max."""

    env_id = "mixing-continuous-v0"
    discrete = False

    @classmethod
    def sizes(cls, p) -> tuple[int, int]:
        return 3 * N_PROBES**2 * HISTORY, 2

    def walls(self, action: torch.Tensor) -> torch.Tensor:
        a0, a1 = action[:, 0], action[:, 1]
        return torch.stack((a0, -a0, -a1, a1), -1)

    def null_action(self) -> torch.Tensor:
        # the continuous image of discrete action 0 (the paper's constant baseline)
        a = torch.zeros((self.n_envs, 2), dtype=self.dtype, device=self.device)
        a[:, 0] = 1.0
        return a
