"""The flow of cylinder-v0: the stretched staggered channel, the immersed cylinder
with its jets, one time step and the developed shedding every episode starts from
(the case and its numerics: :mod:`beacon_torch.envs.cylinder`)."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

from beacon_torch.core.state import map_state
from beacon_torch.numerics import bodies
from beacon_torch.numerics.bodies import Circle, StretchedBox, advance, stable
from beacon_torch.numerics.grid import VALUE
from beacon_torch.numerics.staggered import Axis

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


class Channel(StretchedBox):
    """The stretched grid of the channel and the immersed cylinder: cells of size
    ``h = D / cells_per_diameter`` in a box around the cylinder and its near wake,
    growing by 5 % a cell outside it up to 8 h; the parabolic inflow, no-slip walls, the
    body's forcing of each velocity component, the jets' stream, and the probes.
    Fields are batch-last inside the steps (``[X, Y, B]``), as in the cavities'
    solver."""

    def __init__(self, cells_per_diameter: int, *, dtype, device) -> None:
        _resolution(cells_per_diameter)
        h = DIAMETER / cells_per_diameter
        x, y = Axis(LENGTH, *FINE_X, h, GROWTH, WIDEST * h), Axis(HEIGHT, *FINE_Y, h, GROWTH, WIDEST * h)
        nx, ny = x.n, y.n
        # the jets' vertical stream through the body per unit flow rate, on the v faces
        solid_v = inside(x.centres[:, None], y.faces[None, :])
        stream = jet_profile(x.centres, h)[:, None] * solid_v
        # the body's cells conserve mass by halves, so that the jets' stream carries its
        # rate from the bottom jet to the top one
        body_cells = inside(x.centres[:, None], y.centres[None, :])
        upper = (y.centres > CENTRE[1]).double()[None, :]
        halves = torch.stack((body_cells * upper, body_cells * (1.0 - upper)), -1)  # [nx, ny, 2]
        super().__init__(
            x,
            y,
            h,
            4.0 * U_MAX * y.centres * (HEIGHT - y.centres) / HEIGHT**2,
            VALUE,
            (CYLINDER,),
            jet_wall,
            torch.zeros(nx + 1, ny, 1),
            stream[..., None],
            halves,
            outflow=U_MEAN,
            dtype=dtype,
            device=device,
        )
        # the momentum the body's faces hold per unit flow rate
        self.jet_momentum = float(stream.sum()) * h * h
        self.probe_index, self.probe_weight = self.probes(PROBES + np.array(CENTRE))

    def pressure_probes(self, p: torch.Tensor) -> torch.Tensor:
        """The pressure ``[B, nx, ny]`` at the probes, ``[B, N_PROBES]``."""
        ix, iy = self.probe_index
        return (p[:, ix, iy] * self.probe_weight).sum(-1)


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


def step(i, carried: tuple[Flow, torch.Tensor], target: torch.Tensor, channel: Channel, nu, dt: float):
    """One time step of ``(flow, loads)``: the batch-last flow and the running sums of
    the drag and lift forces on the cylinder (``[2, B]``), with the top jet's rate
    relaxing to ``target`` (``[B]``)."""
    flow, loads = carried
    c, h = channel, channel.h
    q = flow.q + SMOOTHING * (target - flow.q)
    u_star, v_star, hu, hv = c.predict(flow.u, flow.v, flow.p, flow.hu, flow.hv, nu, dt)
    # the body: its faces take its velocity, the first fluid faces around it the value
    # the wall and the flow further out give them; what that removes is the force
    u_new, v_new = c.body_u(u_star, q[None]), c.body_v(v_star, q[None])
    cell = h * h / dt
    drag = (u_star - u_new).sum((0, 1)) * cell
    lift = (v_star - v_new).sum((0, 1)) * cell + c.jet_momentum * (q - flow.q) / dt
    u_new, v_new, p = c.project(u_new, v_new, flow.p, dt)
    return Flow(u=u_new, v=v_new, p=p, hu=hu, hv=hv, q=q), loads + torch.stack((drag, lift))


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
    loop; a Python loop when None)."""
    loads = flow.q.new_zeros(2, *flow.q.shape)
    flow, loads = advance(step, flow, n, loads, target, channel, nu, dt, loop)
    return flow, loads[0] / n, loads[1] / n


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
