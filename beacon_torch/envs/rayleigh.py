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

``sides="periodic"`` makes the cavity a channel of period L (no side walls), the case of
Vignon et al. (2023) with ``**VIGNON``; ``rayleigh-separable-v0`` is that channel with
each segment an agent (TorchRL's multi-agent layout), its own Nusselt number mixed into
its reward.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F

from beacon_torch import seeds
from beacon_torch.cache import cached
from beacon_torch.core.card import PUBLISHED_RESULT, Card, GradCheck, Reference
from beacon_torch.core.state import Noise, map_state
from beacon_torch.envs.cavity import N_OBS, PROBED, CavityPhysics, cavity_frame, grid, transport
from beacon_torch.envs.cavity import substep_adjoint as cavity_adjoint
from beacon_torch.numerics.grid import GRADIENT, NEUMANN, PERIODIC, VALUE, Ghosts, edge_offset
from beacon_torch.numerics.projection import Cavity, Flow
from beacon_torch.numerics.staggered import project
from beacon_torch.params import number, param, resolve_params
from beacon_torch.starts import GENERATED, PUBLISHED, choose_start, published_table, start_param

CELLS_PER_UNIT = 50
DT = 0.01
SUBSTEPS = 200
PR = 0.71
T_HOT, T_COLD = 0.5, -0.5
C = 0.75  # largest temperature fluctuation of a segment
# the developed starts' generation: a new one whenever the scheme changes the flow
START_VERSION = 3
DEVELOP_TIME = 200.0
CHANNEL_DEVELOP_TIME = 400.0  # the uncontrolled run before a periodic channel's episodes
WALLS, CHANNEL = "walls", "periodic"
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


# the parameters that the two layouts declare with their own defaults
def pr_param(default: float):
    return param(default, low=0.01, high=100.0, per_member=False, differentiable=True, doc="Prandtl number")


def sides_param(default: str):
    doc = "the side boundaries: adiabatic no-slip walls (a cavity), or periodic (a channel of period L)"
    return param(default, kind="choice", choices=(WALLS, CHANNEL), doc=doc)


def period_param(default: float):
    doc = f"time between two actions, a multiple of the time step {DT:g}"
    return param(default, low=DT, high=100.0, per_member=False, doc=doc)


def resolution_param(default: int):
    return param(default, low=8, high=200, kind="int", per_member=False, doc="cells per unit length")


@dataclass(frozen=True)
class RayleighParams:
    L: float = param(1.0, low=0.2, high=8.0, per_member=False, doc="length (the period of a channel)")
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
    pr: float = pr_param(PR)
    sides: str = sides_param(WALLS)
    period: float = period_param(DT * SUBSTEPS)
    resolution: int = resolution_param(CELLS_PER_UNIT)
    start: str = start_param("the published stored roll, or the one of developed_convection()")
    solver: str = param(
        "direct",
        kind="choice",
        choices=("direct", "jacobi"),
        doc="pressure increment: direct solve, or the published Jacobi iterations (exact comparisons; eager only)",
    )

    def __post_init__(self):
        choose_start(self, ("L", "H", "ra", "pr", "sides", "resolution"))
        check_layout(self)


def check_layout(p) -> None:
    """The one-line errors of a layout whose segments or action period do not fit the
    grid and the time step."""
    nx = int(round(p.L * p.resolution))
    if p.sides == WALLS and nx % p.n_sgts:
        raise ValueError(f"parameter 'n_sgts' = {p.n_sgts} must divide the {nx} cells along L = {p.L:g}")
    if abs(p.period / DT - round(p.period / DT)) > 1e-9:
        raise ValueError(f"parameter 'period' = {p.period:g} must be a multiple of the time step {DT:g}")
    if p.sides == CHANNEL:
        # the channel's forward-Euler transport is stable up to a diffusion number of 1/2
        dx, dy = p.L / channel_cells(p.L, p.n_sgts, p.resolution), p.H / round(p.H * p.resolution)
        number_ = DT / (number(p.pr) * number(p.ra)) ** 0.5 * (dx**-2 + dy**-2)
        if number_ > 0.5:
            raise ValueError(
                f"parameter 'resolution' = {p.resolution} is too fine for the channel's explicit transport at "
                f"Ra = {number(p.ra):g}, Pr = {number(p.pr):g} (diffusion number {number_:.2f} > 0.5)"
            )


def channel_cells(L: float, n_sgts: int, resolution: int) -> int:
    """The cells along a periodic channel: about ``resolution`` per unit length, rounded
    to a multiple of the segments so that each segment covers whole cells."""
    return n_sgts * max(1, int(round(L * resolution / n_sgts)))


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
    buoyancy = theta[cavity.source_x, 2:-1]
    u, v = cavity.predict(flow, walls, nu, DT, buoyancy)
    u, v, p = project(u, v, flow.p, cavity.solver, DT, cavity.dx, cavity.dy)
    return Flow(u, v, p, transport(theta, u, v, theta_ghosts, theta_offset, cavity, kappa, DT))


def substep_adjoint(start: Flow, end: Flow, grad: Flow, walls, theta_offset, cavity: Cavity, theta_ghosts, nu, kappa):
    """:func:`substep`'s adjoint (:func:`~beacon_torch.envs.cavity.substep_adjoint`,
    where :attr:`Cavity.adjoint`): the gradients of its flow, walls and
    ``theta_offset``."""
    grads, g_buoyancy, g_walls, g_offset = cavity_adjoint(
        start, end, grad, walls, theta_offset, cavity, theta_ghosts, nu, kappa, DT
    )
    # the buoyancy read the cells above the interior v faces
    theta = grads.scalar + F.pad(g_buoyancy, (0, 0, 2, 1, 1, 1))
    return grads._replace(scalar=theta), g_walls, g_offset


def nusselt(theta: torch.Tensor, dy: float) -> torch.Tensor:
    """Instantaneous Nusselt number: the mean over the bottom cells of the first-order
    temperature gradient to the reference plate temperature 1/2, ``[B]``."""
    return ((T_HOT - theta[:, 1:-1, 1]) / (0.5 * dy)).mean(-1)


def rest_state(num_envs: int, nx: int, ny: int, dtype, device) -> Convection:
    zeros = lambda *shape: torch.zeros((num_envs, *shape), dtype=dtype, device=device)
    return Convection(u=zeros(nx + 2, ny + 2), v=zeros(nx + 2, ny + 2), p=zeros(nx, ny), theta=zeros(nx + 2, ny + 2))


def developed_convection(
    p: RayleighParams = RayleighParams(), *, time: float | None = None, seed: int = DEVELOP_SEED
) -> Convection:
    """The published initial state: from rest (theta = 0) ``time`` time units without
    control (default 200 for a cavity, 400 for a channel), in float64, after a
    perturbation of the temperature of amplitude 1e-6 drawn from a generator seeded by
    ``seed`` (the solver is exactly symmetric, so convection would otherwise never
    start). Returns ``u``, ``v``, ``p``, ``theta`` without batch dimension."""
    if time is None:
        time = CHANNEL_DEVELOP_TIME if p.sides == CHANNEL else DEVELOP_TIME
    # the physics of these parameters runs the substeps; its own start is never made
    given = {**dataclasses.asdict(p), "start": "generated"}
    cpu, f64 = torch.device("cpu"), torch.float64
    p = resolve_params(type(p), given, batch_size=1, device=cpu, dtype=f64, env_id="rayleigh-v0")
    physics = RayleighPhysics(p, 1, dtype=f64, device=cpu)
    g = seeds.generator(seed)
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
    substep_adjoint = staticmethod(substep_adjoint)

    @classmethod
    def sizes(cls, p) -> tuple[int, int]:
        return N_OBS, p.n_sgts  # one temperature per bottom segment

    def setup(self, p) -> None:
        self.sides = p.sides
        super().setup(p)
        self.substeps = int(round(p.period / DT))

    def grid(self, p) -> tuple[int, int, float, float]:
        if p.sides == WALLS:
            return grid(p.L, p.H, p.resolution)
        nx, ny = channel_cells(p.L, p.n_sgts, p.resolution), int(round(p.H * p.resolution))
        return nx, ny, p.L / nx, p.H / ny

    def poisson_conditions(self, p):
        return (NEUMANN,) * 4 if p.sides == WALLS else (PERIODIC, PERIODIC, NEUMANN, NEUMANN)

    def scalar_ghosts(self) -> Ghosts:
        # adiabatic sides (or none, in a channel); the plates' temperatures through the
        # ghost offset
        side = GRADIENT if self.sides == WALLS else PERIODIC
        return Ghosts.cells(self.nx, self.ny, side, side, VALUE, VALUE, dtype=self.dtype, device=self.device)

    # derived from ra and pr at each use, so that every differentiated step has its own graph
    def nu(self, p):
        return (p.pr / p.ra) ** 0.5

    def kappa(self, p):
        return 1.0 / (p.pr * p.ra) ** 0.5

    def _start(self, p) -> Convection:
        # loaded at the first reset: an env started by set_state never develops its roll
        if p.start == PUBLISHED:
            start = published_convection(self.nx, self.ny)
            return map_state(lambda v: v.to(device=self.device, dtype=self.dtype), start)
        p = dataclasses.replace(p, ra=number(p.ra), pr=number(p.pr))
        key = dict(L=p.L, H=p.H, ra=p.ra)
        if (p.sides, p.pr, p.resolution) != (WALLS, PR, CELLS_PER_UNIT):  # the shipped cavity's key unchanged
            key.update(sides=p.sides, pr=p.pr, resolution=p.resolution)
            key.update(n_sgts=p.n_sgts if p.sides == CHANNEL else None)
        like = map_state(lambda v: v[0], rest_state(1, self.nx, self.ny, torch.float64, "cpu"))
        # between the walls' temperatures, the ghost cells' reflections of them included
        span = T_HOT - T_COLD
        bounds = {"theta": (T_COLD - span, T_HOT + span)}
        develop = lambda: developed_convection(p)
        where = dict(device=self.device, dtype=self.dtype)
        return cached("rayleigh-convection", START_VERSION, key, develop, like, bounds, **where)

    def state_like(self, p) -> RayleighState:
        flow = Flow(*rest_state(self.num_envs, self.nx, self.ny, self.dtype, self.device))
        return RayleighState(*flow, bottom=flow.p[:, :, 0], probes=self.probes.start(flow))

    def initial_state(self, p, generator, mask=None) -> RayleighState:
        flow = Flow(*(f.expand(self.num_envs, *f.shape).clone() for f in self._start(p)))
        bottom = torch.full((self.num_envs, self.nx), T_HOT, dtype=self.dtype, device=self.device)
        return RayleighState(*flow, bottom=bottom, probes=self.probes.start(flow))

    def heat(self, p, state: RayleighState, action: torch.Tensor) -> RayleighState:
        """The state after one action: the segments at the temperatures of ``action``
        (``[B, n_sgts]``) over the action's substeps."""
        segments = normalise(action)
        bottom = T_HOT + segments.repeat_interleave(self.nx // self.n_actions, dim=-1)
        offset = temperature_offset(bottom, self.ghosts, self.ny)
        flow = self.run(self.flow(state), self.substeps, self.nu(p), self.kappa(p), offset=offset)
        return RayleighState(*flow, bottom=bottom, probes=self.probes.push(state.probes, flow))

    def advance(self, p, state: RayleighState, action: torch.Tensor, count: torch.Tensor, noise: Noise):
        new = self.heat(p, state, action)
        return new, -nusselt(new.theta, self.dy)

    def diagnose(self, p, state: RayleighState) -> dict[str, torch.Tensor]:
        return {"nusselt": nusselt(state.theta, self.dy), "kinetic_energy": self.kinetic_energy(state)}


CARD = Card(
    family="2-D",
    costly=True,  # an action is tens of substeps of a 2-D projection
    published_speed=13.8,
    speed_target=20.0,
    paper_ppo=-130.0,
    gradcheck=GradCheck("ra", 1e4, warmup=0, steps=2),
    frame=cavity_frame(
        "rayleigh",
        lambda physics, state: (state.bottom.double().numpy()[:: physics.nx // physics.n_actions] - T_HOT) / C,
        lambda params, member: (T_COLD, T_HOT),
    ),
)


# Vignon et al. (2023)'s channel: x in [0, 2 pi) periodic, y in [-1, 1], Ra = 1e4 and
# Pr = 0.7 on the half-height, actions every 1.5 time units, 200 a training episode
VIGNON = dict(L=2.0 * math.pi, H=2.0, sides=CHANNEL, pr=0.7, period=1.5)
# BEACON's cavity (rayleigh-v0's geometry) for the same multi-agent layout
BEACON = dict(L=1.0, H=1.0, sides=WALLS, pr=PR, period=DT * SUBSTEPS, resolution=CELLS_PER_UNIT)
VIGNON_RESOLUTION = 32  # cells per unit length (ny = 64 across the channel, as Vignon's 64 modes)
PROBE_ROWS, PROBE_COLUMNS = 8, 3  # probe rows over the height; probe columns per segment


@dataclass(frozen=True)
class RayleighSeparableParams(RayleighParams):
    L: float = param(VIGNON["L"], low=0.2, high=8.0, per_member=False, doc="length (the period of a channel)")
    H: float = param(VIGNON["H"], low=0.2, high=4.0, per_member=False, doc="height between the plates")
    pr: float = pr_param(VIGNON["pr"])
    sides: str = sides_param(CHANNEL)
    period: float = period_param(VIGNON["period"])
    resolution: int = resolution_param(VIGNON_RESOLUTION)
    start: str = param(
        GENERATED, kind="choice", choices=(GENERATED,), doc="the developed flow of developed_convection()"
    )
    window: int = param(
        3,
        low=1,
        high=199,
        kind="int",
        per_member=False,
        doc="segments an agent observes, centred on its own (odd; n_sgts with a channel: the whole flow, recentred)",
    )
    beta: float = param(
        0.0015,
        low=0.0,
        high=1.0,
        per_member=False,
        doc="weight of the agent's own Nusselt number in its reward (the rest: the whole flow's)",
    )

    def __post_init__(self):
        check_layout(self)
        if self.window % 2 == 0 or self.window > self.n_sgts:
            raise ValueError(
                f"parameter 'window' = {self.window} must be odd and at most n_sgts = {self.n_sgts} (segments seen)"
            )


class RayleighSeparablePhysics(RayleighPhysics):
    """The convection with each bottom segment an agent: actions ``[B, n_sgts, 1]``,
    observations ``[B, n_sgts, 3 x 8 rows x 3 columns x window]`` (temperature and the
    two velocities at the probes above the agent's window of segments, its own in the
    middle) and rewards ``[B, n_sgts]``."""

    Params = RayleighSeparableParams
    episode_length = 200
    diagnostics = {
        "nusselt": "the whole flow's Nusselt number, (<v theta> - kappa d<theta>/dy) / (kappa dT / H)",
        "kinetic_energy": "half the mean squared speed in the flow",
    }

    @classmethod
    def sizes(cls, p) -> tuple[int, int]:
        return p.n_sgts * len(PROBED) * PROBE_ROWS * PROBE_COLUMNS * p.window, p.n_sgts

    @property
    def action_shape(self) -> tuple[int, ...]:
        return (self.n_actions, 1)

    def setup(self, p) -> None:
        super().setup(p)
        n, m = self.n_actions, self.nx // self.n_actions
        if m < PROBE_COLUMNS or self.ny < PROBE_ROWS:
            raise ValueError(f"the grid of resolution {p.resolution} is too coarse for the probes of {n} segments")
        columns = [s * m + (2 * c + 1) * m // (2 * PROBE_COLUMNS) for s in range(n) for c in range(PROBE_COLUMNS)]
        rows = [(2 * r + 1) * self.ny // (2 * PROBE_ROWS) for r in range(PROBE_ROWS)]
        self._columns = torch.tensor(columns, device=self.device)
        self._rows = torch.tensor(rows, device=self.device)
        seen = torch.arange(n)[:, None] + torch.arange(p.window)[None, :] - p.window // 2
        # a channel wraps; a cavity's agents near a wall see zeros (segment n) past it
        seen = seen % n if p.sides == CHANNEL else torch.where((seen >= 0) & (seen < n), seen, n)
        self._seen = seen.to(self.device)

    def observe(self, p, state: RayleighState) -> torch.Tensor:
        centre = lambda f: f[:, self._columns][:, :, self._rows]
        theta = state.theta[:, 1:-1, 1:-1]
        u = 0.5 * (state.u[:, 1:-1, 1:-1] + state.u[:, 2:, 1:-1])
        v = 0.5 * (state.v[:, 1:-1, 1:-1] + state.v[:, 1:-1, 2:])
        probes = torch.stack([centre(theta), centre(u), centre(v)], 1)  # [B, 3, n * columns, rows]
        b, n = probes.shape[0], self.n_actions
        probes = F.pad(probes.reshape(b, len(PROBED), n, -1), (0, 0, 0, 1))  # a zero segment n
        return probes[:, :, self._seen].transpose(1, 2).reshape(b, n, -1)

    def column_nusselt(self, p, state: RayleighState) -> torch.Tensor:
        """``[B, nx]``: the Nusselt number of each column of cells, the convective flux
        ``<v theta>`` over the height plus the conduction between the plates' wall
        values, in units of the conduction kappa dT / H."""
        theta = state.theta[:, 1:-1]
        v = 0.5 * (state.v[:, 1:-1, 1:-1] + state.v[:, 1:-1, 2:])
        bottom = 0.5 * (theta[:, :, 0] + theta[:, :, 1])
        top = 0.5 * (theta[:, :, -1] + theta[:, :, -2])
        return (p.H / self.kappa(p) * (v * theta[:, :, 1:-1]).mean(-1) + bottom - top) / (T_HOT - T_COLD)

    def advance(self, p, state: RayleighState, action: torch.Tensor, count: torch.Tensor, noise: Noise):
        new = self.heat(p, state, action[..., 0])
        columns = self.column_nusselt(p, new)
        own = columns.reshape(columns.shape[0], self.n_actions, -1).mean(-1)
        return new, -(p.beta * own + (1.0 - p.beta) * columns.mean(-1, keepdim=True))

    def diagnose(self, p, state: RayleighState) -> dict[str, torch.Tensor]:
        return {"nusselt": self.column_nusselt(p, state).mean(-1), "kinetic_energy": self.kinetic_energy(state)}


# rayleigh-separable-v0: the bottom segments as agents of one convection flow (Vignon
# et al. 2023) in TorchRL's multi-agent layout: each agent observes the probes above
# its window of segments, sets its segment's temperature and is rewarded by minus a mix
# of its own and the whole flow's Nusselt numbers. The default is Vignon's channel;
# ``**BEACON`` gives rayleigh-v0's cavity.
SEPARABLE_CARD = dataclasses.replace(
    CARD,
    test_settings={"period": 0.1},  # ten substeps an action
    published_speed=None,
    speed_target=None,
    paper_ppo=None,
    # the agents' mean reward is minus the flow's Nusselt number, so its reduction is
    # the score's; the share carries over where this grid's level differs from theirs
    reference=Reference(
        PUBLISHED_RESULT,
        "Vignon et al., Phys. Fluids 35 (2023): the multi-agent PPO's Nusselt number 2.0496 against 2.675 "
        "uncontrolled (their plotting script)",
        ratio=2.0496 / 2.675,
    ),
)
