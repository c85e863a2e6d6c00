"""The batched incompressible solver (batch-last fields): direct Poisson solve,
ghost maps, predictor, projection, transport."""

import math

import pytest
import torch

from beacon_torch.numerics.projection import (
    GRADIENT,
    NEUMANN,
    ZERO_GHOST,
    Cavity,
    Ghosts,
    PoissonSolver,
    divergence,
    project,
    scalar_substeps,
    transport,
    transport_rk3,
)

BCS = [(NEUMANN,) * 4, (NEUMANN, NEUMANN, NEUMANN, ZERO_GHOST), (ZERO_GHOST, NEUMANN, ZERO_GHOST, NEUMANN)]
F64 = dict(dtype=torch.float64, device="cpu")


def random(shape, seed):
    return torch.randn(shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


@pytest.mark.parametrize("bc", BCS)
@pytest.mark.parametrize("nx", [30, 31])  # even: the folded x products; odd: the dense ones
def test_poisson_solve_is_exact_to_round_off(bc, nx):
    ny, dx, dy = 20, 1 / nx, 0.5 / 20
    solver = PoissonSolver(nx, ny, dx, dy, bc)
    assert solver.x.folded == (nx % 2 == 0 and bc[0] == bc[1])
    rhs = random((nx, ny, 4), 0)
    if ZERO_GHOST not in bc:  # solvable only for a zero-sum source
        rhs = rhs - rhs.mean((0, 1), keepdim=True)
    phi = solver.solve(rhs)
    scale = rhs.abs().max()
    assert (solver.apply(phi) - rhs).abs().max() < 1e-12 * scale * max(nx, ny) ** 2
    if ZERO_GHOST not in bc:
        assert phi.mean((0, 1)).abs().max() < 1e-12  # the constant mode is removed


def test_poisson_manufactured_solution_converges_at_second_order():
    errors = []
    for n in (16, 32, 64):
        h = 1.0 / n
        x = (torch.arange(n, dtype=torch.float64) + 0.5) * h
        X, Y = torch.meshgrid(x, x, indexing="ij")
        exact = torch.cos(math.pi * X) * torch.cos(2 * math.pi * Y)  # zero normal gradient
        rhs = -5 * math.pi**2 * exact
        phi = PoissonSolver(n, n, h, h).solve(rhs[..., None])[..., 0]
        errors.append((phi - exact).abs().max().item())
    orders = [math.log2(errors[i] / errors[i + 1]) for i in range(2)]
    assert all(1.9 < o < 2.1 for o in orders), orders


@pytest.mark.parametrize("bc", BCS)
def test_solver_matches_a_dense_reference_solve(bc):
    nx, ny = 6, 5
    solver = PoissonSolver(nx, ny, 0.2, 0.3, bc)
    dense = torch.kron(solver.lx, torch.eye(ny, dtype=torch.float64)) + torch.kron(torch.eye(nx, dtype=torch.float64), solver.ly)
    rhs = random(nx * ny, 1)
    if ZERO_GHOST not in bc:
        rhs = rhs - rhs.mean()
        expected = torch.linalg.lstsq(dense, rhs[:, None]).solution[:, 0]
        expected = expected - expected.mean()
    else:
        expected = torch.linalg.solve(dense, rhs)
    got = solver.solve(rhs.reshape(nx, ny, 1))[..., 0]
    torch.testing.assert_close(got, expected.reshape(nx, ny), rtol=1e-10, atol=1e-12)


def test_members_are_solved_independently():
    solver = PoissonSolver(12, 10, 0.1, 0.1, BCS[1])
    rhs = random((12, 10, 3), 2)
    alone = solver.solve(rhs[..., 1:2])
    torch.testing.assert_close(solver.solve(rhs)[..., 1:2], alone, rtol=0, atol=1e-14)


def filled(cavity: Cavity, B: int, seed: int, walls=None):
    """Random face velocities with impermeable walls."""
    nx, ny = cavity.nx, cavity.ny
    u = random((nx + 1, ny, B), seed)
    v = random((nx, ny + 1, B), seed + 1)
    u[0], u[-1], v[:, 0], v[:, -1] = 0.0, 0.0, 0.0, 0.0
    return u, v


@pytest.mark.parametrize("bc", BCS[:2])
def test_projection_leaves_every_member_divergence_free(bc):
    B, nx, ny = 3, 24, 18
    cavity = Cavity(nx, ny, 1 / 24, 0.75 / 18, bc, **F64)
    u, v = filled(cavity, B, 1)
    assert divergence(u, v, cavity.dx, cavity.dy).abs().max() > 1.0
    u2, v2, p = project(u, v, torch.zeros(nx, ny, B, dtype=torch.float64), cavity.solver, 0.01, cavity.dx, cavity.dy)
    assert divergence(u2, v2, cavity.dx, cavity.dy).abs().max() < 1e-10
    # the walls stay impermeable where the increment has zero normal gradient
    assert (u2[0] == 0).all() and (u2[-1] == 0).all() and (v2[:, 0] == 0).all()
    if bc[3] == NEUMANN:
        assert (v2[:, -1] == 0).all()
    else:  # the zero-ghost top carries the correction that keeps the divergence zero
        assert v2[:, -1].abs().max() > 1e-3


def test_wall_ghosts_impose_the_wall_velocities_per_member():
    cavity = Cavity(6, 5, 0.2, 0.2, **F64)
    u, v = filled(cavity, 2, 3)
    v_left = torch.tensor([2.0, -0.5], dtype=torch.float64)
    off_u, off_v = cavity.walls(0.3, -1.0, v_left, 0.0, like=u)
    ue, ve = cavity.u_ghosts(u, off_u), cavity.v_ghosts(v, off_v)
    assert ue.shape == (6 + 1, 5 + 2, 2) and ve.shape == (6 + 2, 5 + 1, 2)
    interior = slice(1, -1)  # the interior faces
    torch.testing.assert_close(0.5 * (ue[interior, 0] + ue[interior, 1]), torch.full_like(ue[interior, 0], 0.3))
    torch.testing.assert_close(0.5 * (ue[interior, -1] + ue[interior, -2]), torch.full_like(ue[interior, 0], -1.0))
    torch.testing.assert_close(0.5 * (ve[0, interior] + ve[1, interior]), v_left.expand_as(ve[0, interior]))
    torch.testing.assert_close(0.5 * (ve[-1, interior] + ve[-2, interior]), torch.zeros_like(ve[0, interior]))
    # the predictor sees impermeable walls
    assert (ue[0, 1:-1] == 0).all() and (ue[-1, 1:-1] == 0).all() and (ve[1:-1, 0] == 0).all()


def test_fields_and_stored_round_trip_the_batch_first_state():
    cavity = Cavity(8, 6, 0.125, 1 / 6, **F64)
    B = 3
    u = torch.zeros(B, 10, 8, dtype=torch.float64)
    v = torch.zeros(B, 10, 8, dtype=torch.float64)
    u[:, 2:-1, 1:-1] = random((B, 7, 6), 4)
    v[:, 1:-1, 2:-1] = random((B, 8, 5), 5)
    c = random((B, 10, 8), 6)
    state = {"u": u, "v": v, "p": random((B, 8, 6), 7), "c": c}
    ghosts = Ghosts.cells(8, 6, *(GRADIENT,) * 4, **F64)
    fields = cavity.fields(state, {"c": (ghosts, None)})
    assert fields["u"].shape == (9, 6, B) and fields["v"].shape == (8, 7, B) and fields["c"].shape == (10, 8, B)
    back = cavity.stored(fields, cavity.walls(like=fields["u"]))
    for name in ("u", "v", "c"):
        torch.testing.assert_close(back[name][:, 1:-1, 1:-1], state[name][:, 1:-1, 1:-1], rtol=0, atol=0)
    torch.testing.assert_close(back["p"], state["p"], rtol=0, atol=0)
    # zero-gradient ghosts of the scalar
    torch.testing.assert_close(back["c"][:, 0, 1:-1], back["c"][:, 1, 1:-1])


def test_fluid_at_rest_stays_at_rest_and_hydrostatic_balance_holds():
    n, h = 10, 0.1
    cavity = Cavity(n, n, h, h, **F64)
    fields = {"u": torch.zeros(n + 1, n, 1, dtype=torch.float64), "v": torch.zeros(n, n + 1, 1, dtype=torch.float64), "p": torch.zeros(n, n, 1, dtype=torch.float64)}
    # a uniform upward force is balanced by the pressure after one projection
    source = torch.ones(n, n - 1, 1, dtype=torch.float64)
    us, vs = cavity.predict(fields, None, 0.01, 0.01, source)
    u2, v2, p2 = project(us, vs, fields["p"], cavity.solver, 0.01, h, h)
    assert u2.abs().max() < 1e-13 and v2.abs().max() < 1e-13
    assert (p2[:, 1:] - p2[:, :-1]).sub(h).abs().max() < 1e-12  # dp/dy = 1


def test_transport_conserves_the_scalar_and_keeps_constants():
    B, nx, ny = 2, 16, 12
    cavity = Cavity(nx, ny, 1 / 16, 1 / 12, **F64)
    u, v = filled(cavity, B, 8)
    u, v, _ = project(u, v, torch.zeros(nx, ny, B, dtype=torch.float64), cavity.solver, 1.0, cavity.dx, cavity.dy)
    ghosts = Ghosts.cells(nx, ny, *(GRADIENT,) * 4, **F64)
    s = ghosts(torch.rand((nx, ny, B), generator=torch.Generator().manual_seed(9), dtype=torch.float64))
    out = transport(s, u, v, 0.01, 1e-3, cavity.dx, cavity.dy)
    torch.testing.assert_close(out.sum((0, 1)), s[1:-1, 1:-1].sum((0, 1)), rtol=1e-13, atol=1e-12)
    const = torch.full_like(s, 0.7)
    torch.testing.assert_close(transport(const, u, v, 0.01, 1e-3, cavity.dx, cavity.dy), const[1:-1, 1:-1], rtol=0, atol=1e-12)
    rk3 = transport_rk3(s, u, v, 0.01, 1e-3, cavity.dx, cavity.dy, ghosts)
    assert rk3.shape == s.shape
    torch.testing.assert_close(rk3[1:-1, 1:-1].sum((0, 1)), s[1:-1, 1:-1].sum((0, 1)), rtol=1e-13, atol=1e-12)


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
    u = torch.zeros(n + 1, n, 1, dtype=torch.float64)
    v = torch.full((n, n + 1, 1), speed, dtype=torch.float64)  # uniform, divergence-free
    i = torch.arange(n + 2)
    s = ((-1.0) ** (i[:, None] + i[None, :])).to(torch.float64)[..., None] * 1e-3
    keep = lambda interior: torch.nn.functional.pad(interior, (0, 0, 1, 1, 1, 1))  # noqa: E731
    euler = rk3 = s
    for _ in range(200):
        euler = keep(transport(euler, u, v, kappa, dt, h, h))
        rk3 = transport_rk3(rk3, u, v, kappa, dt, h, h, keep)
    interior = lambda f: f[3:-3, 3:-3].abs().max().item()  # noqa: E731
    assert interior(rk3) < 1e-4
    assert interior(euler) > 1.0
