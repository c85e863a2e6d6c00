"""The batched incompressible solver: direct Poisson solve, projection, transport."""

import math

import pytest
import torch

from beacon_torch.numerics.projection import (
    NEUMANN,
    ZERO_GHOST,
    PoissonSolver,
    divergence,
    neumann_ghosts,
    predict,
    project,
    scalar_substeps,
    transport,
    transport_rk3,
    wall_velocities,
)

BCS = [(NEUMANN,) * 4, (NEUMANN, NEUMANN, NEUMANN, ZERO_GHOST)]


@pytest.mark.parametrize("bc", BCS)
def test_poisson_solve_is_exact_to_round_off(bc):
    nx, ny, dx, dy = 30, 20, 1 / 30, 0.5 / 20
    solver = PoissonSolver(nx, ny, dx, dy, bc)
    g = torch.Generator().manual_seed(0)
    rhs = torch.randn((4, nx, ny), generator=g, dtype=torch.float64)
    if bc[3] == NEUMANN:  # solvable only for a zero-sum source
        rhs = rhs - rhs.mean((1, 2), keepdim=True)
    phi = solver.solve(rhs)
    scale = rhs.abs().max()
    assert (solver.apply(phi) - rhs).abs().max() < 1e-12 * scale * max(nx, ny) ** 2
    if bc[3] == NEUMANN:
        assert phi.mean((1, 2)).abs().max() < 1e-12  # the constant mode is removed


def test_poisson_manufactured_solution_converges_at_second_order():
    errors = []
    for n in (16, 32, 64):
        h = 1.0 / n
        x = (torch.arange(n, dtype=torch.float64) + 0.5) * h
        X, Y = torch.meshgrid(x, x, indexing="ij")
        exact = torch.cos(math.pi * X) * torch.cos(2 * math.pi * Y)  # zero normal gradient
        rhs = -5 * math.pi**2 * exact
        phi = PoissonSolver(n, n, h, h).solve(rhs[None])[0]
        errors.append((phi - exact).abs().max().item())
    orders = [math.log2(errors[i] / errors[i + 1]) for i in range(2)]
    assert all(1.9 < o < 2.1 for o in orders), orders


