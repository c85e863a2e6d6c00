"""The flow of cylinder-v0: the stretched staggered channel, the immersed cylinder
with its jets, one time step and the developed shedding every episode starts from
(the case and its numerics: :mod:`beacon_torch.envs.cylinder`)."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

from beacon_torch.base import map_state
from beacon_torch.numerics import bodies
from beacon_torch.numerics.bodies import Axis, Circle, ImmersedBoundary, probe_stencil, stable
from beacon_torch.numerics.grid import NEUMANN, VALUE, ZERO_FACE, Ghosts
from beacon_torch.numerics.poisson import PoissonSolver
from beacon_torch.numerics.staggered import Stretched, divergence, tendency

LENGTH, HEIGHT = 2.2, 0.41

CENTRE = (0.2, 0.2)
DIAMETER = 0.1
RADIUS = 0.5 * DIAMETER
CYLINDER = Circle(*CENTRE, RADIUS)
NU = 1e-3
U_MAX = 1.5  # the inflow's centre-line velocity; its mean is 1
U_MEAN = 1.0
DT = 5e-4
SUBSTEPS = 50
EPISODE_LENGTH = 80
Q_MAX = 1e-2  # the largest jet flow rate
SMOOTHING = 0.1  # each step the jets' rates move this fraction of the way to the action
JET_WIDTH = math.radians(10.0)
DRAG_OFFSET = 0.159
PUBLISHED_REDUCTION = 0.08  # of the mean drag, by Rabault et al.'s PPO
LIFT_PENALTY = 0.2
DEVELOP_TIME = 8.0  # from rest, long enough for the shedding to be periodic
# the developed starts' generation: a new one whenever the scheme changes the flow
START_VERSION = 3
# the box of uniform cells around the cylinder and its near wake (the probes' region),
# mirror-symmetric across the channel; outside, cells grow by GROWTH up to WIDEST cells
FINE_X = (0.12, 0.5)
FINE_Y = (0.12, 0.29)
GROWTH = 1.05
WIDEST = 8.0

# The published probes, relative to the cylinder's centre: a 9 x 7 grid in the wake, a
# 4 x 4 grid around the cylinder without its middle rows, two rings of 36.
PROBES = np.array(
    [(x, y) for x in (0.075, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45) for y in np.arange(-3, 4) * 0.05]
    + [(x, y) for x in (-0.025, 0.0, 0.025, 0.05) for y in (-0.15, -0.1, 0.1, 0.15)]
    + [
        (r * math.cos(math.radians(a)), r * math.sin(math.radians(a)))
        for r in (RADIUS + 0.02, RADIUS + 0.05)
        for a in range(0, 360, 10)
    ]
)
N_PROBES = len(PROBES)  # 151


class Flow(NamedTuple):
    """The channel's flow on the staggered grid, batch first as a state holds it (its
    first six fields): the face velocities (the inflow face and the outlet face
    included), the cells' pressure, the explicit terms of the previous step on the
    interior faces (Adams-Bashforth's memory) and the top jet's flow rate. The steps
    carry it batch last (``[X, Y, B]``, the rate ``[B]``)."""

    u: torch.Tensor  # [batch, nx + 1, ny]
    v: torch.Tensor  # [batch, nx, ny + 1]
    p: torch.Tensor  # [batch, nx, ny]
    hu: torch.Tensor  # [batch, nx, ny] on the x-faces 1..nx (the outlet's transport last)
    hv: torch.Tensor  # [batch, nx, ny - 1]
    q: torch.Tensor  # [batch]


def _resolution(value: int) -> None:
    if value % 10:
        raise ValueError(
            f"parameter 'cells_per_diameter' = {value} must be a multiple of 10 (the fine box fits whole cells)"
        )


class Channel:
    """The stretched grid of the channel and the immersed cylinder: cells of size
    ``h = D / cells_per_diameter`` in a box around the cylinder and its near wake,
    growing by 5 % a cell outside it up to 8 h; the inflow, the body's forcing of each
    velocity component and its cells, the jets' stream, the ghost maps, the pressure
    solver and the probes.
    Fields are batch-last inside the steps (``[X, Y, B]``), as in the cavities'
    solver."""

    def __init__(self, cells_per_diameter: int, *, dtype, device) -> None:
        _resolution(cells_per_diameter)
        self.h = h = DIAMETER / cells_per_diameter
        self.x = Axis(LENGTH, *FINE_X, h, GROWTH, WIDEST * h)
        self.y = Axis(HEIGHT, *FINE_Y, h, GROWTH, WIDEST * h)
        self.nx, self.ny = nx, ny = self.x.n, self.y.n
        # copies: a compiled loop takes no two inputs that share memory
        cast = lambda t: t.to(dtype=dtype, device=device, copy=True)
        # spacings, shaped to broadcast against [X, Y, B]
        along, across = (lambda t: cast(t)[:, None, None]), (lambda t: cast(t)[None, :, None])
        self.dx_cells, self.dy_cells = along(self.x.widths), across(self.y.widths)
        self.dx_gaps, self.dy_gaps = along(self.x.gaps), across(self.y.gaps)
        # the x-gradient's distances on the faces 1..nx (the outlet's mirrored ghost last)
        self.dx_grad = along(self.x.gaps[1:])
        # the axes as the shared staggered operators take them
        self.x_spacing, self.y_spacing = (
            Stretched(self.dx_cells, self.dx_gaps, 0),
            Stretched(self.dy_cells, self.dy_gaps, 1),
        )
        x_faces, x_cells, y_faces, y_cells = self.x.faces, self.x.centres, self.y.faces, self.y.centres
        self.inflow = cast(4.0 * U_MAX * y_cells * (HEIGHT - y_cells) / HEIGHT**2)[:, None]  # [ny, 1]
        # the body: the faces inside it and the first fluid faces around it, per component
        solid_v = inside(x_cells[:, None], y_faces[None, :])
        # the jets' vertical stream through the body per unit flow rate, on the v faces
        stream = jet_profile(x_cells, h)[:, None] * solid_v
        body = (CYLINDER,)
        self.body_u = ImmersedBoundary(x_faces, y_cells, 0, body, jet_wall, torch.zeros(nx + 1, ny, 1), h)
        self.body_v = ImmersedBoundary(x_cells, y_faces, 1, body, jet_wall, stream[..., None], h)
        self.body_u.to(dtype=dtype, device=device)
        self.body_v.to(dtype=dtype, device=device)
        # the momentum the body's faces hold per unit flow rate
        self.jet_momentum = float(stream.sum()) * h * h
        # cells whose centre lies in the body: they need not conserve mass one by one
        # (their faces are forced), only each half of the body together, so that the
        # jets' stream carries its rate from the bottom jet to the top one
        body_cells = inside(x_cells[:, None], y_cells[None, :])
        self.fluid_cells = cast(1.0 - body_cells)[..., None]
        upper = (y_cells > CENTRE[1]).double()[None, :]
        halves = torch.stack((body_cells * upper, body_cells * (1.0 - upper)), -1)  # [nx, ny, 2]
        self.halves = cast(halves)
        self.half_share = cast(halves / halves.sum((0, 1)))
        # cells with a free face: the pressure of the others acts on forced faces only
        # (each step overwrites them), so it is not carried from step to step
        free_u, free_v = self.body_u.free.reshape(nx + 1, ny), self.body_v.free.reshape(nx, ny + 1)
        enclosed = (1 - free_u[1:]) * (1 - free_u[:-1]) * (1 - free_v[:, 1:]) * (1 - free_v[:, :-1])
        self.live = cast(1.0 - enclosed)[..., None]
        # impermeable, no-slip walls below and above; v = 0 at the inflow, carried out
        self.u_ghosts = Ghosts(None, [1.0] * (nx + 1), *Ghosts._cell_axis(ny, VALUE, VALUE), dtype=dtype, device=device)
        v_x = Ghosts._cell_axis(nx, VALUE, 1.0)
        self.v_ghosts = Ghosts(*v_x, None, [0.0, *[1.0] * (ny - 1), 0.0], dtype=dtype, device=device)
        # solved across the channel first (a mirror-symmetric grid: the folded basis),
        # then along it: the fields are transposed for the solve
        self.solver = PoissonSolver.stretched(
            self.y.laplacian(NEUMANN, NEUMANN),
            self.y.widths,
            self.x.laplacian(NEUMANN, ZERO_FACE),
            self.x.widths,
            dtype=dtype,
            device=device,
        )
        self.probe_index, self.probe_weight = probe_stencil(PROBES + np.array(CENTRE), x_cells, y_cells)
        self.probe_index = tuple(i.to(device) for i in self.probe_index)
        self.probe_weight = cast(self.probe_weight)

    def pressure_probes(self, p: torch.Tensor) -> torch.Tensor:
        """The pressure ``[B, nx, ny]`` at the probes, ``[B, N_PROBES]``."""
        ix, iy = self.probe_index
        return (p[:, ix, iy] * self.probe_weight).sum(-1)

    def x_gradient(self, f: torch.Tensor) -> torch.Tensor:
        """d/dx of a cell field on the x-faces 1..nx, zero on the outlet face."""
        ext = torch.cat((f, -f[-1:]), 0)
        return (ext[1:] - ext[:-1]) / self.dx_grad

    def y_gradient(self, f: torch.Tensor) -> torch.Tensor:
        """d/dy of a cell field on the interior y-faces 1..ny-1."""
        return (f[:, 1:] - f[:, :-1]) / self.dy_gaps[:, 1:-1]

    def divergence(self, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return divergence(u, v, self.dx_cells, self.dy_cells)

    def continuity(self, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """The divergence the projection removes: all of it in the fluid's cells; in the
        body's cells, each half's mean only, so that the faces around the body keep the
        values the forcing gave them while each half of the body passes on exactly
        what its jet's stream brings (no fluid made or lost, the jets' rates exact)."""
        div = self.divergence(u, v)
        total = torch.einsum("xyb,xyh->hb", div, self.halves)  # [2, B]
        return div * self.fluid_cells + torch.einsum("xyh,hb->xyb", self.half_share, total)

    def solve(self, rhs: torch.Tensor) -> torch.Tensor:
        """phi with lap phi = rhs in the cells: zero normal gradient on the walls and
        the inflow, zero on the outlet face."""
        return self.solver.solve(rhs.transpose(0, 1).contiguous()).transpose(0, 1)


def inside(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """1.0 where the point ``(x, y)`` lies inside the cylinder, else 0.0."""
    return bodies.inside((CYLINDER,), x, y)


def jet_profile(x_cells: torch.Tensor, h: float, points: int = 64) -> torch.Tensor:
    """The vertical velocity of the jets' stream per unit flow rate at the cells' x
    (``[nx]``): the published cosine of the polar angle across the jet, averaged over
    each cell's width and scaled so that the cells carry exactly a unit flow."""
    half = RADIUS * math.sin(0.5 * JET_WIDTH)
    offsets = (torch.arange(points, dtype=torch.float64) + 0.5) / points - 0.5
    x = x_cells[:, None] + h * offsets[None, :] - CENTRE[0]
    angle = torch.asin((x / RADIUS).clamp(-1.0, 1.0))
    across = x.abs() < half
    # radial velocity cos(pi angle / width); the stream is vertical, so its vertical
    # velocity is the radial one over cos(angle)
    profile = torch.where(across, torch.cos(math.pi * angle / JET_WIDTH) / torch.cos(angle), 0.0).mean(1)
    return profile / (profile.sum() * h)


