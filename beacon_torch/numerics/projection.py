"""Batched incompressible flow on a staggered grid, for rayleigh and mixing.

Layout (all ``[B, nx + 2, ny + 2]``, x first, one ghost layer at index 0 and n + 1):
``u[i, j]`` is the x-velocity on the west face of cell (i, j), ``v[i, j]`` the
y-velocity on its south face; cells 1..n are inside, so ``u[:, 1]`` and ``u[:, nx + 1]``
are the left and right walls and ``v[..., 1]``, ``v[..., ny + 1]`` the bottom and top
walls. Scalars (temperature, concentration) are cell-centred with the same ghost layer;
the pressure is cell-centred without ghosts (``[B, nx, ny]``).

One substep of the published scheme: an explicit predictor with centred fluxes
(face-averaged velocities) and the current pressure, an exact projection with the
pressure increment from a direct Poisson solve, then explicit centred transport of the
scalar by the corrected velocity. Everything is out-of-place on fresh tensors, so the
graph survives when gradients are wanted.
"""

from __future__ import annotations

from typing import Callable, Sequence

import torch

import math

NEUMANN = "neumann"
ZERO_GHOST = "zero_ghost"


def laplacian_1d(n: int, h: float, low: str, high: str) -> torch.Tensor:
    """The ``[n, n]`` second-difference matrix with the boundary rows of each condition:
    zero normal gradient (ghost = neighbour) or a zero ghost value."""
    a = torch.diag(torch.full((n,), -2.0, dtype=torch.float64))
    a += torch.diag(torch.ones(n - 1, dtype=torch.float64), 1) + torch.diag(torch.ones(n - 1, dtype=torch.float64), -1)
    for index, kind in ((0, low), (n - 1, high)):
        if kind == NEUMANN:
            a[index, index] = -1.0
        elif kind != ZERO_GHOST:
            raise ValueError(f"boundary condition must be {NEUMANN!r} or {ZERO_GHOST!r}, got {kind!r}")
    return a / h**2


class PoissonSolver:
    """Direct solver of the 5-point Poisson equation on an ``nx x ny`` cell grid.

    The 2-D operator is separable, L = Lx (x) I + I (x) Ly; with the eigendecompositions
    Lx = Qx diag(ex) Qx^T and Ly = Qy diag(ey) Qy^T (computed once, in float64), the
    solve is four matrix products and a division, exact to round-off. With zero normal
    gradient on every wall the constant mode has eigenvalue 0 and is dropped: the
    solution has zero mean and the source must have zero sum (it does, for the
    divergence of a field with no flux through the walls).

    ``bc`` gives the conditions on the (left, right, bottom, top) walls.
    """

    def __init__(
        self,
        nx: int,
        ny: int,
        dx: float,
        dy: float,
        bc: Sequence[str] = (NEUMANN,) * 4,
        *,
        dtype: torch.dtype = torch.float64,
        device="cpu",
    ) -> None:
        left, right, bottom, top = bc
        lx, ly = laplacian_1d(nx, dx, left, right), laplacian_1d(ny, dy, bottom, top)
        ex, qx = torch.linalg.eigh(lx)
        ey, qy = torch.linalg.eigh(ly)
        self.lx = lx.to(dtype=dtype, device=device)
        self.ly = ly.to(dtype=dtype, device=device)
        eig = ex[:, None] + ey[None, :]
        scale = 1.0 / min(dx, dy) ** 2
        inv = torch.where(eig.abs() < 1e-9 * scale, torch.zeros_like(eig), 1.0 / eig)
        self.qx = qx.to(dtype=dtype, device=device)
        self.qy = qy.to(dtype=dtype, device=device)
        self.inv = inv.to(dtype=dtype, device=device)
        self.bc = tuple(bc)

    def solve(self, rhs: torch.Tensor) -> torch.Tensor:
        """phi with L phi = rhs, both ``[B, nx, ny]``."""
        hat = self.qx.T @ rhs @ self.qy
        return self.qx @ (hat * self.inv) @ self.qy.T

    def apply(self, phi: torch.Tensor) -> torch.Tensor:
        """L phi, with the solver's boundary conditions (for checks and tests)."""
        return self.lx @ phi + phi @ self.ly


