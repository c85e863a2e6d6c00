"""The flow of pinball-v0: the stretched box around the three rotating cylinders, one
time step, and the developed flow every episode starts from (the case and its
numerics: :mod:`beacon_torch.envs.pinball`)."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

from beacon_torch.core.state import map_state
from beacon_torch.numerics.bodies import Circle, StretchedBox, advance, stable
from beacon_torch.numerics.grid import GRADIENT
from beacon_torch.numerics.staggered import Axis

DIAMETER = 1.0
RADIUS = 0.5 * DIAMETER
U_INF = 1.0
# the cylinders, front, top and bottom: an equilateral triangle of side 1.5 D pointing
# upstream, the origin midway between the two rear cylinders
CYLINDERS = (
    Circle(-0.75 * math.sqrt(3.0) * DIAMETER, 0.0, RADIUS),
    Circle(0.0, 0.75 * DIAMETER, RADIUS),
    Circle(0.0, -0.75 * DIAMETER, RADIUS),
)
NAMES = ("front", "top", "bottom")
# the box: 6 D upstream and on each side, 20 D downstream
X_RANGE, Y_RANGE = (-6.0, 20.0), (-6.0, 6.0)
# cells of size h fill the box around the cylinders and the near wake (the probes);
# outside, cells grow by GROWTH a cell up to WIDEST cells
FINE_X, FINE_Y = (-2.5, 4.5), (-2.0, 2.0)
GROWTH = 1.05
WIDEST = 8.0
DT = 5e-3
SUBSTEPS = 100  # an action every 0.5 convective time units
EPISODE_LENGTH = 100
SMOOTHING = 0.1  # each step the rotation rates move this fraction of the way to the action
# velocity probes in the wake: 5 columns x 7 rows behind the rear cylinders
PROBES = np.array([(x, y) for x in np.linspace(1.0, 3.5, 5) for y in np.linspace(-1.25, 1.25, 7)])
N_PROBES = len(PROBES)


class Flow(NamedTuple):
    """The flow on the staggered grid, batch first as a state holds it: the face
    velocities (the inflow face and the outlet face included), the cells' pressure,
    the explicit terms of the previous step (Adams-Bashforth's memory) and the
    cylinders' rotation rates. The steps carry it batch last (``[X, Y, B]``, the
    rates ``[3, B]``)."""

    u: torch.Tensor  # [batch, nx + 1, ny]
    v: torch.Tensor  # [batch, nx, ny + 1]
    p: torch.Tensor  # [batch, nx, ny]
    hu: torch.Tensor  # [batch, nx, ny]
    hv: torch.Tensor  # [batch, nx, ny - 1]
    omega: torch.Tensor  # [batch, 3] angular velocities, counter-clockwise positive


def resolution_error(cells: int) -> str | None:
    """Why ``cells`` per diameter cannot make the grid, or None."""
    if cells % 2:
        return f"parameter 'cells_per_diameter' = {cells} must be even (the fine box fits whole cells)"
    return None


def rotation_wall(cylinders: tuple[Circle, ...]):
    """The wall's velocity per unit angular velocity of each cylinder, as the forcing
    takes it: at wall points of the cylinders ``body`` with outward normals ``normal``,
    ``[n, 2, 3]``, tangential, R omega, on the cylinder the point belongs to."""
    radii = np.array([c.radius for c in cylinders])

    def wall(body: np.ndarray, normal: np.ndarray) -> np.ndarray:
        velocity = np.zeros((len(body), 2, len(cylinders)))
        rows = np.arange(len(body))
        velocity[rows, 0, body] = -radii[body] * normal[1]
        velocity[rows, 1, body] = radii[body] * normal[0]
        return velocity

    return wall


def rigid_rotation(xs: torch.Tensor, ys: torch.Tensor, component: int, cylinders: tuple[Circle, ...]) -> torch.Tensor:
    """The velocity component at the nodes ``xs`` x ``ys`` of each body turning at a unit
    angular velocity about its centre, on the nodes inside it (``[X, Y, 3]``)."""
    x, y = xs[:, None], ys[None, :]
    columns = []
    for c in cylinders:
        inside = (torch.hypot(x - c.x, y - c.y) < c.radius).double()
        columns.append(inside * (-(y - c.y) if component == 0 else (x - c.x)))
    return torch.stack(columns, -1)


def shifted(length: float, low: float, h: float, fine: tuple[float, float]) -> Axis:
    """A stretched :class:`Axis` over ``[low, low + length]`` (its faces and centres in
    the box's coordinates)."""
    axis = Axis(length, fine[0] - low, fine[1] - low, h, GROWTH, WIDEST * h)
    axis.faces, axis.centres = axis.faces + low, axis.centres + low
    return axis


class Box(StretchedBox):
    """The stretched grid around the three cylinders: cells of size
    ``h = D / cells_per_diameter`` in the box around them and their near wake, growing
    by 5 % a cell outside it up to 8 h; the uniform inflow, slip walls at y = -6 and 6
    (v = 0, no shear), the cylinders' forcing with their rotation, and the probes.
    ``cylinders`` and ``x_range`` move the cylinders and the box's ends (the validation
    against other published set-ups); they must leave the cylinders in the fine box."""

    def __init__(
        self,
        cells_per_diameter: int,
        *,
        cylinders: tuple[Circle, ...] = CYLINDERS,
        x_range: tuple[float, float] = X_RANGE,
        dtype,
        device,
    ) -> None:
        error = resolution_error(cells_per_diameter)
        if error:
            raise ValueError(error)
        h = DIAMETER / cells_per_diameter
        x = shifted(x_range[1] - x_range[0], x_range[0], h, FINE_X)
        y = shifted(Y_RANGE[1] - Y_RANGE[0], Y_RANGE[0], h, FINE_Y)
        # each cylinder's cells conserve mass together
        cells = torch.stack(
            [(torch.hypot(x.centres[:, None] - c.x, y.centres[None, :] - c.y) < c.radius).double() for c in cylinders],
            -1,
        )
        # the faces inside each cylinder turning with it at a unit angular velocity
        inner_u = rigid_rotation(x.faces, y.centres, 0, cylinders)
        inner_v = rigid_rotation(x.centres, y.faces, 1, cylinders)
        super().__init__(
            x,
            y,
            h,
            torch.full((y.n,), U_INF, dtype=torch.float64),
            GRADIENT,
            cylinders,
            rotation_wall(cylinders),
            inner_u,
            inner_v,
            cells,
            outflow=U_INF,
            dtype=dtype,
            device=device,
        )
        self.cylinders = cylinders
        # the angular momentum the faces inside each cylinder hold per unit angular
        # velocity: what its forcing spends on turning them is not the flow's torque
        spin = (inner_u**2).sum((0, 1)) + (inner_v**2).sum((0, 1))
        self.spin = self.cast(spin * h * h)[:, None]  # [3, 1]
        self.probe_index, self.probe_weight = self.probes(PROBES)

    def velocity_probes(self, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """The velocity at the probes from batch-first faces: u then v, ``[B, 2 P]``."""
        ix, iy = self.probe_index
        uc, vc = 0.5 * (u[:, 1:] + u[:, :-1]), 0.5 * (v[:, :, 1:] + v[:, :, :-1])
        at = lambda f: (f[:, ix, iy] * self.probe_weight).sum(-1)
        return torch.cat((at(uc), at(vc)), -1)

    def loads(self, du: torch.Tensor, dv: torch.Tensor, spun: torch.Tensor, dt: float) -> torch.Tensor:
        """Each cylinder's force and torque from what its forcing removed from the
        predicted faces (``du``, ``dv``, batch last), the torque less what turned the
        faces inside it faster (``spun``, the change of its angular velocity,
        ``[3, B]``): ``[3, 3, B]`` (drag, lift, torque), per unit density."""
        cell = self.h * self.h / dt
        bu, bv = self.body_u, self.body_v
        u_taken = du.reshape(-1, du.shape[-1])[bu.forced]  # [F_u, B]
        v_taken = dv.reshape(-1, dv.shape[-1])[bv.forced]
        drag = bu.groups @ u_taken
        lift = bv.groups @ v_taken
        torque = bv.groups @ (bv.arm[0][:, None] * v_taken) - bu.groups @ (bu.arm[1][:, None] * u_taken)
        torque = torque + self.spin * spun / (self.h * self.h)
        return torch.stack((drag, lift, torque)) * cell


def step(i, carried: tuple[Flow, torch.Tensor], target: torch.Tensor, box: Box, nu, dt: float):
    """One time step of ``(flow, loads)``: the batch-last flow and the running sums of
    the cylinders' drag, lift and torque (``[3, 3, B]``), the rotation rates relaxing to
    ``target`` (``[3, B]``)."""
    flow, loads = carried
    omega = flow.omega + SMOOTHING * (target - flow.omega)
    u_star, v_star, hu, hv = box.predict(flow.u, flow.v, flow.p, flow.hu, flow.hv, nu, dt)
    u_new, v_new = box.body_u(u_star, omega), box.body_v(v_star, omega)
    loads = loads + box.loads(u_star - u_new, v_star - v_new, omega - flow.omega, dt)
    u_new, v_new, p = box.project(u_new, v_new, flow.p, dt)
    return Flow(u=u_new, v=v_new, p=p, hu=hu, hv=hv, omega=omega), loads


def rest(num_envs: int, box: Box, dtype, device) -> Flow:
    """The box with the free stream everywhere (the cylinders then impose themselves)."""
    nx, ny = box.nx, box.ny
    zeros = lambda *shape: torch.zeros((num_envs, *shape), dtype=dtype, device=device)
    return Flow(
        u=torch.full((num_envs, nx + 1, ny), U_INF, dtype=dtype, device=device),
        v=zeros(nx, ny + 1),
        p=zeros(nx, ny),
        hu=zeros(nx, ny),
        hv=zeros(nx, ny - 1),
        omega=zeros(3),
    )


def run(flow: Flow, n: int, target: torch.Tensor, box: Box, nu, dt: float = DT, loop=None) -> tuple[Flow, torch.Tensor]:
    """``n`` steps from a batch-first flow towards the rotation rates ``target``
    (``[B, 3]``); returns the new flow and the cylinders' loads averaged over the steps
    (``[B, 3, 3]``: drag, lift and torque, each of the front, top and bottom cylinder).
    ``loop`` runs the steps (an env's substep loop; a Python loop when None)."""
    loads = flow.u.new_zeros(3, 3, flow.u.shape[0])
    flow, loads = advance(step, flow, n, loads, target.movedim(0, -1).contiguous(), box, nu, dt, loop)
    return flow, loads.permute(2, 0, 1) / n


def coefficient(force: torch.Tensor) -> torch.Tensor:
    """A force's coefficient, 2 F / (rho U^2 D)."""
    return 2.0 * force / (U_INF**2 * DIAMETER)


def developed(
    cells_per_diameter: int, nu: float, *, time: float, dt: float = DT, kick: float = 0.0
) -> tuple[Flow, dict[str, np.ndarray]]:
    """The uncontrolled flow ``time`` time units after the free stream is set over the
    cylinders, in float64, without batch dimension, and the histories (one value per
    time unit of ``1 / dt`` steps' mean) of each cylinder's drag and lift coefficients.
    ``kick`` turns the front cylinder at that angular velocity for the first time unit,
    which breaks the flow's mirror symmetry (a symmetric flow on a symmetric grid stays
    symmetric to round-off far longer)."""
    box = Box(cells_per_diameter, dtype=torch.float64, device="cpu")
    if not stable(box.h, nu, dt):
        raise ValueError(f"dt = {dt:g} is unstable for {cells_per_diameter} cells per diameter at nu = {nu:g}")
    flow = rest(1, box, torch.float64, "cpu")
    per_unit = int(round(1.0 / dt))
    units = int(round(time))
    drag, lift = np.empty((units, 3)), np.empty((units, 3))
    with torch.no_grad():
        for k in range(units):
            target = torch.tensor([[kick if k == 0 else 0.0, 0.0, 0.0]], dtype=torch.float64)
            flow, loads = run(flow, per_unit, target, box, nu, dt)
            drag[k], lift[k] = coefficient(loads[0, 0]).numpy(), coefficient(loads[0, 1]).numpy()
    history = {"time": np.arange(1, units + 1, dtype=float), "drag": drag, "lift": lift}
    return map_state(lambda f: f[0], flow), history