def wall_velocity(theta: np.ndarray) -> np.ndarray:
    """The outward velocity of the cylinder's surface at the polar angles ``theta`` per
    unit flow rate of the top jet (the bottom one's rate is opposite): the published
    cosine across each jet, 10 degrees wide, which carries a unit flow rate."""
    amplitude = math.pi / (2.0 * JET_WIDTH * RADIUS)
    velocity = np.zeros_like(theta)
    for centre, sign in ((0.5 * math.pi, 1.0), (1.5 * math.pi, -1.0)):
        off = np.angle(np.exp(1j * (theta - centre)))  # the angle from the jet's centre
        across = np.abs(off) < 0.5 * JET_WIDTH
        velocity += np.where(across, sign * amplitude * np.cos(math.pi * off / JET_WIDTH), 0.0)
    return velocity


def jet_wall(body: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """The wall's velocity per unit flow rate of the top jet (``[n, 2, 1]``): outward,
    :func:`wall_velocity` along the normal."""
    theta = np.arctan2(normal[1], normal[0])
    return (wall_velocity(theta) * normal).T[:, :, None]


def step(i, carried: tuple[Flow, torch.Tensor, torch.Tensor], target: torch.Tensor, channel: Channel, nu, dt: float):
    """One time step of ``(flow, drag, lift)``: the batch-last flow and the running
    sums of the forces on the cylinder (``[B]``), with the top jet's rate relaxing to
    ``target`` (``[B]``)."""
    flow, drag_sum, lift_sum = carried
    c, h = channel, channel.h
    u, v, p = flow.u, flow.v, flow.p
    q = flow.q + SMOOTHING * (target - flow.q)
    # explicit terms: centred advection and diffusion inside, the outlet face carried out
    hu, hv = tendency(c.u_ghosts(u), c.v_ghosts(v), nu, c.x_spacing, c.y_spacing)
    hu = torch.cat((hu, -U_MEAN * (u[-1:] - u[-2:-1]) / c.dx_cells[-1:]), 0)
    u_star = u[1:] + dt * (1.5 * hu - 0.5 * flow.hu - c.x_gradient(p))
    v_star = v[:, 1:-1] + dt * (1.5 * hv - 0.5 * flow.hv - c.y_gradient(p))
    u_star = torch.cat((c.inflow.expand_as(u[:1]), u_star), 0)
    v_star = torch.nn.functional.pad(v_star, (0, 0, 1, 1))
    # the body: its faces take its velocity, the first fluid faces around it the value
    # the wall and the flow further out give them; what that removes is the force
    u_new, v_new = c.body_u(u_star, q[None]), c.body_v(v_star, q[None])
    cell = h * h / dt
    drag = (u_star - u_new).sum((0, 1)) * cell
    lift = (v_star - v_new).sum((0, 1)) * cell + c.jet_momentum * (q - flow.q) / dt
    # projection on the rectangle
    phi = c.solve(c.continuity(u_new, v_new) / dt)
    u_new = torch.cat((u_new[:1], u_new[1:] - dt * c.x_gradient(phi)), 0)
    v_new = torch.cat((v_new[:, :1], v_new[:, 1:-1] - dt * c.y_gradient(phi), v_new[:, -1:]), 1)
    return Flow(u=u_new, v=v_new, p=p * c.live + phi, hu=hu, hv=hv, q=q), drag_sum + drag, lift_sum + lift


def rest(num_envs: int, channel: Channel, dtype, device) -> Flow:
    """The channel at rest with its inflow on."""
    nx, ny = channel.nx, channel.ny
    zeros = lambda *shape: torch.zeros((num_envs, *shape), dtype=dtype, device=device)
    u = zeros(nx + 1, ny)
    u[:, 0] = channel.inflow[:, 0].to(dtype)
    return Flow(u=u, v=zeros(nx, ny + 1), p=zeros(nx, ny), hu=zeros(nx, ny), hv=zeros(nx, ny - 1), q=zeros())


def run(
    flow: Flow, n: int, target: torch.Tensor, channel: Channel, nu, dt: float = DT, loop=None
) -> tuple[Flow, torch.Tensor, torch.Tensor]:
    """``n`` steps from a batch-first flow; returns the new flow and the mean drag and
    lift forces over the steps (``[B]``). ``loop`` runs the steps (an env's substep
    loop; a Python loop when None). The flow's layout is converted once each way."""
    last = lambda f: f.movedim(0, -1).contiguous()
    carried = Flow(*(last(f) for f in flow)), torch.zeros_like(flow.q), torch.zeros_like(flow.q)
    if loop is None:
        for i in range(n):
            carried = step(i, carried, target, channel, nu, dt)
    else:
        carried = loop(n, carried, target, channel, nu, dt)
    first = lambda f: f.movedim(-1, 0).contiguous()
    flow, drag, lift = carried
    return Flow(*(first(f) for f in flow)), drag / n, lift / n


def coefficient(force: torch.Tensor) -> torch.Tensor:
    """A force's coefficient, 2 F / (rho U^2 D) with the mean inflow U."""
    return 2.0 * force / (U_MEAN**2 * DIAMETER)


def developed_shedding(
    cells_per_diameter: int = 20, *, time: float = DEVELOP_TIME, nu: float = NU, dt: float = DT
) -> tuple[Flow, dict[str, np.ndarray]]:
    """The uncontrolled flow ``time`` time units after the inflow is switched on over
    the channel at rest, in float64, without batch dimension, and the histories of the
    drag and lift coefficients of every step (``"time"``, ``"drag"``, ``"lift"``).
    The cylinder sits 0.005 below the channel's centre line, which starts the shedding."""
    channel = Channel(cells_per_diameter, dtype=torch.float64, device="cpu")
    if not stable(channel.h, nu, dt):
        raise ValueError(f"dt = {dt:g} is unstable for {cells_per_diameter} cells per diameter: take a smaller one")
    flow = rest(1, channel, torch.float64, "cpu")
    target = torch.zeros(1, dtype=torch.float64)
    steps = int(round(time / dt))
    drag, lift = np.empty(steps), np.empty(steps)
    with torch.no_grad():
        for k in range(steps):
            flow, fd, fl = run(flow, 1, target, channel, nu, dt)
            drag[k], lift[k] = float(fd[0]), float(fl[0])
    history = {"time": dt * np.arange(1, steps + 1), "drag": coefficient(torch.from_numpy(drag)).numpy()}
    history["lift"] = coefficient(torch.from_numpy(lift)).numpy()
    return map_state(lambda f: f[0], flow), history
