"""Circular bodies immersed in the stretched staggered grid: the grid's axes, the
bodies' direct forcing, the box they sit in (inflow, open outlet, walls below and
above; its predictor and projection), the probes' stencil and the explicit step's
diffusion limit. Shared by the flows past cylinders (one cylinder in a channel, three
in a free stream).

Layout: fields batch last, ``[X, Y, B]``, as everywhere in the staggered numerics. A
body's motion is driven by ``C`` controls (a jet's flow rate, the cylinders' rotation
rates), passed to the forcing as ``[C, B]``."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
import torch

from beacon_torch.numerics.grid import NEUMANN, VALUE, ZERO_FACE, Ghosts
from beacon_torch.numerics.poisson import PoissonSolver
from beacon_torch.numerics.staggered import Axis, Stretched, divergence, tendency

# Adams-Bashforth 2 is stable on the negative real axis up to 1 (forward Euler: 2); the
# grid-scale diffusion mode of a square cell sits at -8 nu dt / h^2. A margin for the
# advection that comes on top of it.
DIFFUSION_LIMIT = 0.8


def stable(h: float, nu: float, dt: float) -> bool:
    """Whether the explicit diffusion of cells of size ``h`` is stable at ``dt``."""
    return 8.0 * nu * dt / h**2 < DIFFUSION_LIMIT


# the relative distance from a wall within which a node counts as on it
WALL_TOLERANCE = 1e-9


class Circle(NamedTuple):
    """A circular body: its centre and radius."""

    x: float
    y: float
    radius: float


def inside(circles: Sequence[Circle], x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """1.0 where the point ``(x, y)`` lies inside one of the circles, else 0.0."""
    solid = torch.zeros(torch.broadcast_shapes(x.shape, y.shape), dtype=torch.bool)
    for c in circles:
        solid |= torch.hypot(x - c.x, y - c.y) < c.radius
    return solid.double()


# The wall's velocity per unit of each control: given each wall point's body index
# (``[n]``) and the body's outward unit normal there (``[2, n]``), the ``[n, 2, C]``
# velocity (x and y components) of the wall there per unit of each of the ``C`` controls.
WallVelocity = Callable[[np.ndarray, np.ndarray], np.ndarray]


class ImmersedBoundary:
    """The bodies' direct forcing on one velocity component, whose nodes are the grid
    ``xs`` x ``ys``, applied to a predicted field ``[X, Y, B]`` with the controls ``q``
    (``[C, B]``). Nodes inside a circle take the body's velocity (``inside_value``,
    ``[X * Y, C]`` per unit of each control). Nodes outside with a neighbour inside, the
    first fluid nodes, belong to the nearest body's wall and take the value at their
    wall distance ``d`` of the quadratic in the wall distance through the wall's velocity
    (``wall``) and the flow at ``d + h`` and ``d + 2 h`` along the wall normal, each read
    bilinearly from the nodes around it: a boundary of second order, without the
    staircase's first-order shift of the wall. Where those nodes are first fluid nodes
    themselves, the conditions are coupled; they are solved once here, so that a step
    applies ``forced = M @ free_values + m @ q``.

    ``groups`` (``[G, F]`` over the forced nodes ``forced``) sums what the forcing
    changed body by body: the momentum each body takes from the flow; ``arm``
    (``[2, F]``) is each forced node's position from its body's centre."""

    def __init__(
        self,
        xs: torch.Tensor,
        ys: torch.Tensor,
        component: int,
        circles: Sequence[Circle],
        wall: WallVelocity,
        inside_value: torch.Tensor,
        h: float,
    ):
        xs, ys = xs.numpy(), ys.numpy()
        x, y = np.meshgrid(xs, ys, indexing="ij")
        nx, ny = x.shape
        # each node's distance to each wall, its nearest body and that body's geometry
        centres = np.array([(c.x, c.y) for c in circles])
        radii = np.array([c.radius for c in circles])
        offsets = np.stack((x.reshape(-1)[:, None] - centres[:, 0], y.reshape(-1)[:, None] - centres[:, 1]))
        r_all = np.hypot(offsets[0], offsets[1])  # [nodes, bodies]
        body_of = np.argmin(r_all - radii, axis=1)
        nodes = np.arange(nx * ny)
        r = r_all[nodes, body_of].reshape(nx, ny)
        # a node on a wall (to round-off) is a fluid node at distance zero, whichever
        # side the rounding puts it: mirror-symmetric bodies then meet mirror-symmetric
        # forcing
        solid = (r_all < radii * (1.0 - WALL_TOLERANCE)).any(1).reshape(nx, ny)
        near = np.zeros_like(solid)
        near[1:] |= solid[:-1]
        near[:-1] |= solid[1:]
        near[:, 1:] |= solid[:, :-1]
        near[:, :-1] |= solid[:, 1:]
        first = np.flatnonzero(near & ~solid)
        row = {node: k for k, node in enumerate(first)}
        body = body_of[first]
        normal = np.stack((offsets[0][first, body], offsets[1][first, body])) / r.flat[first]
        d = np.maximum(r.flat[first] - radii[body], 0.0)
        # the quadratic's weights of the points at d + h and d + 2 h; the wall has the rest
        points = ((h, 2.0 * d / (d + h)), (2.0 * h, -d / (d + 2.0 * h)))
        wall_weight = 1.0 - points[0][1] - points[1][1]
        inside_value = inside_value.double().reshape(nx * ny, -1).numpy()
        coupled = np.zeros((len(first), len(first)))
        free: dict[int, int] = {}
        free_weights: list[tuple[int, int, float]] = []
        rate = wall_weight[:, None] * wall(body, normal)[:, component]
        for distance, weight in points:
            px = x.flat[first] + distance * normal[0]
            py = y.flat[first] + distance * normal[1]
            i = np.clip(np.searchsorted(xs, px) - 1, 0, nx - 2)
            j = np.clip(np.searchsorted(ys, py) - 1, 0, ny - 2)
            tx, ty = (px - xs[i]) / (xs[i + 1] - xs[i]), (py - ys[j]) / (ys[j + 1] - ys[j])
            corners = ((0, 0, (1 - tx) * (1 - ty)), (1, 0, tx * (1 - ty)), (0, 1, (1 - tx) * ty), (1, 1, tx * ty))
            for di, dj, w in corners:
                for k, node in enumerate((i + di) * ny + j + dj):
                    c = weight[k] * w[k]
                    if node in row:
                        coupled[k, row[node]] += c
                    elif solid.flat[node]:
                        rate[k] += c * inside_value[node]
                    else:
                        free_weights.append((k, free.setdefault(int(node), len(free)), c))
        weights = np.zeros((len(first), len(free)))
        for k, column, c in free_weights:
            weights[k, column] += c
        system = np.eye(len(first)) - coupled
        self.matrix = torch.from_numpy(np.linalg.solve(system, weights))  # [first, free]
        self.rate = torch.from_numpy(np.linalg.solve(system, rate))  # [first, C]
        self.sources = torch.tensor(sorted(free, key=free.get))  # the free nodes read
        self.targets = torch.from_numpy(first)  # the first fluid nodes
        forced = solid | (near & ~solid)
        self.free = torch.from_numpy(~forced.reshape(-1)).double()[:, None]  # [nodes, 1]
        self.inside = torch.from_numpy(np.where(solid.reshape(-1, 1), inside_value, 0.0))  # [nodes, C]
        # the forced nodes, each counted to its nearest body
        self.forced = torch.from_numpy(np.flatnonzero(forced))
        owner = body_of[self.forced.numpy()]
        self.groups = torch.from_numpy((owner[None, :] == np.arange(len(circles))[:, None]).astype(np.float64))
        # and its arm from that body's centre (for the torques)
        arm = (x.flat[self.forced.numpy()] - centres[owner, 0], y.flat[self.forced.numpy()] - centres[owner, 1])
        self.arm = torch.from_numpy(np.stack(arm))  # [2, forced]

    def to(self, dtype, device) -> None:
        for name in ("matrix", "rate", "free", "inside", "groups", "arm"):
            setattr(self, name, getattr(self, name).to(dtype=dtype, device=device, copy=True))
        self.sources, self.targets, self.forced = (t.to(device) for t in (self.sources, self.targets, self.forced))

    def __call__(self, f: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        nx, ny, batch = f.shape
        flat = f.reshape(nx * ny, batch)
        first = self.matrix @ flat[self.sources] + self.rate @ q
        return (flat * self.free + self.inside @ q).index_add(0, self.targets, first).reshape(nx, ny, batch)


def probe_stencil(
    points: np.ndarray, x_cells: torch.Tensor, y_cells: torch.Tensor
) -> tuple[tuple[torch.Tensor, ...], torch.Tensor]:
    """The four cells around each point and their bilinear weights: indices
    ``([P, 4], [P, 4])`` and weights ``[P, 4]``."""

    def along(coordinate: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        i = np.clip(np.searchsorted(centres, coordinate) - 1, 0, len(centres) - 2)
        return i, (coordinate - centres[i]) / (centres[i + 1] - centres[i])

    i0, wx = along(points[:, 0], x_cells.numpy())
    j0, wy = along(points[:, 1], y_cells.numpy())
    ix = np.stack((i0, i0 + 1, i0, i0 + 1), 1)
    iy = np.stack((j0, j0, j0 + 1, j0 + 1), 1)
    w = np.stack(((1 - wx) * (1 - wy), wx * (1 - wy), (1 - wx) * wy, wx * wy), 1)
    return (torch.from_numpy(ix), torch.from_numpy(iy)), torch.from_numpy(w)


class StretchedBox:
    """The rectangle of stretched cells the bodies sit in: the inflow ``inflow``
    (``[ny]``, the x-velocity on the left face), an open outlet on the right (zero
    pressure on its face, the velocity carried out at ``outflow``), and below and above
    impermeable walls, no-slip (``walls`` VALUE) or slip (GRADIENT). The bodies
    (``circles``) force each velocity component (:class:`ImmersedBoundary`, the wall's
    velocity ``wall``, the bodies' inner faces ``inside_u`` ``[nx + 1, ny, C]`` and
    ``inside_v`` ``[nx, ny + 1, C]`` per unit of each control); the cells inside them
    conserve mass by groups (``cell_groups``, ``[nx, ny, G]``), not one by one.

    A time step is :meth:`predict` (Adams-Bashforth 2 for advection and diffusion with
    centred fluxes, the previous pressure's gradient), the bodies' forcing of the
    predicted faces, and :meth:`project`. Fields are batch last (``[X, Y, B]``)."""

    def __init__(
        self,
        x: Axis,
        y: Axis,
        h: float,
        inflow: torch.Tensor,
        walls: float,
        circles: Sequence[Circle],
        wall: WallVelocity,
        inside_u: torch.Tensor,
        inside_v: torch.Tensor,
        cell_groups: torch.Tensor,
        *,
        outflow: float = 1.0,
        dtype,
        device,
    ) -> None:
        self.h, self.x, self.y, self.outflow = h, x, y, outflow
        self.nx, self.ny = nx, ny = x.n, y.n
        # copies: a compiled loop takes no two inputs that share memory
        cast = lambda t: t.to(dtype=dtype, device=device, copy=True)
        self.cast = cast
        # spacings, shaped to broadcast against [X, Y, B]
        along, across = (lambda t: cast(t)[:, None, None]), (lambda t: cast(t)[None, :, None])
        self.dx_cells, self.dy_cells = along(x.widths), across(y.widths)
        self.dx_gaps, self.dy_gaps = along(x.gaps), across(y.gaps)
        # the x-gradient's distances on the faces 1..nx (the outlet's mirrored ghost last)
        self.dx_grad = along(x.gaps[1:])
        # the axes as the shared staggered operators take them
        self.x_spacing = Stretched(self.dx_cells, self.dx_gaps, 0)
        self.y_spacing = Stretched(self.dy_cells, self.dy_gaps, 1)
        self.inflow = cast(inflow)[:, None]  # [ny, 1]
        # the bodies: the faces inside them and the first fluid faces around them
        self.body_u = ImmersedBoundary(x.faces, y.centres, 0, circles, wall, inside_u, h)
        self.body_v = ImmersedBoundary(x.centres, y.faces, 1, circles, wall, inside_v, h)
        self.body_u.to(dtype=dtype, device=device)
        self.body_v.to(dtype=dtype, device=device)
        # cells whose centre lies in a body need not conserve mass one by one (their
        # faces are forced), only by groups, so that the projection leaves the forced
        # faces as the forcing set them
        body_cells = inside(circles, x.centres[:, None], y.centres[None, :])
        self.fluid_cells = cast(1.0 - body_cells)[..., None]
        self.groups = cast(cell_groups)
        self.group_share = cast(cell_groups / cell_groups.sum((0, 1)))
        # cells with a free face: the pressure of the others acts on forced faces only
        # (each step overwrites them), so it is not carried from step to step
        free_u, free_v = self.body_u.free.reshape(nx + 1, ny), self.body_v.free.reshape(nx, ny + 1)
        enclosed = (1 - free_u[1:]) * (1 - free_u[:-1]) * (1 - free_v[:, 1:]) * (1 - free_v[:, :-1])
        self.live = cast(1.0 - enclosed)[..., None]
        # the walls below and above; v = 0 at the inflow, carried out at the outlet
        u_y = Ghosts._cell_axis(ny, walls, walls)
        self.u_ghosts = Ghosts(None, [1.0] * (nx + 1), *u_y, dtype=dtype, device=device)
        v_x = Ghosts._cell_axis(nx, VALUE, 1.0)
        self.v_ghosts = Ghosts(*v_x, None, [0.0, *[1.0] * (ny - 1), 0.0], dtype=dtype, device=device)
        # solved across the box first (a mirror-symmetric grid: the folded basis), then
        # along it: the fields are transposed for the solve
        self.solver = PoissonSolver.stretched(
            y.laplacian(NEUMANN, NEUMANN),
            y.widths,
            x.laplacian(NEUMANN, ZERO_FACE),
            x.widths,
            dtype=dtype,
            device=device,
        )

    def probes(self, points: np.ndarray) -> tuple[tuple[torch.Tensor, ...], torch.Tensor]:
        """The cells' bilinear stencil of the ``[P, 2]`` points (see :func:`probe_stencil`),
        on this box's device and in its dtype."""
        index, weight = probe_stencil(points, self.x.centres, self.y.centres)
        return tuple(i.to(self.fluid_cells.device) for i in index), self.cast(weight)

    def vorticity(self, u: torch.Tensor, v: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The vorticity of one member's faces (``[nx + 1, ny]``, ``[nx, ny + 1]``) at the
        cells' inner corners, with the corners' x and y (for a figure), in float64."""
        u, v = u.double(), v.double()
        dvdx = (v[1:, 1:-1] - v[:-1, 1:-1]) / self.x.gaps[1:-1, None]
        dudy = (u[1:-1, 1:] - u[1:-1, :-1]) / self.y.gaps[None, 1:-1]
        return self.x.faces[1:-1].numpy(), self.y.faces[1:-1].numpy(), (dvdx - dudy).numpy()

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
        bodies' cells, each group's mean only, so that the faces around the bodies keep
        the values the forcing gave them."""
        div = self.divergence(u, v)
        total = torch.einsum("xyb,xyh->hb", div, self.groups)  # [G, B]
        return div * self.fluid_cells + torch.einsum("xyh,hb->xyb", self.group_share, total)

    def solve(self, rhs: torch.Tensor) -> torch.Tensor:
        """phi with lap phi = rhs in the cells: zero normal gradient on the walls and
        the inflow, zero on the outlet face."""
        return self.solver.solve(rhs.transpose(0, 1).contiguous()).transpose(0, 1)

    def predict(self, u, v, p, hu_prev, hv_prev, nu, dt: float):
        """The predicted faces ``(u*, v*)`` (the inflow's face set, the walls' zero) and
        the explicit terms ``(hu, hv)`` of this step (Adams-Bashforth's memory): centred
        advection and diffusion inside, the outlet's face carried out."""
        hu, hv = tendency(self.u_ghosts(u), self.v_ghosts(v), nu, self.x_spacing, self.y_spacing)
        hu = torch.cat((hu, -self.outflow * (u[-1:] - u[-2:-1]) / self.dx_cells[-1:]), 0)
        u_star = u[1:] + dt * (1.5 * hu - 0.5 * hu_prev - self.x_gradient(p))
        v_star = v[:, 1:-1] + dt * (1.5 * hv - 0.5 * hv_prev - self.y_gradient(p))
        u_star = torch.cat((self.inflow.expand_as(u[:1]), u_star), 0)
        v_star = torch.nn.functional.pad(v_star, (0, 0, 1, 1))
        return u_star, v_star, hu, hv

    def project(self, u, v, p, dt: float):
        """The incremental projection of the forced faces: ``(u, v, p)`` divergence-free
        where :meth:`continuity` asks it, the pressure incremented."""
        phi = self.solve(self.continuity(u, v) / dt)
        u = torch.cat((u[:1], u[1:] - dt * self.x_gradient(phi)), 0)
        v = torch.cat((v[:, :1], v[:, 1:-1] - dt * self.y_gradient(phi), v[:, -1:]), 1)
        return u, v, p * self.live + phi


def advance(step: Callable, flow, n: int, loads: torch.Tensor, target: torch.Tensor, box, nu, dt, loop=None):
    """``n`` time steps of a flow past bodies. ``flow`` is batch-first (an env's state)
    and is turned once each way into the batch-last layout the steps work in; ``loads``
    (``[..., B]``, zeros) is the running sum of the bodies' forces that each step adds
    to, ``target`` (``[C, B]``) the controls the actuation relaxes to. ``step(i,
    (flow, loads), target, box, nu, dt)`` is one time step; ``loop`` runs the steps
    (an env's substep loop, compiled or not), a Python loop of ``step`` when None.
    Returns the batch-first flow and the loads summed over the steps."""
    last = lambda f: f.movedim(0, -1).contiguous()
    carried = type(flow)(*(last(f) for f in flow)), loads
    if loop is None:
        for i in range(n):
            carried = step(i, carried, target, box, nu, dt)
    else:
        carried = loop(n, carried, target, box, nu, dt)
    flow, loads = carried
    first = lambda f: f.movedim(-1, 0).contiguous()
    return type(flow)(*(first(f) for f in flow)), loads