def test_solver_matches_a_dense_reference_solve():
    nx, ny = 6, 5
    solver = PoissonSolver(nx, ny, 0.2, 0.3, BCS[1])
    dense = torch.kron(solver.lx, torch.eye(ny, dtype=torch.float64)) + torch.kron(torch.eye(nx, dtype=torch.float64), solver.ly)
    rhs = torch.randn(nx * ny, dtype=torch.float64)
    expected = torch.linalg.solve(dense, rhs).reshape(nx, ny)
    torch.testing.assert_close(solver.solve(rhs.reshape(1, nx, ny))[0], expected, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("bc", BCS)
def test_projection_leaves_every_member_divergence_free(bc):
    B, nx, ny, dx, dy = 3, 24, 18, 1 / 24, 0.75 / 18
    g = torch.Generator().manual_seed(1)
    u = torch.randn((B, nx + 2, ny + 2), generator=g, dtype=torch.float64)
    v = torch.randn((B, nx + 2, ny + 2), generator=g, dtype=torch.float64)
    u, v = wall_velocities(u, v, 1.0, -1.0, torch.tensor([[0.5], [0.0], [-2.0]], dtype=torch.float64), 0.0)
    solver = PoissonSolver(nx, ny, dx, dy, bc)
    assert divergence(u, v, dx, dy).abs().max() > 1.0
    u2, v2, p = project(u, v, torch.zeros(B, nx, ny, dtype=torch.float64), solver, 0.01, dx, dy)
    assert divergence(u2, v2, dx, dy).abs().max() < 1e-10
    # the walls stay impermeable where the increment has zero normal gradient
    assert (u2[:, 1, 1:-1] == 0).all() and (u2[:, -1, 1:-1] == 0).all() and (v2[:, 1:-1, 1] == 0).all()
    if bc[3] == NEUMANN:
        assert (v2[:, 1:-1, -1] == 0).all()


def test_wall_ghosts_impose_the_wall_velocities():
    u = torch.rand(2, 7, 6, dtype=torch.float64)
    v = torch.rand(2, 7, 6, dtype=torch.float64)
    u2, v2 = wall_velocities(u, v, u_bottom=0.3, u_top=-1.0, v_left=2.0, v_right=0.0)
    torch.testing.assert_close(0.5 * (u2[:, 1:-1, 0] + u2[:, 1:-1, 1]), torch.full_like(u2[:, 1:-1, 0], 0.3))
    torch.testing.assert_close(0.5 * (u2[:, 1:-1, -1] + u2[:, 1:-1, -2]), torch.full_like(u2[:, 1:-1, 0], -1.0))
    torch.testing.assert_close(0.5 * (v2[:, 0, 1:-1] + v2[:, 1, 1:-1]), torch.full_like(v2[:, 0, 1:-1], 2.0))
    assert (u2[:, 1, 1:-1] == 0).all() and (v2[:, 1:-1, -1] == 0).all()


def test_fluid_at_rest_stays_at_rest_and_hydrostatic_balance_holds():
    B, n, h = 1, 10, 0.1
    u = torch.zeros(B, n + 2, n + 2, dtype=torch.float64)
    v = torch.zeros_like(u)
    p = torch.zeros(B, n, n, dtype=torch.float64)
    solver = PoissonSolver(n, n, h, h)
    # a uniform upward force is balanced by the pressure after one projection
    source = torch.ones(B, n, n - 1, dtype=torch.float64)
    us, vs = predict(u, v, p, 0.01, 0.01, h, h, source)
    u2, v2, p2 = project(us, vs, p, solver, 0.01, h, h)
    assert u2.abs().max() < 1e-13 and v2.abs().max() < 1e-13
    assert (p2[:, :, 1:] - p2[:, :, :-1]).sub(h).abs().max() < 1e-12  # dp/dy = 1


def test_transport_conserves_the_scalar_and_keeps_constants():
    B, nx, ny, dx, dy = 2, 16, 12, 1 / 16, 1 / 12
    g = torch.Generator().manual_seed(2)
    u = torch.randn((B, nx + 2, ny + 2), generator=g, dtype=torch.float64)
    v = torch.randn((B, nx + 2, ny + 2), generator=g, dtype=torch.float64)
    u, v = wall_velocities(u, v, 1.0, 1.0, 1.0, 1.0)
    u, v, _ = project(u, v, torch.zeros(B, nx, ny, dtype=torch.float64), PoissonSolver(nx, ny, dx, dy), 1.0, dx, dy)
    s = neumann_ghosts(torch.rand((B, nx + 2, ny + 2), generator=g, dtype=torch.float64))
    out = transport(s, u, v, 0.01, 1e-3, dx, dy)
    total = lambda f: f[:, 1:-1, 1:-1].sum((1, 2))  # noqa: E731
    torch.testing.assert_close(total(out), total(s), rtol=1e-13, atol=1e-12)
    const = torch.full_like(s, 0.7)
    torch.testing.assert_close(transport(const, u, v, 0.01, 1e-3, dx, dy), const, rtol=0, atol=1e-12)


def test_scalar_substeps_keep_explicit_diffusion_stable():
    assert scalar_substeps(1e-4, 0.002, 0.01, 0.01) == 1
    # rayleigh: kappa = 1 / sqrt(0.71e4), dt = 0.01, dx = 0.02: 2.37 for the grid-scale
    # mode, within RK3's interval, beyond forward Euler's
    assert scalar_substeps(1 / math.sqrt(0.71e4), 0.01, 0.02, 0.02) == 1
    assert scalar_substeps(0.05, 0.01, 0.02, 0.02) == 4


def test_rk3_transport_is_stable_where_forward_euler_is_not():
    """rayleigh's numbers: forward Euler amplifies the grid-scale checkerboard of the
    temperature, RK3 damps it."""
    kappa, speed, dt, h = 1 / math.sqrt(0.71e4), 0.3, 0.01, 0.02
    n = 20
    u = torch.zeros(1, n + 2, n + 2, dtype=torch.float64)
    v = torch.full_like(u, speed)  # a uniform (divergence-free) flow through periodic-like data
    i = torch.arange(n + 2)
    s = ((-1.0) ** (i[:, None] + i[None, :])).to(torch.float64)[None] * 1e-3
    ident = lambda f: f  # noqa: E731
    euler = rk3 = s
    for _ in range(200):
        euler = transport(euler, u, v, kappa, dt, h, h)
        rk3 = transport_rk3(rk3, u, v, kappa, dt, h, h, ident)
    interior = lambda f: f[:, 3:-3, 3:-3].abs().max().item()  # noqa: E731
    assert interior(rk3) < 1e-4
    assert interior(euler) > 1.0
