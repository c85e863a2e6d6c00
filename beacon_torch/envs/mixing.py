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

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import torch

from beacon_torch.core.card import Card, GradCheck
from beacon_torch.core.state import Noise
from beacon_torch.envs.cavity import N_OBS, CavityPhysics, cavity_frame, transport
from beacon_torch.envs.cavity import substep_adjoint as cavity_adjoint
from beacon_torch.numerics.grid import GRADIENT, NEUMANN, ZERO_GHOST, Ghosts
from beacon_torch.numerics.projection import Cavity, Flow
from beacon_torch.numerics.staggered import project
from beacon_torch.params import param

DT = 0.002
SUBSTEPS = 250
# wall velocities (u_bottom, u_top, v_left, v_right) of the discrete actions, in u_max
LIDS = ((1.0, -1.0, 0.0, 0.0), (-1.0, 1.0, 0.0, 0.0), (0.0, 0.0, -1.0, 1.0), (0.0, 0.0, 1.0, -1.0))


class MixingState(NamedTuple):
    """The flow (a :class:`~beacon_torch.numerics.projection.Flow`'s fields, batch
    first) and what the env adds."""

    u: torch.Tensor  # [batch, nx + 2, ny + 2] the x-velocity on the faces, ghosted
    v: torch.Tensor  # [batch, nx + 2, ny + 2] the y-velocity on the faces, ghosted
    p: torch.Tensor  # [batch, nx, ny] the pressure of the cells
    c: torch.Tensor  # [batch, nx + 2, ny + 2] the concentration, ghosted
    walls: torch.Tensor  # [batch, 4] the wall speeds of the last action, in units of u_max
    probes: torch.Tensor  # [batch, HISTORY, 3 * 16] the probe samples, oldest first


@dataclass(frozen=True)
class MixingParams:
    L: float = param(1.0, low=0.2, high=4.0, per_member=False, doc="cavity length (100 cells per unit)")
    H: float = param(1.0, low=0.2, high=4.0, per_member=False, doc="cavity height")
    re: float = param(
        100.0, low=1.0, high=1e3, doc="Reynolds number: viscosity 1 / re and wall speed u_max = 0.01 re / L"
    )
    pe: float = param(1e4, low=1.0, high=1e8, doc="Peclet number (diffusivity 1 / pe)")
    side: float = param(
        0.5, low=0.02, high=4.0, per_member=False, doc="side of the initial square patch, at most min(L, H)"
    )
    c0: float = param(1.0, low=0.0, high=1e3, low_open=True, doc="initial concentration in the patch")
    solver: str = param(
        "direct",
        kind="choice",
        choices=("direct", "jacobi"),
        doc="pressure increment: direct solve, or the published Jacobi iterations (exact comparisons; eager only)",
    )

    def __post_init__(self):
        if self.side > min(self.L, self.H):
            raise ValueError(f"parameter 'side' = {self.side:g} must fit in the cavity ({self.L:g} x {self.H:g})")


def substep(flow: Flow, walls, c_offset, cavity: Cavity, c_ghosts: Ghosts, nu, kappa) -> Flow:
    """One projection substep of the solver's batch-last flow with the wall-velocity
    ghost offsets ``walls`` (:meth:`Cavity.walls`); no flux of c through the walls
    (``c_offset`` None)."""
    u, v = cavity.predict(flow, walls, nu, DT)
    u, v, p = project(u, v, flow.p, cavity.solver, DT, cavity.dx, cavity.dy)
    return Flow(u, v, p, transport(flow.scalar, u, v, c_ghosts, c_offset, cavity, kappa, DT))


def substep_adjoint(start: Flow, end: Flow, grad: Flow, walls, c_offset, cavity: Cavity, c_ghosts, nu, kappa):
    """:func:`substep`'s adjoint (:func:`~beacon_torch.envs.cavity.substep_adjoint`,
    where :attr:`Cavity.adjoint`): the gradients of its flow, walls and ``c_offset``."""
    grads, _, g_walls, g_offset = cavity_adjoint(start, end, grad, walls, c_offset, cavity, c_ghosts, nu, kappa, DT)
    return grads, g_walls, g_offset


