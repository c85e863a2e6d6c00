"""rayleigh-v0: suppress Rayleigh-Benard convection with the bottom plate's temperature
(Beintema et al. 2020; BEACON paper, section "Rayleigh").

Boussinesq flow in an L x H cavity heated from below (theta = +1/2 on average) and cooled
from above (theta = -1/2), adiabatic sides, no-slip walls:

    div u = 0
    u_t + (u.grad) u = -grad p + sqrt(Pr / Ra) lap u + theta y
    theta_t + u.grad theta = lap theta / sqrt(Pr Ra)

on the shared staggered-grid projection solver (``beacon_torch.numerics.projection``),
50 cells per unit length, dt = 0.01, 200 substeps per action, 100 actions. The agent sets
the temperatures of n_sgts bottom segments around the mean 1/2; the reward is minus the
Nusselt number. Every episode starts from the developed single convection roll
(:func:`developed_convection`, shipped for the defaults).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from beacon_torch.base import GradCheck, Noise, map_state
from beacon_torch.cache import cached
from beacon_torch.envs.cavity import N_OBS, CavityEnv, CavityPhysics, transport
from beacon_torch.numerics.grid import GRADIENT, VALUE, Ghosts, edge_offset
from beacon_torch.numerics.projection import Cavity, Flow
from beacon_torch.numerics.staggered import project
from beacon_torch.params import number, param, resolve_params
from beacon_torch.starts import PUBLISHED, choose_start, published_table, start_param

CELLS_PER_UNIT = 50
DT = 0.01
SUBSTEPS = 200
PR = 0.71
T_HOT, T_COLD = 0.5, -0.5
C = 0.75  # largest temperature fluctuation of a segment
DEVELOP_TIME = 200.0
DEVELOP_SEED = 0
PERTURBATION = 1e-6  # breaks the left-right symmetry of the exact solver


class Convection(NamedTuple):
    """The flow of a cavity, batch first (or one member without its batch dimension):
    ghosted ``[nx + 2, ny + 2]`` velocities (faces) and temperature (cells), the
    pressure of the cells ``[nx, ny]``."""

    u: torch.Tensor
    v: torch.Tensor
    p: torch.Tensor
    theta: torch.Tensor


class RayleighState(NamedTuple):
    """The flow (:class:`Convection`'s fields, batch first) and what the env adds."""

    u: torch.Tensor  # [batch, nx + 2, ny + 2]
    v: torch.Tensor  # [batch, nx + 2, ny + 2]
    p: torch.Tensor  # [batch, nx, ny]
    theta: torch.Tensor  # [batch, nx + 2, ny + 2] the temperature
    bottom: torch.Tensor  # [batch, nx] the bottom plate's temperature of the last action
    probes: torch.Tensor  # [batch, HISTORY, 3 * 16] the probe samples, oldest first


@dataclass(frozen=True)
class RayleighParams:
    L: float = param(1.0, low=0.2, high=4.0, per_member=False, doc="cavity length (50 cells per unit)")
    H: float = param(1.0, low=0.2, high=4.0, per_member=False, doc="cavity height")
    n_sgts: int = param(
        10,
        low=1,
        high=200,
        kind="int",
        per_member=False,
        doc="number of bottom segments (actions); divides the cells along L",
    )
    ra: float = param(1e4, low=1.0, high=1e6, per_member=False, differentiable=True, doc="Rayleigh number")
    start: str = start_param("the published stored roll, or the one of developed_convection()")
    solver: str = param(
        "direct",
        kind="choice",
        choices=("direct", "jacobi"),
        doc="pressure increment: direct solve, or the published Jacobi iterations (exact comparisons; eager only)",
    )

    def __post_init__(self):
        choose_start(self, ("L", "H", "ra"))
        nx = int(round(self.L * CELLS_PER_UNIT))
        if nx % self.n_sgts:
            raise ValueError(f"parameter 'n_sgts' = {self.n_sgts} must divide the {nx} cells along L = {self.L:g}")


def temperature_offset(bottom: torch.Tensor, ghosts: Ghosts, ny: int) -> torch.Tensor:
    """The ghost offset of bottom cells at the temperatures ``bottom`` (``[B, nx]``)
    and the cold top plate, ``[nx + 2, ny + 2, B]``."""
    low = bottom.T[ghosts.ix][:, None]  # the side ghosts take their neighbour's value
    return edge_offset(ny + 2, 1, low, T_COLD, bottom)


def substep(flow: Flow, walls, theta_offset: torch.Tensor, cavity: Cavity, theta_ghosts: Ghosts, nu, kappa) -> Flow:
    """One projection substep of the Boussinesq flow, the solver's batch-last flow
    with the temperature as its scalar (no-slip walls: ``walls`` None;
    ``theta_offset`` from :func:`temperature_offset`)."""
    theta = flow.scalar
    # as published, each interior v face takes the temperature of the cell above it
    buoyancy = theta[1:-1, 2:-1]
    u, v = cavity.predict(flow, walls, nu, DT, buoyancy)
    u, v, p = project(u, v, flow.p, cavity.solver, DT, cavity.dx, cavity.dy)
    return Flow(u, v, p, transport(theta, u, v, theta_ghosts, theta_offset, cavity, kappa, DT))


def nusselt(theta: torch.Tensor, dy: float) -> torch.Tensor:
    """Instantaneous Nusselt number: the mean over the bottom cells of the first-order
    temperature gradient to the reference plate temperature 1/2, ``[B]``."""
    return ((T_HOT - theta[:, 1:-1, 1]) / (0.5 * dy)).mean(-1)


def rest_state(num_envs: int, nx: int, ny: int, dtype, device) -> Convection:
    zeros = lambda *shape: torch.zeros((num_envs, *shape), dtype=dtype, device=device)
    return Convection(u=zeros(nx + 2, ny + 2), v=zeros(nx + 2, ny + 2), p=zeros(nx, ny), theta=zeros(nx + 2, ny + 2))


def developed_convection(
    p: RayleighParams = RayleighParams(), *, time: float = DEVELOP_TIME, seed: int = DEVELOP_SEED
) -> Convection:
    """The published initial state: from rest (theta = 0) ``time`` time units without
    control, in float64, after a perturbation of the temperature of amplitude 1e-6 drawn
    from a generator seeded by ``seed`` (the solver is exactly symmetric, so convection
    would otherwise never start). Returns ``u``, ``v``, ``p``, ``theta`` without batch
    dimension."""
    # the physics of these parameters runs the substeps; its own start is never made
    given = {**dataclasses.asdict(p), "start": "generated"}
    cpu, f64 = torch.device("cpu"), torch.float64
    p = resolve_params(RayleighParams, given, batch_size=1, device=cpu, dtype=f64, env_id=RayleighEnv.env_id)
    physics = RayleighPhysics(p, 1, dtype=f64, device=cpu)
    g = torch.Generator().manual_seed(seed)
    flow = Flow(*rest_state(1, physics.nx, physics.ny, torch.float64, "cpu"))
    theta = PERTURBATION * (2.0 * torch.rand(flow.scalar.shape, generator=g, dtype=torch.float64) - 1.0)
    bottom = torch.full((1, physics.nx), T_HOT, dtype=torch.float64)
    offset = temperature_offset(bottom, physics.ghosts, physics.ny)
    flow = physics.run(
        flow._replace(scalar=theta), int(round(time / DT)), physics.nu(p), physics.kappa(p), offset=offset
    )
    return Convection(*(f[0] for f in flow))


def published_convection(nx: int, ny: int) -> Convection:
    """The developed roll stored with the published code: the file's four blocks of
    ghosted ``[nx + 2, ny + 2]`` arrays u, v, p, T (our pressure keeps the cells only)."""
    table = published_table("rayleigh", 4 * (nx + 2), ny + 2)
    u, v, p, theta = table.reshape(4, nx + 2, ny + 2).unbind(0)
    return Convection(u=u, v=v, p=p[1:-1, 1:-1].contiguous(), theta=theta)


def normalise(action: torch.Tensor) -> torch.Tensor:
    """The published normalisation of the segment temperatures: scale by C, remove the
    mean, and shrink so that no segment departs from it by more than C."""
    a = C * action
    a = a - a.mean(-1, keepdim=True)
    return a / torch.clamp(a.abs().amax(-1, keepdim=True) / C, min=1.0)


class RayleighPhysics(CavityPhysics):
    """The convection cell heated by bottom segments (one action per segment)."""

    Params = RayleighParams
    state_type = RayleighState
    blowup_reward = -1.0
    diagnostics = {
        "nusselt": "the Nusselt number at the bottom plate (minus the reward)",
        "kinetic_energy": "half the mean squared speed in the cavity",
    }
    scalar = "theta"
    cells_per_unit = CELLS_PER_UNIT
    dt = DT
    substeps = SUBSTEPS
    jacobi_tol = 1e-8
    substep = staticmethod(substep)

    @classmethod
    def sizes(cls, p) -> tuple[int, int]:
        return N_OBS, p.n_sgts  # one temperature per bottom segment

    def scalar_ghosts(self) -> Ghosts:
        # adiabatic sides; the plates' temperatures through the ghost offset
        return Ghosts.cells(self.nx, self.ny, GRADIENT, GRADIENT, VALUE, VALUE, dtype=self.dtype, device=self.device)

    # derived from ra at each use, so that every differentiated step has its own graph
    def nu(self, p):
        return (PR / p.ra) ** 0.5

    def kappa(self, p):
        return 1.0 / (PR * p.ra) ** 0.5

    def _start(self, p) -> Convection:
        # loaded at the first reset: an env started by set_state never develops its roll
        return self.remembered(("convection", p.start, number(p.ra)), lambda: self._developed(p))

    def _developed(self, p) -> Convection:
        if p.start == PUBLISHED:
            start = published_convection(self.nx, self.ny)
        else:
            p = dataclasses.replace(p, ra=number(p.ra))
            key = dict(version=3, L=p.L, H=p.H, ra=p.ra)
            like = map_state(lambda v: v[0], rest_state(1, self.nx, self.ny, torch.float64, "cpu"))
            start = cached("rayleigh-convection", key, lambda: developed_convection(p), like)
        return map_state(lambda v: v.to(device=self.device, dtype=self.dtype), start)

    def initial_state(self, p, generator, mask=None) -> RayleighState:
        flow = Flow(*(f.expand(self.num_envs, *f.shape).clone() for f in self._start(p)))
        bottom = torch.full((self.num_envs, self.nx), T_HOT, dtype=self.dtype, device=self.device)
        return RayleighState(*flow, bottom=bottom, probes=self.probes.start(flow))

    def advance(self, p, state: RayleighState, action: torch.Tensor, count: torch.Tensor, noise: Noise):
        segments = normalise(action)
        bottom = T_HOT + segments.repeat_interleave(self.nx // self.n_actions, dim=-1)
        offset = temperature_offset(bottom, self.ghosts, self.ny)
        flow = self.run(self.flow(state), SUBSTEPS, self.nu(p), self.kappa(p), offset=offset)
        new = RayleighState(*flow, bottom=bottom, probes=self.probes.push(state.probes, flow))
        return new, -nusselt(new.theta, self.dy)

    def diagnose(self, p, state: RayleighState) -> dict[str, torch.Tensor]:
        return {"nusselt": nusselt(state.theta, self.dy), "kinetic_energy": self.kinetic_energy(state)}


class RayleighEnv(CavityEnv):
    """Batched rayleigh-v0 (one continuous action per bottom segment)."""

    env_id = "rayleigh-v0"
    physics_type = RayleighPhysics
    published_speed = 13.8
    speed_target = 20.0
    paper_ppo = -130.0
    gradcheck = GradCheck("ra", 1e4, warmup=0, steps=2)

    def actuation(self, state: RayleighState) -> np.ndarray:
        return (state.bottom.double().numpy()[:: self.nx // self.n_actions] - T_HOT) / C

    def scalar_range(self) -> tuple[float, float]:
        return T_COLD, T_HOT
