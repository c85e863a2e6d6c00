"""The batched incompressible solver (batch-last fields): direct Poisson solve,
ghost maps, predictor, projection, transport."""

import math
import shutil
import warnings

import pytest
import torch

from beacon_torch.numerics import native
from beacon_torch.numerics.grid import GRADIENT, NEUMANN, ZERO_GHOST, Ghosts
from beacon_torch.numerics.poisson import JacobiSolver, PoissonSolver
from beacon_torch.numerics.projection import Cavity, Flow
from beacon_torch.numerics.staggered import Stretched, divergence, project, tendency

BCS = [(NEUMANN,) * 4, (NEUMANN, NEUMANN, NEUMANN, ZERO_GHOST), (ZERO_GHOST, NEUMANN, ZERO_GHOST, NEUMANN)]
F64 = dict(dtype=torch.float64, device="cpu")


def random(shape, seed):
    return torch.randn(shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


@pytest.fixture(params=["C", "tensors"])
def native_path(request, monkeypatch):
    """Both ways the sweep and the Poisson solve run without gradients: the C kernels
    (where a compiler is, which they must then be built with) and the tensor path."""
    if request.param == "C":
        if shutil.which("cc") is None and shutil.which("gcc") is None:
            pytest.skip("no C compiler")
        assert native.applies("cpu", torch.float64)
    else:
        monkeypatch.setenv("BEACON_TORCH_NATIVE", "0")
    return request.param


@pytest.mark.parametrize("bc", BCS)
@pytest.mark.parametrize("nx", [30, 31])  # even: the folded x products; odd: the dense ones
@pytest.mark.parametrize("members", [4, 40])  # y products as one matrix product, or batched over x
def test_poisson_solve_is_exact_to_round_off(bc, nx, members, native_path):
    ny, dx, dy = 20, 1 / nx, 0.5 / 20
    solver = PoissonSolver(nx, ny, dx, dy, bc)
    assert solver.native == (native_path == "C")
    assert solver.x.folded == (nx % 2 == 0 and bc[0] == bc[1])
    rhs = random((nx, ny, members), 0)
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
def test_solver_matches_a_dense_reference_solve(bc, native_path):
    nx, ny = 6, 5
    solver = PoissonSolver(nx, ny, 0.2, 0.3, bc)
    dense = torch.kron(solver.lx, torch.eye(ny, dtype=torch.float64)) + torch.kron(
        torch.eye(nx, dtype=torch.float64), solver.ly
    )
    rhs = random(nx * ny, 1)
    if ZERO_GHOST not in bc:
        rhs = rhs - rhs.mean()
        expected = torch.linalg.lstsq(dense, rhs[:, None]).solution[:, 0]
        expected = expected - expected.mean()
    else:
        expected = torch.linalg.solve(dense, rhs)
    got = solver.solve(rhs.reshape(nx, ny, 1))[..., 0]
    torch.testing.assert_close(got, expected.reshape(nx, ny), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("members", [3, 40])
def test_members_are_solved_independently(members, native_path):
    """A member's solution does not depend on the others, nor on how many there are
    (few members take another order of the same products: equal to round-off)."""
    solver = PoissonSolver(12, 10, 0.1, 0.1, BCS[1])
    rhs = random((12, 10, members), 2)
    alone = solver.solve(rhs[..., 1:2])
    torch.testing.assert_close(solver.solve(rhs)[..., 1:2], alone, rtol=0, atol=1e-14)


@pytest.mark.parametrize("bc", BCS[:2])
def test_poisson_paths_agree_in_float32_with_gradients_or_without(bc):
    """The C line solves against the y eigenvector products at a cavity's size, in
    float32; with autograd recording, the C path keeps the graph (its adjoint:
    tests/test_adjoints.py)."""
    n, members = 64, 5
    fast = PoissonSolver(n, n, 1 / n, 1 / n, bc, dtype=torch.float32)
    rhs = random((n, n, members), 9)
    rhs = (rhs - rhs.mean((0, 1))).float()
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("BEACON_TORCH_NATIVE", "0")
        slow = PoissonSolver(n, n, 1 / n, 1 / n, bc, dtype=torch.float32)
    assert not slow.native
    expected = slow.solve(rhs)
    scale = expected.abs().max()
    torch.testing.assert_close(fast.solve(rhs), expected, rtol=0, atol=2e-5 * scale)
    if fast.native:
        with pytest.raises(ValueError, match="do not fit"):
            native.lines(rhs, *fast.lines[0], fast.upper, fast.width)
    grad_in = rhs.clone().requires_grad_()
    with torch.enable_grad():
        out = fast.solve(grad_in)
    assert out.grad_fn is not None
    torch.testing.assert_close(out.detach(), expected, rtol=0, atol=2e-5 * scale)


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
    div = divergence(u2, v2, cavity.dx, cavity.dy)
    if bc[3] == ZERO_GHOST:
        # as published, the top wall keeps v = 0, so the top cells keep the divergence
        # the zero-ghost increment leaves there
        assert div[:, -1].abs().max() > 1e-3
        div = div[:, :-1]
    assert div.abs().max() < 1e-10
    # the walls stay impermeable where the increment has zero normal gradient
    assert (u2[0] == 0).all() and (u2[-1] == 0).all() and (v2[:, 0] == 0).all()
    assert (v2[:, -1] == 0).all()


@pytest.mark.parametrize("bc", BCS)
def test_the_walled_correction_reads_the_increment_as_its_ghosted_field_does(bc):
    # the interior faces' pressure gradient, taken from the increment's cells, is the
    # one taken from its ghost-extended field, to the last bit, and so is its gradient
    B, nx, ny, dt = 3, 12, 10, 0.01
    cavity = Cavity(nx, ny, 1 / 12, 0.8 / 10, bc, **F64)
    u, v = filled(cavity, B, 5)
    p = random((nx, ny, B), 7)
    u, v, p = (t.requires_grad_() for t in (u, v, p))

    def ghosted(u, v, p):
        solver = cavity.solver
        phi = solver.solve(divergence(u, v, cavity.dx, cavity.dy) / dt)
        ext = solver.ghosts(phi)
        gx = torch.nn.functional.pad((ext[2:-1, 1:-1] - ext[1:-2, 1:-1]) / cavity.dx, (0, 0, 0, 0, 1, 1))
        gy = torch.nn.functional.pad((ext[1:-1, 2:-1] - ext[1:-1, 1:-2]) / cavity.dy, (0, 0, 1, 1))
        return u - dt * gx, v - dt * gy, p + phi

    weights = [random(t.shape, 11 + k) for k, t in enumerate((u, v, p))]
    outputs = {}
    for name, fn in (("cells", lambda *a: project(*a, cavity.solver, dt, cavity.dx, cavity.dy)), ("ghosts", ghosted)):
        out = fn(u, v, p)
        grads = torch.autograd.grad(sum((w * o).sum() for w, o in zip(weights, out, strict=True)), (u, v, p))
        outputs[name] = ([o.detach() for o in out], grads)
    for a, b in zip(outputs["cells"][0], outputs["ghosts"][0], strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    for a, b in zip(outputs["cells"][1], outputs["ghosts"][1], strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12 * float(b.abs().max()))


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


def stretched(widths, dim: int) -> Stretched:
    """An axis of the given cell widths along ``dim`` (0: x, 1: y), ghost centres
    mirrored beyond its ends."""
    w = torch.as_tensor(widths, dtype=torch.float64)
    gaps = torch.cat((w[:1], 0.5 * (w[1:] + w[:-1]), w[-1:]))
    shaped = lambda t: t.reshape((-1, 1, 1) if dim == 0 else (1, -1, 1))
    return Stretched(shaped(w), shaped(gaps), dim)


def test_the_explicit_terms_on_equal_stretched_cells_are_the_uniform_ones():
    nx, ny, members = 7, 5, 2
    u, v = random((nx + 1, ny + 2, members), 1), random((nx + 2, ny + 1, members), 2)
    uniform = tendency(u, v, 0.01, 0.2, 0.3)
    on_stretched = tendency(u, v, 0.01, stretched([0.2] * nx, 0), stretched([0.3] * ny, 1))
    for a, b in zip(uniform, on_stretched, strict=True):
        assert a.shape == b.shape
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("dim", [0, 1])
def test_stretched_differences_are_exact_where_the_scheme_is_second_order(dim):
    widths = 0.1 * 1.05 ** torch.arange(8, dtype=torch.float64)
    axis = stretched(widths, dim)
    along = lambda t: t.reshape((-1, 1, 1) if dim == 0 else (1, -1, 1))
    faces = torch.cat((widths.new_zeros(1), widths.cumsum(0)))
    centres = faces[:-1] + 0.5 * widths
    ghosted = torch.cat((centres[:1] - widths[:1], centres, centres[-1:] + widths[-1:]))
    part = lambda t, a, b: t.narrow(dim, a, t.shape[dim] + b - a)
    # a quadratic on the faces: its second derivative at the interior faces, exactly
    f = along(faces**2)
    torch.testing.assert_close(
        axis.second(part(f, 0, -2), part(f, 1, -1), part(f, 2, 0), faces=True), torch.full_like(part(f, 1, -1), 2.0)
    )
    # a linear field on the ghosted cells has none
    g = along(3.0 * ghosted + 1.0)
    assert axis.second(part(g, 0, -2), part(g, 1, -1), part(g, 2, 0), faces=False).abs().max() < 1e-12
    # a linear flux: its difference over the control volumes of the interior faces
    # (from the cells) and of the cells (from the faces) is its slope
    flux_cells, flux_faces = along(3.0 * centres), along(3.0 * faces)
    torch.testing.assert_close(
        axis.difference(part(flux_cells, 1, 0) - part(flux_cells, 0, -1), faces=True),
        torch.full_like(part(flux_cells, 1, 0), 3.0),
    )
    torch.testing.assert_close(
        axis.difference(part(flux_faces, 1, 0) - part(flux_faces, 0, -1), faces=False),
        torch.full_like(part(flux_faces, 1, 0), 3.0),
    )


def test_a_flow_goes_to_the_solver_and_back_to_the_batch_first_state():
    cavity = Cavity(8, 6, 0.125, 1 / 6, **F64)
    B = 3
    u = torch.zeros(B, 10, 8, dtype=torch.float64)
    v = torch.zeros(B, 10, 8, dtype=torch.float64)
    u[:, 2:-1, 1:-1] = random((B, 7, 6), 4)
    v[:, 1:-1, 2:-1] = random((B, 8, 5), 5)
    flow = Flow(u=u, v=v, p=random((B, 8, 6), 7), scalar=random((B, 10, 8), 6))
    ghosts = Ghosts.cells(8, 6, *(GRADIENT,) * 4, **F64)
    solver = cavity.to_solver(flow, ghosts)
    assert isinstance(solver, Flow)
    assert solver.u.shape == (9, 6, B) and solver.v.shape == (8, 7, B) and solver.scalar.shape == (10, 8, B)
    back = cavity.to_state(solver, cavity.walls(like=solver.u))
    assert isinstance(back, Flow)
    for name in ("u", "v", "scalar"):
        expected = getattr(flow, name)[:, 1:-1, 1:-1]
        torch.testing.assert_close(getattr(back, name)[:, 1:-1, 1:-1], expected, rtol=0, atol=0)
    torch.testing.assert_close(back.p, flow.p, rtol=0, atol=0)
    # zero-gradient ghosts of the scalar
    torch.testing.assert_close(back.scalar[:, 0, 1:-1], back.scalar[:, 1, 1:-1])


def test_fluid_at_rest_stays_at_rest_and_hydrostatic_balance_holds():
    n, h = 10, 0.1
    cavity = Cavity(n, n, h, h, **F64)
    zeros = lambda *shape: torch.zeros(*shape, 1, dtype=torch.float64)
    flow = Flow(u=zeros(n + 1, n), v=zeros(n, n + 1), p=zeros(n, n), scalar=zeros(n + 2, n + 2))
    # a uniform upward force is balanced by the pressure after one projection
    source = torch.ones(n, n - 1, 1, dtype=torch.float64)
    us, vs = cavity.predict(flow, None, 0.01, 0.01, source)
    u2, v2, p2 = project(us, vs, flow.p, cavity.solver, 0.01, h, h)
    assert u2.abs().max() < 1e-13 and v2.abs().max() < 1e-13
    assert (p2[:, 1:] - p2[:, :-1]).sub(h).abs().max() < 1e-12  # dp/dy = 1


def published_sweep(s, u, v, kappa, dt, dx, dy):
    """The published transport literally: cell after cell, x outer, y inner, updating
    the array in place (ghosted indices, u on west faces, v on south faces)."""
    t = s.clone()
    nx, ny = t.shape[0] - 2, t.shape[1] - 2
    for i in range(1, nx + 1):
        for j in range(1, ny + 1):
            ue, uw, vn, vs = u[i, j - 1], u[i - 1, j - 1], v[i - 1, j], v[i - 1, j - 1]
            te, tw = 0.5 * (t[i + 1, j] + t[i, j]), 0.5 * (t[i - 1, j] + t[i, j])
            tn, ts = 0.5 * (t[i, j + 1] + t[i, j]), 0.5 * (t[i, j - 1] + t[i, j])
            conv = (ue * te - uw * tw) / dx + (vn * tn - vs * ts) / dy
            diff = kappa * (
                (t[i + 1, j] - 2 * t[i, j] + t[i - 1, j]) / dx**2 + (t[i, j + 1] - 2 * t[i, j] + t[i, j - 1]) / dy**2
            )
            t[i, j] = t[i, j] + dt * (diff - conv)
    return t[1:-1, 1:-1]


@pytest.mark.parametrize("shape", [(7, 5), (4, 9)])
def test_sweep_is_the_published_in_place_transport(shape, native_path):
    nx, ny = shape
    B = 3
    cavity = Cavity(nx, ny, 1 / nx, 0.8 / ny, **F64)
    u, v = filled(cavity, B, 11)
    s = random((nx + 2, ny + 2, B), 12)
    kappa = torch.tensor([0.01, 0.05, 0.2], dtype=torch.float64)  # one per member
    out = cavity.sweep(s, u, v, kappa, 2e-3, cavity.dx, cavity.dy)
    for m in range(B):
        expected = published_sweep(s[..., m], u[..., m], v[..., m], kappa[m].item(), 2e-3, cavity.dx, cavity.dy)
        torch.testing.assert_close(out[..., m], expected, rtol=1e-13, atol=1e-13)
    # with gradients wanted (the C loop and its reverse, or the tensor recurrence kept
    # out of place as a graph), the same recurrence
    with torch.enable_grad():
        graph = cavity.sweep(s.clone().requires_grad_(), u, v, kappa, 2e-3, cavity.dx, cavity.dy)
    torch.testing.assert_close(graph.detach(), out, rtol=1e-14, atol=1e-14)


def test_c_sweep_keeps_the_ghosts_it_was_given():
    if not native.applies("cpu", torch.float64):
        pytest.skip("no C compiler")
    nx, ny, B = 5, 4, 3
    s = random((nx + 2, ny + 2, B), 13)
    a, b = random((nx, ny, B), 14) * 0.1, random((nx, ny, B), 15) * 0.1
    out = native.sweep(s, a, b)
    ring = torch.ones(nx + 2, ny + 2, dtype=torch.bool)
    ring[1:-1, 1:-1] = False
    assert torch.equal(out[ring], s[ring])
    # the first interior cell reads its ghost neighbours only
    torch.testing.assert_close(out[1, 1], s[1, 1] + a[0, 0] * s[0, 1] + b[0, 0] * s[1, 0], rtol=1e-15, atol=0)


def test_sweep_paths_agree_in_float32():
    nx, ny, B = 20, 30, 5
    cavity = Cavity(nx, ny, 1 / nx, 1 / ny, dtype=torch.float32, device=None)
    u, v = (f.float() for f in filled(Cavity(nx, ny, 1 / nx, 1 / ny, **F64), B, 3))
    s = random((nx + 2, ny + 2, B), 4).float()
    fast = cavity.sweep(s, u, v, 0.01, 1e-3, cavity.dx, cavity.dy)
    if cavity.sweep.native:
        with pytest.raises(ValueError, match="do not fit"):
            native.sweep(s.clone(), fast[:, :-1].contiguous(), fast[:, :-1].contiguous())
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("BEACON_TORCH_NATIVE", "0")
        tensor_path = Cavity(nx, ny, 1 / nx, 1 / ny, dtype=torch.float32, device=None)
    assert not tensor_path.sweep.native
    slow = tensor_path.sweep(s, u, v, 0.01, 1e-3, cavity.dx, cavity.dy)
    # the two paths sum the same few float32 terms in another order: each value is s,
    # of order one, plus a small correction, so they differ by a few of float32's
    # epsilons (1.2e-7) of order-one values; 1e-6 is eight of them
    torch.testing.assert_close(fast, slow, rtol=1e-6, atol=1e-6)


def test_sweep_without_a_compiler_warns_once_and_keeps_the_tensor_path(monkeypatch):
    monkeypatch.setattr(native, "_tried", False)
    monkeypatch.setattr(native, "_library", None)
    monkeypatch.setenv("CC", "false")  # a compiler that always fails
    nx, ny, B = 6, 5, 2
    with pytest.warns(RuntimeWarning, match="could not be built"):
        cavity = Cavity(nx, ny, 1 / nx, 1 / ny, **F64)
    assert not cavity.sweep.native
    u, v = filled(cavity, B, 1)
    s = random((nx + 2, ny + 2, B), 2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = cavity.sweep(s, u, v, 0.01, 1e-3, cavity.dx, cavity.dy)
        again = Cavity(nx, ny, 1 / nx, 1 / ny, **F64).sweep(s, u, v, 0.01, 1e-3, cavity.dx, cavity.dy)
    expected = torch.stack(
        [published_sweep(s[..., m], u[..., m], v[..., m], 0.01, 1e-3, cavity.dx, cavity.dy) for m in range(B)], -1
    )
    torch.testing.assert_close(out, expected, rtol=1e-13, atol=1e-13)
    assert torch.equal(out, again)


def test_a_compiled_loop_holds_the_tensor_sweep(monkeypatch):
    """Without the C kernels (a GPU, or a machine with no C compiler) a compiled step
    runs its substeps as one while_loop, which refuses a graph break: the sweep's
    tensor recurrence is taken into the graph, with the eager loop's numbers."""
    from beacon_torch.compiled import Kernels

    monkeypatch.setenv("BEACON_TORCH_NATIVE", "0")
    nx, ny, B = 6, 5, 2
    cavity = Cavity(nx, ny, 1 / nx, 1 / ny, **F64)
    assert not cavity.sweep.native
    u, v = filled(cavity, B, 1)
    s = random((nx + 2, ny + 2, B), 2)
    ring = torch.ones_like(s)
    ring[1:-1, 1:-1] = 0

    def substep(i, s, u, v):
        swept = cavity.sweep(s, u, v, 0.01, 1e-3, cavity.dx, cavity.dy)
        return torch.nn.functional.pad(swept, (0, 0, 1, 1, 1, 1)) + ring * s

    kernels = Kernels()
    loop = kernels.loop(substep)
    eager = loop(3, s, u, v)
    kernels.compile()
    torch.testing.assert_close(loop(3, s, u, v), eager, rtol=1e-13, atol=1e-13)


def test_sweep_keeps_constants_in_a_divergence_free_flow():
    B, nx, ny = 2, 16, 12
    cavity = Cavity(nx, ny, 1 / 16, 1 / 12, **F64)
    u, v = filled(cavity, B, 8)
    u, v, _ = project(u, v, torch.zeros(nx, ny, B, dtype=torch.float64), cavity.solver, 1.0, cavity.dx, cavity.dy)
    const = torch.full((nx + 2, ny + 2, B), 0.7, dtype=torch.float64)
    torch.testing.assert_close(
        cavity.sweep(const, u, v, 0.01, 1e-3, cavity.dx, cavity.dy), const[1:-1, 1:-1], rtol=0, atol=1e-12
    )


def test_sweep_is_stable_at_rayleighs_diffusion_number():
    """rayleigh's numbers: plain forward Euler amplifies the temperature's grid-scale
    checkerboard (diffusion number 2.37 > 2); the published in-place sweep damps it."""
    kappa, dt, h, n = 1 / math.sqrt(0.71e4), 0.01, 0.02, 20
    cavity = Cavity(n, n, h, h, **F64)
    u = torch.zeros(n + 1, n, 1, dtype=torch.float64)
    v = torch.zeros(n, n + 1, 1, dtype=torch.float64)
    i = torch.arange(n + 2)
    s = ((-1.0) ** (i[:, None] + i[None, :])).to(torch.float64)[..., None] * 1e-3
    keep = lambda interior: torch.nn.functional.pad(interior, (0, 0, 1, 1, 1, 1))
    swept = s
    for _ in range(200):
        swept = keep(cavity.sweep(swept, u, v, kappa, dt, h, h))
    assert swept[3:-3, 3:-3].abs().max().item() < 1e-4


@pytest.mark.parametrize("bc", BCS[:2])
def test_jacobi_solver_converges_to_the_direct_solve_and_stops_per_member(bc):
    nx, ny, B = 12, 10, 2
    direct = PoissonSolver(nx, ny, 1 / nx, 1 / ny, bc, **F64)
    rhs = random((nx, ny, B), 5)
    rhs = rhs - rhs.mean((0, 1))  # compatible with zero normal gradient everywhere
    rhs[..., 1] *= 1e-3  # the second member is small: it stops earlier
    exact = direct.solve(rhs)
    jacobi = JacobiSolver(nx, ny, 1 / nx, 1 / ny, bc, 1e-22, **F64)
    phi = jacobi.solve(rhs)
    # the Neumann problem fixes phi up to a constant
    shift = lambda f: f - f.mean((0, 1)) if bc[3] == NEUMANN else f
    torch.testing.assert_close(shift(phi), shift(exact), rtol=0, atol=1e-6 * exact.abs().max().item())
    loose = JacobiSolver(nx, ny, 1 / nx, 1 / ny, bc, 1e-6, **F64)
    one = loose.solve(rhs[..., :1])
    both = loose.solve(rhs)
    # a member's answer does not depend on the others still iterating
    torch.testing.assert_close(both[..., :1], one, rtol=0, atol=0)


def test_jacobi_solver_refuses_compilation():
    solver = JacobiSolver(4, 4, 0.25, 0.25, (NEUMANN,) * 4, 1e-8, **F64)
    compiled = torch.compile(solver.solve, fullgraph=True)
    with pytest.raises(Exception, match="eagerly only"):
        compiled(torch.zeros(4, 4, 1, dtype=torch.float64))


def test_the_dict_methods_of_a_cavity_name_their_typed_replacements():
    cavity = Cavity(4, 4, 0.25, 0.25, **F64)
    with pytest.raises(AttributeError, match=r"Cavity.fields is now Cavity.to_solver, which takes and gives a Flow"):
        cavity.fields({}, {})
    with pytest.raises(AttributeError, match=r"Cavity.stored is now Cavity.to_state"):
        cavity.stored({}, None)