class MixingPhysics(CavityPhysics):
    """The lid-driven cavity mixing a scalar (4 discrete actions: which walls move,
    which way)."""

    diagnostics = {
        "mixing_deviation": "the mean |c - c_mixed| over the cavity (minus the reward)",
        "kinetic_energy": "half the mean squared speed in the cavity",
    }
    Params = MixingParams
    state_type = MixingState
    discrete = True
    scalar = "c"
    cells_per_unit = 100
    dt = DT
    substeps = SUBSTEPS
    # a differentiated compiled substep here is milliseconds, its call's fixed cost a few
    # percent: chunks of 8 measured slower (9.7 against 8.5 times the forward) and took
    # 255 s to compile against 74
    grad_chunk = 1
    # the substeps' adjoint written out, whose calls keep no graph: 10 substeps a call
    # made an action 16 % cheaper than 1 (575 against 686 ms at 8 members, forward and
    # backward) for 168 s of compilation once
    adjoint_chunk = 10
    # the pressure increment: zero normal gradient but on the top wall, where its ghost is 0
    poisson_bc = (NEUMANN, NEUMANN, NEUMANN, ZERO_GHOST)
    jacobi_tol = 1e-4
    substep = staticmethod(substep)
    substep_adjoint = staticmethod(substep_adjoint)

    @classmethod
    def sizes(cls, p) -> tuple[int, int]:
        return N_OBS, 4

    def setup(self, p) -> None:
        super().setup(p)
        self._lids = torch.tensor(LIDS, dtype=self.dtype, device=self.device)

    def scalar_ghosts(self) -> Ghosts:
        # the published reward averages over the ghosted array, whose corners stay zero
        return Ghosts.cells(self.nx, self.ny, *(GRADIENT,) * 4, corners=False, dtype=self.dtype, device=self.device)

    # derived from the parameters at each use, so that every differentiated step has
    # its own graph to them
    def u_max(self, p):
        return self.member(p.re) * 0.01 / p.L  # the published scaling: 1 at the defaults

    def nu(self, p):
        return 1.0 / self.member(p.re, 0)  # per member, against the batch-last fields

    def kappa(self, p):
        return 1.0 / self.member(p.pe, 0)

    def target(self, p):
        return p.side**2 * self.member(p.c0, 2) / (p.L * p.H)

    def walls(self, action: torch.Tensor) -> torch.Tensor:
        """``[B, 4]`` wall speeds (u_bottom, u_top, v_left, v_right) of an action batch,
        in units of u_max."""
        return self._lids[action]

    def initial_state(self, p, generator, mask=None) -> MixingState:
        B, nx, ny = self.num_envs, self.nx, self.ny
        zeros = lambda *shape: torch.zeros((B, *shape), dtype=self.dtype, device=self.device)
        c = zeros(nx + 2, ny + 2)
        # the published patch spans ghosted indices i0 .. i0 + n - 1, i.e. one cell off
        # the centre towards the origin (25..74 of 0..101 at the defaults)
        n_side = int(round(p.side / self.dx)), int(round(p.side / self.dy))
        i0, j0 = int(round((nx - n_side[0]) / 2)), int(round((ny - n_side[1]) / 2))
        c[:, i0 : i0 + n_side[0], j0 : j0 + n_side[1]] = 1.0
        c = c * self.member(p.c0, 2)
        flow = Flow(u=zeros(nx + 2, ny + 2), v=zeros(nx + 2, ny + 2), p=zeros(nx, ny), scalar=c)
        return MixingState(*flow, walls=zeros(4), probes=self.probes.start(flow))

    def advance(self, p, state: MixingState, action: torch.Tensor, count: torch.Tensor, noise: Noise):
        walls = self.walls(action)
        lids = (walls * self.u_max(p)).T
        walls_moving = self.cavity.walls(*lids, like=lids)
        flow = self.run(self.flow(state), SUBSTEPS, self.nu(p), self.kappa(p), walls=walls_moving)
        new = MixingState(*flow, walls=walls, probes=self.probes.push(state.probes, flow))
        return new, -(new.c - self.target(p)).abs().mean((-2, -1))

    def diagnose(self, p, state: MixingState) -> dict[str, torch.Tensor]:
        return {
            "mixing_deviation": (state.c - self.target(p)).abs().mean((-2, -1)),
            "kinetic_energy": self.kinetic_energy(state),
        }


class MixingContinuousPhysics(MixingPhysics):
    """a in [-1, 1]^2 drives the bottom/top walls at (+a0, -a0) u_max and the
    right/left walls at (+a1, -a1) u_max."""

    discrete = False

    @classmethod
    def sizes(cls, p) -> tuple[int, int]:
        return N_OBS, 2

    def walls(self, action: torch.Tensor) -> torch.Tensor:
        a0, a1 = action[:, 0], action[:, 1]
        return torch.stack((a0, -a0, -a1, a1), -1)

    def null_action(self) -> torch.Tensor:
        # the continuous image of discrete action 0 (the paper's constant baseline)
        a = torch.zeros((self.num_envs, 2), dtype=self.dtype, device=self.device)
        a[:, 0] = 1.0
        return a


CARD = Card(
    family="2-D",
    costly=True,  # an action is tens of substeps of a 2-D projection
    published_speed=3.7,
    speed_target=30.0,
    paper_ppo=-12.0,
    # a 30 x 30 cavity of the same scheme and the same probes, a tenth of the published
    # grid's cost
    test_settings={"L": 0.3, "H": 0.3, "side": 0.2},
    frame=cavity_frame(
        "mixing",
        lambda physics, state: state.walls.double().numpy(),
        lambda params, member: (0.0, float(params.c0[member])),
        ("u_b", "u_t", "v_l", "v_r"),
    ),
)
CONTINUOUS_CARD = dataclasses.replace(CARD, gradcheck=GradCheck("re", 100.0, warmup=1, steps=1))