def wall_velocities(
    u: torch.Tensor,
    v: torch.Tensor,
    u_bottom=0.0,
    u_top=0.0,
    v_left=0.0,
    v_right=0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """No-penetration walls and tangential wall velocities through the ghosts
    (ghost = 2 v_wall - interior). Wall values are numbers or per-member ``[B, 1]``."""
    u, v = u.clone(), v.clone()
    u[:, 0] = 0.0
    u[:, 1] = 0.0
    u[:, -1] = 0.0
    v[:, :, 0] = 0.0
    v[:, :, 1] = 0.0
    v[:, :, -1] = 0.0
    u[:, 1:-1, 0] = 2.0 * u_bottom - u[:, 1:-1, 1]
    u[:, 1:-1, -1] = 2.0 * u_top - u[:, 1:-1, -2]
    v[:, 0, 1:-1] = 2.0 * v_left - v[:, 1, 1:-1]
    v[:, -1, 1:-1] = 2.0 * v_right - v[:, -2, 1:-1]
    return u, v


def predict(
    u: torch.Tensor,
    v: torch.Tensor,
    p: torch.Tensor,
    nu,
    dt: float,
    dx: float,
    dy: float,
    v_source: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Explicit predictor u* = u + dt (-(u.grad)u + nu lap u - grad p [+ source]) on the
    interior faces, with centred fluxes of face-averaged velocities. ``u``/``v`` carry
    their wall ghosts; ``v_source`` (``[B, nx, ny - 1]``) is added to the interior v
    faces (buoyancy)."""
    # u on the interior west faces i = 2..nx, cells j = 1..ny
    uc = u[:, 1:-1, 1:-1]
    ue = 0.5 * (u[:, 2:-1, 1:-1] + u[:, 3:, 1:-1])  # cell centre east of the face
    uw = 0.5 * (u[:, 1:-2, 1:-1] + u[:, 2:-1, 1:-1])  # cell centre west of the face
    duu = (ue * ue - uw * uw) / dx
    un = 0.5 * (u[:, 2:-1, 1:-1] + u[:, 2:-1, 2:])
    vn = 0.5 * (v[:, 1:-2, 2:] + v[:, 2:-1, 2:])
    us = 0.5 * (u[:, 2:-1, :-2] + u[:, 2:-1, 1:-1])
    vs = 0.5 * (v[:, 1:-2, 1:-1] + v[:, 2:-1, 1:-1])
    duv = (un * vn - us * vs) / dy
    uf = u[:, 2:-1, 1:-1]
    lap_u = (u[:, 3:, 1:-1] - 2.0 * uf + u[:, 1:-2, 1:-1]) / dx**2 + (u[:, 2:-1, 2:] - 2.0 * uf + u[:, 2:-1, :-2]) / dy**2
    gpx = (p[:, 1:, :] - p[:, :-1, :]) / dx
    u_star = u.clone()
    u_star[:, 2:-1, 1:-1] = uf + dt * (-duu - duv + nu * lap_u - gpx)
    del uc

    # v on the interior south faces j = 2..ny, cells i = 1..nx
    vf = v[:, 1:-1, 2:-1]
    vn_c = 0.5 * (v[:, 1:-1, 2:-1] + v[:, 1:-1, 3:])
    vs_c = 0.5 * (v[:, 1:-1, 1:-2] + v[:, 1:-1, 2:-1])
    dvv = (vn_c * vn_c - vs_c * vs_c) / dy
    ve = 0.5 * (v[:, 1:-1, 2:-1] + v[:, 2:, 2:-1])
    ue_c = 0.5 * (u[:, 2:, 1:-2] + u[:, 2:, 2:-1])
    vw = 0.5 * (v[:, :-2, 2:-1] + v[:, 1:-1, 2:-1])
    uw_c = 0.5 * (u[:, 1:-1, 1:-2] + u[:, 1:-1, 2:-1])
    duv_x = (ue_c * ve - uw_c * vw) / dx
    lap_v = (v[:, 2:, 2:-1] - 2.0 * vf + v[:, :-2, 2:-1]) / dx**2 + (v[:, 1:-1, 3:] - 2.0 * vf + v[:, 1:-1, 1:-2]) / dy**2
    gpy = (p[:, :, 1:] - p[:, :, :-1]) / dy
    dv = -dvv - duv_x + nu * lap_v - gpy
    if v_source is not None:
        dv = dv + v_source
    v_star = v.clone()
    v_star[:, 1:-1, 2:-1] = vf + dt * dv
    return u_star, v_star


def divergence(u: torch.Tensor, v: torch.Tensor, dx: float, dy: float) -> torch.Tensor:
    """Discrete divergence in the cells, ``[B, nx, ny]``."""
    return (u[:, 2:, 1:-1] - u[:, 1:-1, 1:-1]) / dx + (v[:, 1:-1, 2:] - v[:, 1:-1, 1:-1]) / dy


def project(
    u: torch.Tensor,
    v: torch.Tensor,
    p: torch.Tensor,
    solver: PoissonSolver,
    dt: float,
    dx: float,
    dy: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Incremental projection: L phi = div(u*) / dt, u = u* - dt grad phi on the faces
    the boundary conditions leave free, p += phi."""
    phi = solver.solve(divergence(u, v, dx, dy) / dt)
    u, v = u.clone(), v.clone()
    u[:, 2:-1, 1:-1] = u[:, 2:-1, 1:-1] - dt * (phi[:, 1:] - phi[:, :-1]) / dx
    v[:, 1:-1, 2:-1] = v[:, 1:-1, 2:-1] - dt * (phi[:, :, 1:] - phi[:, :, :-1]) / dy
    # a zero-ghost wall carries the increment's gradient across it; correcting that face
    # too keeps the divergence exactly zero (the published Jacobi solve leaves it at its
    # tolerance)
    left, right, bottom, top = solver.bc
    if left == ZERO_GHOST:
        u[:, 1, 1:-1] = u[:, 1, 1:-1] - dt * phi[:, 0] / dx
    if right == ZERO_GHOST:
        u[:, -1, 1:-1] = u[:, -1, 1:-1] + dt * phi[:, -1] / dx
    if bottom == ZERO_GHOST:
        v[:, 1:-1, 1] = v[:, 1:-1, 1] - dt * phi[:, :, 0] / dy
    if top == ZERO_GHOST:
        v[:, 1:-1, -1] = v[:, 1:-1, -1] + dt * phi[:, :, -1] / dy
    return u, v, p + phi


def transport(s: torch.Tensor, u: torch.Tensor, v: torch.Tensor, kappa, dt: float, dx: float, dy: float) -> torch.Tensor:
    """Explicit centred advection-diffusion of a cell-centred scalar with ghosts; returns
    the scalar with updated interior (the ghosts are the caller's boundary conditions)."""
    fx = u[:, 1:, 1:-1] * 0.5 * (s[:, :-1, 1:-1] + s[:, 1:, 1:-1])  # faces i = 1..nx+1
    fy = v[:, 1:-1, 1:] * 0.5 * (s[:, 1:-1, :-1] + s[:, 1:-1, 1:])  # faces j = 1..ny+1
    adv = (fx[:, 1:] - fx[:, :-1]) / dx + (fy[:, :, 1:] - fy[:, :, :-1]) / dy
    sc = s[:, 1:-1, 1:-1]
    lap = (s[:, 2:, 1:-1] - 2.0 * sc + s[:, :-2, 1:-1]) / dx**2 + (s[:, 1:-1, 2:] - 2.0 * sc + s[:, 1:-1, :-2]) / dy**2
    out = s.clone()
    out[:, 1:-1, 1:-1] = sc + dt * (-adv + kappa * lap)
    return out


def scalar_substeps(kappa: float, dt: float, dx: float, dy: float) -> int:
    """How many equal SSP-RK3 sub-steps keep the explicit diffusion of a scalar stable:
    the grid-scale mode's kappa dt' (4/dx^2 + 4/dy^2) must stay within RK3's stability
    interval on the negative real axis (2.51; 2.5 is used)."""
    number = kappa * dt * (4.0 / dx**2 + 4.0 / dy**2)
    return max(1, math.ceil(number / 2.5 - 1e-12))


def transport_rk3(
    s: torch.Tensor,
    u: torch.Tensor,
    v: torch.Tensor,
    kappa,
    dt: float,
    dx: float,
    dy: float,
    ghosts: Callable[[torch.Tensor], torch.Tensor],
    n_sub: int = 1,
) -> torch.Tensor:
    """Centred advection-diffusion of a scalar integrated with the three-stage SSP
    Runge-Kutta scheme (Shu & Osher), in ``n_sub`` sub-steps; ``ghosts`` applies the
    scalar's boundary conditions before each stage and to the result.

    The published code writes this transport as explicit centred; with forward Euler
    the centred advection of mixing's nearly inviscid scalar (cell Peclet 100) grows
    without bound within 20 actions, and rayleigh's diffusion number (2.37 for the
    grid-scale mode) is beyond forward Euler's bound of 2. RK3 keeps the same centred
    fluxes and is stable for both; it reproduces the published scores (docs)."""
    h = dt / n_sub

    def euler(f: torch.Tensor) -> torch.Tensor:
        return transport(ghosts(f), u, v, kappa, h, dx, dy)

    for _ in range(n_sub):
        s1 = euler(s)
        s2 = 0.75 * s + 0.25 * euler(s1)
        s = s / 3.0 + (2.0 / 3.0) * euler(s2)
    return ghosts(s)


def neumann_ghosts(s: torch.Tensor) -> torch.Tensor:
    """Zero normal gradient of a cell-centred scalar on every wall (corners included)."""
    s = s.clone()
    s[:, 0] = s[:, 1]
    s[:, -1] = s[:, -2]
    s[:, :, 0] = s[:, :, 1]
    s[:, :, -1] = s[:, :, -2]
    return s
