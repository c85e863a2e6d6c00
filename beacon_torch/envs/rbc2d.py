"""rbc2d-easy-v0, rbc2d-medium-v0, rbc2d-hard-v0: FluidGym's two-dimensional
Rayleigh-Benard levels (Becktepe et al. 2026, after Vignon et al. 2023), on the
convection solver of rayleigh-v0.

Boussinesq flow between a hot bottom plate (T = 1) and a cold top one (T = 0), periodic
in x with period L = pi (height H = 1), in free-fall units:

    div u = 0
    u_t + (u.grad) u = -grad p + sqrt(Pr / Ra) lap u + T y
    T_t + u.grad T = lap T / sqrt(Pr Ra)

at Ra = 8e4 / 4e5 / 8e5 and Pr = 0.7. The grid is FluidGym's: 12 heaters of 8 cells
along x (96 cells) and round(2 x 96 / pi) = 61 rows refined towards both plates, each
row 1.02 times as high as its neighbour on the wall's side (:func:`wall_refined`).
The solver is the cavities' staggered projection on those rows: the periodic channel's
explicit predictor with centred fluxes, a direct Poisson solve in the rows' widths and
the explicit centred transport of the temperature, forward Euler at a fixed step per
level (FluidGym's PISO adapts its step to a CFL number of 0.8 or 0.5; an explicit
centred step is bounded by the diffusion of its fluxes first, see the page).

Control: 12 heaters, one action each in [-1, 1]. As FluidGym (Vignon et al.'s eqs. 8-9):
the actions' mean removed, scaled by 0.75 and clipped to +-0.75, added to T = 1, and
each heater's edge cells blended with its neighbour's by a cubic over a tenth of a
heater (:func:`blend_matrix`). An action lasts one time unit; 200 make an episode.

Observation: the temperature, the two velocities and the pressure at 8 x 48 sensors
(rows at the heights (j + 1/2) / 8, four columns per heater at (k + 1/2) L / 48), read
bilinearly from the cells. Reward: ``nu_ref - Nu`` with Nu = 1 + sqrt(Ra Pr) <v T>, the
volume mean, and ``nu_ref`` the reference of FluidGym's reward at the level.

Multi-agent (``rbc2d-*-ma-v0``): each heater an agent; it observes the sensors above
the 11 heaters centred on its own (the channel wraps) and earns 0.2 of its window's
Nusselt reward plus 0.8 of the whole flow's.

Starts: FluidGym's. Ten developed flows (:func:`developed_bank`: the conduction profile
with noise of each one's own seed, 283 time units without control; FluidGym develops ten
domains so for each of its modes) and, at each reset, a member's own copy of one of them
drawn at random, flipped in x with probability 1/2, shifted by a random number of cells,
with noise of 0.05 on the temperature (clipped to [0, 1]) and the velocities, then 1 to
2 time units without control. Training draws from the train bank; the validation and
test start sets (``starts=``) from banks of their own, developed from other seeds, as
FluidGym's modes do. At the medium level some seeds settle into one pair of rolls
instead of two, with a lower Nusselt number: a bank keeps that mix, as FluidGym's
domains do.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from beacon_torch import seeds
from beacon_torch.cache import cached
from beacon_torch.core.card import PUBLISHED_RESULT, Card, GradCheck, Reference
from beacon_torch.core.state import Noise
from beacon_torch.envs.cavity import CavityPhysics, _any_substep, cavity_frame, transport
from beacon_torch.numerics.bodies import probe_stencil
from beacon_torch.numerics.grid import NEUMANN, PERIODIC, VALUE, Ghosts, edge_offset
from beacon_torch.numerics.projection import Cavity, Flow
from beacon_torch.numerics.staggered import Axis, project
from beacon_torch.params import number, param, resolve_params

T_HOT, T_COLD = 1.0, 0.0
HEATER_LIMIT = 0.75  # the largest departure of a heater from T_HOT
BLEND = 0.1  # the share of a heater blended with its neighbour's temperature
HEIGHT = 1.0
Y_SCALE = 2.0  # rows per unit height against columns per unit length
BASE = 1.02  # the rows' height ratio towards the plates
SENSOR_ROWS, SENSORS_PER_HEATER = 8, 4
FIELDS = ("temperature", "u", "v", "pressure")  # the observed fields, in this order
EPISODE_LENGTH = 200
DEVELOP_TIME = 283.0  # FluidGym's initial domain: 283 actions without control
# FluidGym's initial domains: ten developed flows for each of its modes, each mode from
# its own seeds (ours drawn by our generator), so that a policy is judged from developed
# flows it never trained from
BANK_SEEDS = {"train": tuple(range(100, 110)), "validation": tuple(range(200, 210)), "test": tuple(range(300, 310))}
START_VERSION = 2
# FluidGym's randomisation of a start
START_NOISE = 0.05
START_RUN = (1.0, 2.0)  # time units without control, drawn uniformly (the start_run default)
# the conduction start's noise, as FluidGym's initial domain
CONDUCTION_T_NOISE, CONDUCTION_U_NOISE = 0.1, 0.05

# FluidGym's levels: Rayleigh number, its reward's reference Nusselt number (the median
# of its uncontrolled statistics; its results table gives it as reward + Nusselt number,
# alike in every row), and this solver's time step
LEVELS = {
    "easy": dict(ra=8e4, nu_ref=4.896, dt=0.01),
    "medium": dict(ra=4e5, nu_ref=6.429, dt=0.005),
    "hard": dict(ra=8e5, nu_ref=7.243, dt=0.004),
}
# the uncontrolled Nusselt numbers of FluidGym's table (its "Baseflow" rows: the mean
# over its test episodes)
FLUIDGYM_NUSSELT = {"easy": 4.841, "medium": 6.856, "hard": 7.854}
# the lowest controlled Nusselt number of FluidGym's table at each level, and whose
FLUIDGYM_BEST = {"easy": (3.872, "MA-PPO"), "medium": (5.639, "SAC"), "hard": (6.717, "SAC")}


class Rbc2dState(NamedTuple):
    """The flow (:class:`~beacon_torch.numerics.projection.Flow`'s fields, batch first,
    ghosted as the cavities') and the bottom plate's temperature of the last action."""

    u: torch.Tensor  # [batch, nx + 2, ny + 2]
    v: torch.Tensor  # [batch, nx + 2, ny + 2]
    p: torch.Tensor  # [batch, nx, ny]
    theta: torch.Tensor  # [batch, nx + 2, ny + 2] the temperature
    bottom: torch.Tensor  # [batch, nx]


@dataclass(frozen=True)
class Rbc2dParams:
    ra: float = param(8e4, low=1e3, high=1e7, per_member=False, differentiable=True, doc="Rayleigh number")
    pr: float = param(0.7, low=0.1, high=10.0, per_member=False, differentiable=True, doc="Prandtl number")
    heaters: int = param(12, low=2, high=48, kind="int", per_member=False, doc="heaters on the bottom plate (actions)")
    heater_cells: int = param(
        8, low=4, high=32, kind="int", per_member=False, doc="cells along x per heater (8: FluidGym's grid)"
    )
    aspect: float = param(1.0, low=0.25, high=4.0, per_member=False, doc="the period L in multiples of pi (H = 1)")
    base: float = param(BASE, low=1.0, high=1.1, per_member=False, doc="height ratio of neighbouring rows")
    dt: float = param(0.01, low=1e-4, high=0.05, per_member=False, doc="time step")
    period: float = param(1.0, low=1e-4, high=10.0, per_member=False, doc="time between two actions")
    start_run: float = param(
        START_RUN[0],
        low=0.0,
        high=10.0,
        per_member=False,
        doc="a start runs uncontrolled for between this and twice this time after its randomisation (FluidGym: 1)",
    )
    nu_ref: float = param(4.896, low=0.0, high=100.0, per_member=False, doc="the reward's reference Nusselt number")
    local_weight: float = param(
        0.2, low=0.0, high=1.0, per_member=False, doc="multi-agent: the share of an agent's own window in its reward"
    )
    window: int = param(
        11, low=1, high=47, kind="int", per_member=False, doc="multi-agent: heaters an agent sees (odd)"
    )
    domains: str = param(
        "train",
        kind="choice",
        choices=tuple(BANK_SEEDS),
        doc="the bank of developed flows a start is drawn from (FluidGym's train, validation and test domains; "
        "a start set draws from its own)",
    )

    def __post_init__(self):
        if abs(self.period / self.dt - round(self.period / self.dt)) > 1e-9:
            raise ValueError(f"parameter 'period' = {self.period:g} must be a multiple of the time step {self.dt:g}")
        if self.window % 2 == 0 or self.window > self.heaters:
            raise ValueError(
                f"parameter 'window' = {self.window} must be odd and at most heaters = {self.heaters} (heaters seen)"
            )


def wall_refined(n: int, base: float) -> torch.Tensor:
    """The heights of ``n`` rows across a unit height, refined towards both walls as
    FluidGym's grids: row k's height is ``base ** e_k`` with exponents rising from 0
    at each wall to the middle (``0, 1, ..., n // 2 - 1``, then down from ``n // 2``),
    scaled to sum to one. float64."""
    exponents = list(range(n))
    exponents = exponents[: n // 2] + exponents[::-1][n // 2 :]
    heights = base ** torch.tensor(exponents, dtype=torch.float64)
    return heights / heights.sum()


def blend_matrix(heaters: int, cells: int) -> torch.Tensor:
    """``[heaters * cells, heaters]``: each cell's weights on the heaters' temperatures,
    FluidGym's smoothing: a cubic blend ``s = t^2 (3 - 2 t)`` with the left neighbour
    over the first ``round(cells / 10)`` cells of a heater (its first cell half and
    half) and, by its shifted mirror, with the right neighbour at the heater's end."""
    nx = heaters * cells
    width = round(cells * BLEND)
    m = np.zeros((nx, heaters))
    column = np.arange(nx)
    own, pos = column // cells, column % cells
    m[column, own] = 1.0
    if width == 0:
        return torch.from_numpy(m)
    t_left = np.clip(pos / width + 0.5, 0.0, 1.0)
    t_right = 1.0 - np.roll(t_left, cells - width + 1)
    s = lambda t: t * t * (3.0 - 2.0 * t)
    for zone, t, other, own_share in (
        (pos < width, t_left, (own - 1) % heaters, lambda t: s(t)),
        ((pos >= cells - width) & ~(pos < width), t_right, (own + 1) % heaters, lambda t: 1.0 - s(t)),
    ):
        c = column[zone]
        m[c, own[zone]] = own_share(t[zone])
        m[c, other[zone]] += 1.0 - own_share(t[zone])
    return torch.from_numpy(m)


def heater_temperatures(action: torch.Tensor, blend: torch.Tensor) -> torch.Tensor:
    """The bottom plate's temperature of each cell, ``[B, nx]``, from the actions
    ``[B, heaters]``: their mean removed, scaled and clipped to the heater limit, and
    blended across the heaters' edges (``blend`` from :func:`blend_matrix`)."""
    shifted = action - action.mean(-1, keepdim=True)
    departure = shifted / (shifted.abs().clamp(min=1.0) / HEATER_LIMIT)
    return T_HOT + departure @ blend.T


def substep(flow: Flow, walls, theta_offset: torch.Tensor, cavity: Cavity, theta_ghosts: Ghosts, nu, kappa, *, dt):
    """One projection substep of the Boussinesq flow on the solver's batch-last flow,
    the buoyancy of each interior v face the temperature interpolated to it."""
    theta = flow.scalar
    low, high = theta[:, 1:-2], theta[:, 2:-1]  # the cells below and above each face
    buoyancy = low + cavity.up_share * (high - low)
    u, v = cavity.predict(flow, walls, nu, dt, buoyancy)
    u, v, p = project(u, v, flow.p, cavity.solver, dt, cavity.dx, cavity.dy)
    return Flow(u, v, p, transport(theta, u, v, theta_ghosts, theta_offset, cavity, kappa, dt))


class Rbc2dPhysics(CavityPhysics):
    """FluidGym's RBC2D: the heated channel with one action per heater."""

    Params = Rbc2dParams
    state_type = Rbc2dState
    episode_length = EPISODE_LENGTH
    deterministic = False  # every episode starts from its own randomised copy of the flow
    blowup_reward = -1.0
    diagnostics = {
        "nusselt": "the Nusselt number 1 + sqrt(Ra Pr) <v T> (minus the reward, less nu_ref)",
        "kinetic_energy": "half the mean squared speed in the flow",
        "cfl": "the largest |u| dt / dx + |v| dt / dy of the last state",
    }
    scalar = "theta"

    @classmethod
    def sizes(cls, p) -> tuple[int, int]:
        return len(FIELDS) * SENSOR_ROWS * SENSORS_PER_HEATER * p.heaters, p.heaters

    def setup(self, p) -> None:
        self.nx = p.heaters * p.heater_cells
        self.L = p.aspect * math.pi
        self.ny = round(Y_SCALE * self.nx / self.L)
        self.dx = self.L / self.nx
        self.axis = Axis.of_widths(HEIGHT * wall_refined(self.ny, p.base))
        bc = (PERIODIC, PERIODIC, NEUMANN, NEUMANN)
        self.cavity = Cavity(self.nx, self.ny, self.dx, self.axis, bc, dtype=self.dtype, device=self.device)
        self.dy = self.cavity.dy
        w = self.axis.widths
        # linear interpolation to a face from the cells below and above it
        self.cavity.up_share = (w[:-1] / (w[:-1] + w[1:])).to(dtype=self.dtype, device=self.device)[None, :, None]
        self.solver = self.cavity.solver
        self.ghosts = Ghosts.cells(
            self.nx, self.ny, PERIODIC, PERIODIC, VALUE, VALUE, dtype=self.dtype, device=self.device
        )
        self.dt = p.dt
        self.substeps = int(round(p.period / p.dt))
        self._substeps = self.kernels.loop(functools.partial(_any_substep, functools.partial(substep, dt=p.dt)))
        self.blend = blend_matrix(p.heaters, p.heater_cells).to(dtype=self.dtype, device=self.device)
        cast = lambda t: t.to(dtype=self.dtype, device=self.device)
        self.volume = cast(w / w.sum())[None, None, :]  # each row's share of the height
        self._row_height = cast(w)[None, None, :]
        # the sensors, bilinear in the cell centres
        columns = p.heaters * SENSORS_PER_HEATER
        xs = (np.arange(columns) + 0.5) * self.L / columns
        ys = (np.arange(SENSOR_ROWS) + 0.5) * HEIGHT / SENSOR_ROWS
        points = np.stack(np.meshgrid(xs, ys, indexing="xy"), -1).reshape(-1, 2)  # row by row
        x_centres = (torch.arange(self.nx, dtype=torch.float64) + 0.5) * self.dx
        (ix, iy), weight = probe_stencil(points, x_centres, self.axis.centres)
        self._sensor = (ix.to(self.device), iy.to(self.device), cast(weight))
        # an agent's window of heaters, centred on its own
        seen = (torch.arange(p.heaters)[:, None] + torch.arange(p.window)[None, :] - p.window // 2) % p.heaters
        self._seen = seen.to(self.device)

    def member_floats(self) -> int:
        return 5 * (self.nx + 2) * (self.ny + 2)

    # derived from ra and pr at each use, so that every differentiated step has its own graph
    def nu(self, p):
        return (p.pr / p.ra) ** 0.5

    def kappa(self, p):
        return 1.0 / (p.pr * p.ra) ** 0.5

    def offset(self, bottom: torch.Tensor) -> torch.Tensor:
        """The temperature's ghost offset of the bottom cells' plate temperatures
        ``bottom`` (``[B, nx]``) and the cold top plate, ``[nx + 2, ny + 2, B]``."""
        low = bottom.T[self.ghosts.ix][:, None]
        return edge_offset(self.ny + 2, 1, low, T_COLD, bottom)

    def _start(self, p) -> Flow:
        p = dataclasses.replace(p, ra=number(p.ra), pr=number(p.pr))
        key = start_key(p)
        like = rest_state(len(BANK_SEEDS[p.domains]), self.nx, self.ny, torch.float64, "cpu")
        span = T_HOT - T_COLD
        bounds = {"scalar": (T_COLD - span, T_HOT + span)}
        # compiled where the env is: minutes of substeps
        develop = lambda: developed_bank(p, compile=self.kernels.compiled)
        return cached(
            "rbc2d-developed", START_VERSION, key, develop, like, bounds, device=self.device, dtype=self.dtype
        )

    def state_like(self, p) -> Rbc2dState:
        flow = rest_state(self.num_envs, self.nx, self.ny, self.dtype, self.device)
        return Rbc2dState(*flow, bottom=flow.p[:, :, 0])

    def initial_state(self, p, generator, mask=None) -> Rbc2dState:
        b, nx = self.num_envs, self.nx
        bank = self._start(p)
        pick = torch.randint(bank.u.shape[0], (b,), generator=generator).to(self.device)
        flow = Flow(*(f[pick] for f in bank))
        bottom = torch.full((b, nx), T_HOT, dtype=self.dtype, device=self.device)
        offset = self.offset(bottom)
        s = self.cavity.to_solver(flow, self.ghosts, offset)
        draw = lambda *shape: torch.rand(shape, generator=generator, dtype=torch.float64).to(self.device)
        flip = draw(b) > 0.5
        shift = (draw(b) * nx).long().clamp(max=nx - 1)
        run = p.start_run * (1.0 + draw(b)) / p.dt
        # in x, cells and the periodic faces (face nx is face 0) flipped and shifted
        cells = torch.arange(nx, device=self.device)[:, None]
        source = torch.where(flip, nx - 1 - cells, cells)  # [nx, B]
        source = (source - shift) % nx
        face_source = torch.where(flip, (nx - cells) % nx, cells)
        face_source = (face_source - shift) % nx
        gather = lambda f, index: torch.take_along_dim(f, index[:, None, :], 0)
        sign = torch.where(flip, -1.0, 1.0).to(self.dtype)
        u = gather(s.u[:nx], face_source) * sign
        v, p_, theta = gather(s.v, source), gather(s.p, source), gather(s.scalar[1:-1, 1:-1], source)
        normal = lambda f: torch.randn(f.shape, generator=generator, dtype=torch.float64).to(self.device, self.dtype)
        theta = (theta + START_NOISE * normal(theta)).clamp(T_COLD, T_HOT)
        u = u + START_NOISE * normal(u)
        v = v + START_NOISE * normal(v)
        v[:, 0], v[:, -1] = 0.0, 0.0  # the plates stay impermeable
        s = Flow(torch.cat((u, u[:1])), v, p_, self.ghosts(theta, offset))
        # each member run for its own time: kept where its count is reached
        steps = run.floor().long()
        kept = s
        nu, kappa = self.nu(p), self.kappa(p)
        for i in range(1, int(steps.max()) + 1):
            s = self._substeps(1, s, None, offset, self.cavity, self.ghosts, nu, kappa)
            done = (steps == i).to(self.dtype)
            kept = Flow(*(k + done * (f - k) for k, f in zip(kept, s, strict=True)))
        flow = self.cavity.to_state(kept, self.cavity.walls(like=kept.u))
        return Rbc2dState(*flow, bottom=bottom)

    def heat(self, p, state: Rbc2dState, action: torch.Tensor) -> Rbc2dState:
        """The state after one action: the heaters at the temperatures of ``action``
        (``[B, heaters]``) over the action's substeps."""
        bottom = heater_temperatures(action, self.blend)
        flow = self.run(self.flow(state), self.substeps, self.nu(p), self.kappa(p), offset=self.offset(bottom))
        return Rbc2dState(*flow, bottom=bottom)

    def column_flux(self, p, state: Rbc2dState) -> torch.Tensor:
        """``[B, nx]``: each column's height mean of ``v T`` at the cell centres."""
        theta = state.theta[:, 1:-1, 1:-1]
        v = 0.5 * (state.v[:, 1:-1, 1:-1] + state.v[:, 1:-1, 2:])
        return (v * theta * self.volume).sum(-1)

    def nusselt(self, p, state: Rbc2dState) -> torch.Tensor:
        return 1.0 + self.column_flux(p, state).mean(-1) / self.kappa(p)

    def advance(self, p, state: Rbc2dState, action: torch.Tensor, count: torch.Tensor, noise: Noise):
        new = self.heat(p, state, action)
        return new, p.nu_ref - self.nusselt(p, new)

    def cfl(self, p, state: Rbc2dState) -> torch.Tensor:
        u = state.u[:, 1:, 1:-1].abs()
        v = state.v[:, 1:-1, 1:].abs()
        return (0.5 * (u[:, 1:] + u[:, :-1]) / self.dx + 0.5 * (v[:, :, 1:] + v[:, :, :-1]) / self._row_height).amax(
            (-2, -1)
        ) * p.dt

    def out_of_bounds(self, p, state: Rbc2dState) -> torch.Tensor:
        theta = state.theta[:, 1:-1, 1:-1]
        hot = T_HOT + HEATER_LIMIT
        outside = (theta.amin((-2, -1)) < T_COLD - 0.5) | (theta.amax((-2, -1)) > hot + 0.5)
        return outside | (self.cfl(p, state) > 1.0)

    def diagnose(self, p, state: Rbc2dState) -> dict[str, torch.Tensor]:
        return {
            "nusselt": self.nusselt(p, state),
            "kinetic_energy": self.kinetic_energy(state),
            "cfl": self.cfl(p, state),
        }

    def sensors(self, state: Rbc2dState) -> torch.Tensor:
        """``[B, 4, SENSOR_ROWS, columns]``: the observed fields at the sensors."""
        theta = state.theta[:, 1:-1, 1:-1]
        u = 0.5 * (state.u[:, 1:-1, 1:-1] + state.u[:, 2:, 1:-1])
        v = 0.5 * (state.v[:, 1:-1, 1:-1] + state.v[:, 1:-1, 2:])
        fields = torch.stack((theta, u, v, state.p), 1)  # [B, 4, nx, ny]
        ix, iy, w = self._sensor
        values = (fields[:, :, ix, iy] * w).sum(-1)  # [B, 4, points]
        return values.reshape(*values.shape[:2], SENSOR_ROWS, -1)

    def observe(self, p, state: Rbc2dState) -> torch.Tensor:
        return self.sensors(state).flatten(1)


def rest_state(num_envs: int, nx: int, ny: int, dtype, device) -> Flow:
    zeros = lambda *shape: torch.zeros((num_envs, *shape), dtype=dtype, device=device)
    return Flow(u=zeros(nx + 2, ny + 2), v=zeros(nx + 2, ny + 2), p=zeros(nx, ny), scalar=zeros(nx + 2, ny + 2))


def start_key(p: Rbc2dParams) -> dict:
    """What the developed start depends on: the parameters of its file's name."""
    return dict(
        ra=p.ra,
        pr=p.pr,
        heaters=p.heaters,
        heater_cells=p.heater_cells,
        aspect=p.aspect,
        base=p.base,
        dt=p.dt,
        domains=p.domains,
    )


def developed_bank(
    p: Rbc2dParams = Rbc2dParams(), *, time: float = DEVELOP_TIME, seeds=None, compile: bool = False
) -> Flow:
    """FluidGym's initial domains, one per seed of ``seeds`` (None: the seeds of the
    bank ``p.domains``): :func:`develop` in float64,
    kept in float32 (``[len(seeds), ...]``, ghosted as a state; a start is randomised
    before use). ``compile`` runs the substeps compiled."""
    given = {**dataclasses.asdict(p)}
    seeds = BANK_SEEDS[p.domains] if seeds is None else seeds
    cpu, f64 = torch.device("cpu"), torch.float64
    p = resolve_params(Rbc2dParams, given, batch_size=len(seeds), device=cpu, dtype=f64, env_id="rbc2d-easy-v0")
    physics = Rbc2dPhysics(p, len(seeds), dtype=f64, device=cpu)
    if compile:
        physics.kernels.compile()
    return Flow(*(f.float() for f in develop(physics, p, seeds, time)))


def develop(physics: Rbc2dPhysics, p, seeds, time: float = DEVELOP_TIME) -> Flow:
    """The flows from :func:`conduction` of each seed of ``seeds`` (side by side, a
    member each) after ``time`` time units without control, a time unit a call."""
    flow = Flow(*(torch.cat(parts) for parts in zip(*(conduction(physics, s) for s in seeds), strict=True)))
    per_unit = int(round(1.0 / p.dt))
    for _ in range(int(round(time))):
        flow = uncontrolled(physics, p, flow, per_unit)
    return flow


def conduction(physics: Rbc2dPhysics, seed: int) -> Flow:
    """The conduction profile (linear from the hot to the cold plate) with normal noise
    of 0.1 clipped to the plates' range, and velocities of normal noise 0.05, drawn from
    a generator seeded by ``seed``: one member's batch-first flow, in the physics'
    dtype."""
    nx, ny, f64 = physics.nx, physics.ny, torch.float64
    g = seeds.generator(seed)
    conduction = (T_HOT + (T_COLD - T_HOT) * physics.axis.centres)[None, :].expand(nx, ny)
    theta = (conduction + CONDUCTION_T_NOISE * torch.randn((nx, ny), generator=g, dtype=f64)).clamp(T_COLD, T_HOT)
    u = CONDUCTION_U_NOISE * torch.randn((nx, ny), generator=g, dtype=f64)
    v = CONDUCTION_U_NOISE * torch.randn((nx, ny + 1), generator=g, dtype=f64)
    v[:, 0], v[:, -1] = 0.0, 0.0
    flow = rest_state(1, nx, ny, f64, "cpu")
    flow.u[0, 1:-1, 1:-1], flow.u[0, -1, 1:-1] = u, u[0]  # face nx is face 0
    flow.v[0, 1:-1, 1:] = v
    flow.scalar[0, 1:-1, 1:-1] = theta
    return Flow(*(f.to(dtype=physics.dtype, device=physics.device) for f in flow))


def uncontrolled(physics: Rbc2dPhysics, p, flow: Flow, n: int) -> Flow:
    """``n`` substeps of a batch-first flow with the bottom plate at T_HOT."""
    bottom = torch.full((flow.u.shape[0], physics.nx), T_HOT, dtype=physics.dtype, device=physics.device)
    return physics.run(flow, n, physics.nu(p), physics.kappa(p), offset=physics.offset(bottom))


class Rbc2dSeparablePhysics(Rbc2dPhysics):
    """The same flow with each heater an agent: actions ``[B, heaters, 1]``, observations
    ``[B, heaters, 4 x 8 rows x 4 columns x window]`` (the sensors above the agent's
    window of heaters, its own in the middle) and rewards ``[B, heaters]``."""

    @classmethod
    def sizes(cls, p) -> tuple[int, int]:
        return p.heaters * len(FIELDS) * SENSOR_ROWS * SENSORS_PER_HEATER * p.window, p.heaters

    @property
    def action_shape(self) -> tuple[int, ...]:
        return (self.n_actions, 1)

    def observe(self, p, state: Rbc2dState) -> torch.Tensor:
        values = self.sensors(state)  # [B, 4, rows, heaters * per heater]
        b, n = values.shape[0], self.n_actions
        per_heater = values.reshape(b, len(FIELDS), SENSOR_ROWS, n, SENSORS_PER_HEATER)
        windows = per_heater[:, :, :, self._seen]  # [B, 4, rows, n, window, per heater]
        return windows.permute(0, 3, 1, 2, 4, 5).reshape(b, n, -1)

    def advance(self, p, state: Rbc2dState, action: torch.Tensor, count: torch.Tensor, noise: Noise):
        new = self.heat(p, state, action[..., 0])
        flux = self.column_flux(p, new)
        heaters = flux.reshape(flux.shape[0], self.n_actions, -1).mean(-1)  # [B, heaters]
        local = 1.0 + heaters[:, self._seen].mean(-1) / self.kappa(p)
        whole = 1.0 + flux.mean(-1, keepdim=True) / self.kappa(p)
        return new, p.local_weight * (p.nu_ref - local) + (1.0 - p.local_weight) * (p.nu_ref - whole)


CARD = Card(
    family="2-D",
    costly=True,  # an action is a hundred or more substeps of a 2-D projection
    gradcheck=GradCheck("ra", 8e4, warmup=0, steps=2, params={"period": 0.02, "start_run": 0.02}),
    test_settings={"period": 0.02, "start_run": 0.02},  # two substeps an action, two to four a start
    frame=cavity_frame(
        "rbc2d",
        lambda physics, state: (
            (state.bottom.double().numpy()[:: physics.nx // physics.n_actions] - T_HOT) / HEATER_LIMIT
        ),
        lambda params, member: (T_COLD, T_HOT + HEATER_LIMIT),
        size=lambda physics, params: (physics.L, HEIGHT),
    ),
)


def level_card(level: str) -> Card:
    """The card of a level: the easy level's, with FluidGym's best result at the level
    as its normalised scores' "= 1". A score is EPISODE_LENGTH x nu_ref less the summed
    Nusselt numbers, so FluidGym's fall of the Nusselt number carries over as a share of
    no control's from the same starts (on its grid their uncontrolled level differs a
    little from ours: the page's validation)."""
    best, algorithm = FLUIDGYM_BEST[level]
    reference = Reference(
        PUBLISHED_RESULT,
        f"FluidGym's results table (Becktepe et al. 2026): {algorithm}'s Nusselt number {best} against "
        f"{FLUIDGYM_NUSSELT[level]} uncontrolled, the lowest of its four algorithms at the {level} level",
        ratio=best / FLUIDGYM_NUSSELT[level],
        origin=EPISODE_LENGTH * LEVELS[level]["nu_ref"],
    )
    return dataclasses.replace(CARD, reference=reference)
