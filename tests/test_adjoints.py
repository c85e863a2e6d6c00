"""The adjoints written beside the C loops: each gradient equals autograd's gradient of
the same computation written as tensor operations, to round-off in float64, on random
inputs and on a real state, agrees with central differences, and keeps working under
``torch.func`` (``vmap`` of ``grad``) and ``torch.compile``."""

import pytest
import torch
from torch.func import grad, vmap

import beacon_torch
from beacon_torch.numerics import native
from beacon_torch.numerics.grid import NEUMANN, ZERO_FACE, ZERO_GHOST
from beacon_torch.numerics.poisson import PoissonSolver
from beacon_torch.numerics.projection import Cavity
from beacon_torch.numerics.transport import Sweep, _graph_rows

pytestmark = pytest.mark.skipif(not native.applies("cpu", torch.float64), reason="no C compiler")
F64 = dict(dtype=torch.float64, device=None)


def rand(shape, seed: int, scale: float = 1.0) -> torch.Tensor:
    return scale * torch.randn(shape, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))


def tensor_path(monkeypatch, build):
    """What ``build()`` makes with the C kernels switched off: the computation as tensor
    operations, which autograd differentiates itself."""
    with monkeypatch.context() as mp:
        mp.setenv("BEACON_TORCH_NATIVE", "0")
        return build()


def gradients(fn, inputs, weight):
    """The gradient of ``(fn(*inputs) * weight).sum()`` with respect to each input."""
    inputs = [t.detach().clone().requires_grad_() for t in inputs]
    return torch.autograd.grad((fn(*inputs) * weight).sum(), inputs)


def sweep_inputs(nx: int, ny: int, members: int, seed: int):
    s = rand((nx + 2, ny + 2, members), seed)
    a = 0.3 * torch.rand((nx, ny, members), dtype=torch.float64, generator=torch.Generator().manual_seed(seed + 1))
    b = 0.3 * torch.rand((nx, ny, members), dtype=torch.float64, generator=torch.Generator().manual_seed(seed + 2))
    return s, a, b


def recurrence(sweep: Sweep, s: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """What :func:`native.sweep` computes, as the tensor recurrence of ``sweep`` (a
    :class:`Sweep` without the C kernels): autograd differentiates it itself."""
    pad = lambda f: torch.nn.functional.pad(f, (0, 0, 1, 1, 1, 1))
    rows = _graph_rows(sweep._skewed(s), sweep._skewed(pad(a)), sweep._skewed(pad(b)), sweep.nx + sweep.ny)
    interior = rows[sweep.unskew_k, sweep.unskew_i]
    return torch.cat((s[:1], torch.cat((s[1:-1, :1], interior, s[1:-1, -1:]), 1), s[-1:]))


@pytest.mark.parametrize("nx, ny", [(7, 5), (3, 9)])
def test_the_reverse_sweep_is_autograds_gradient_of_the_sweep(nx, ny, monkeypatch):
    """Random coefficients: the C adjoint of the in-place sweep against autograd through
    the tensor recurrence, for the field, its ghosts and both coefficients; and against
    central differences."""
    tensors = tensor_path(monkeypatch, lambda: Sweep(nx, ny, None, torch.float64))
    assert not tensors.native
    s, a, b = sweep_inputs(nx, ny, 3, seed=nx)
    weight = rand((nx + 2, ny + 2, 3), seed=99)
    expected = gradients(lambda s, a, b: recurrence(tensors, s, a, b), (s, a, b), weight)
    for got, want in zip(gradients(native.sweep, (s, a, b), weight), expected, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-13, atol=1e-13)
    s, a, b = (t[..., :1].clone().requires_grad_() for t in (s, a, b))
    assert torch.autograd.gradcheck(native.sweep, (s, a, b))


def test_the_transport_of_a_real_state_has_the_tensor_paths_gradient(monkeypatch):
    """rayleigh-v0's developed start: the temperature and face velocities of its cells
    swept as a substep sweeps them, the gradient with respect to all three by the C
    adjoint and by autograd through the tensor recurrence."""
    env = beacon_torch.make("rayleigh-v0", 2, dtype="float64")
    env.reset()
    state = env.state
    theta, u, v = (f.movedim(0, -1).contiguous() for f in (state.theta, state.u, state.v))
    nx, ny = theta.shape[0] - 2, theta.shape[1] - 2
    fast = Cavity(nx, ny, 1 / nx, 1 / ny, **F64)
    slow = tensor_path(monkeypatch, lambda: Cavity(nx, ny, 1 / nx, 1 / ny, **F64))
    assert fast.sweep.native and not slow.sweep.native
    u, v = u[:-1, 1:-1], v[1:-1, :-1]  # the faces (the ghosted arrays' last row or column aside)
    weight = rand((nx, ny, 2), seed=3)
    step = lambda sweep: lambda t, u, v: sweep(t, u, v, 0.01, 0.01, 1 / nx, 1 / ny)
    got = gradients(step(fast.sweep), (theta, u, v), weight)
    want = gradients(step(slow.sweep), (theta, u, v), weight)
    for g, w in zip(got, want, strict=True):
        torch.testing.assert_close(g, w, rtol=1e-12, atol=1e-12 * w.abs().max())


SOLVERS = {
    "walls": lambda: PoissonSolver(8, 10, 1 / 8, 1 / 10, (NEUMANN,) * 4, **F64),
    "open top": lambda: PoissonSolver(8, 10, 1 / 8, 1 / 10, (NEUMANN, NEUMANN, NEUMANN, ZERO_GHOST), **F64),
    "stretched": lambda: PoissonSolver.stretched(
        *stretched(2.0, NEUMANN, NEUMANN), *stretched(3.0, NEUMANN, ZERO_FACE), **F64
    ),
}


def stretched(length: float, low: str, high: str) -> tuple[torch.Tensor, torch.Tensor]:
    """A 1-D operator ``diag(1 / w) S`` of a stretched axis (cells growing away from a
    refined middle, as the wakes' grids), and its cells' widths."""
    from beacon_torch.numerics.staggered import Axis

    axis = Axis(length, 0.4 * length, 0.6 * length, 0.1, 1.3, 0.5)
    return axis.laplacian(low, high), axis.widths


@pytest.mark.parametrize("kind", sorted(SOLVERS))
def test_a_direct_solves_adjoint_is_the_same_solve(kind, monkeypatch):
    """The C line solves with their adjoint (the same solve, between two scalings by
    the cells' widths on a stretched grid) against autograd through the eigenvector
    products, on every kind of grid and wall; and against central differences."""
    fast, slow = SOLVERS[kind](), tensor_path(monkeypatch, SOLVERS[kind])
    assert fast.native and not slow.native
    nx, ny = fast.x.n, fast.qy.shape[0]
    rhs = rand((nx, ny, 3), seed=1)
    weight = rand((nx, ny, 3), seed=2)
    (got,), (want,) = gradients(fast.solve, (rhs,), weight), gradients(slow.solve, (rhs,), weight)
    if kind == "walls":
        # the two solves differ by the constant field, the walls' null space: the C one
        # gives the zero-mean solution of a source of zero sum (a divergence) and its
        # adjoint is exact for what it computes (central differences, below); the
        # gradients agree once the constant is taken out, which a divergence's
        # adjoint (the gradient of a field) never sees
        got = got - got.mean((0, 1))
    torch.testing.assert_close(got, want, rtol=1e-11, atol=1e-11 * want.abs().max())
    assert torch.autograd.gradcheck(fast.solve, (rhs[..., :1].clone().requires_grad_(),))


def test_the_adjoints_map_and_compile():
    """``vmap`` of ``grad`` through the sweep and the solve is each mapped value's own
    gradient; a compiled function of them differentiates to the eager gradient."""
    s, a, b = sweep_inputs(5, 4, 2, seed=7)
    several = torch.stack([s, 2.0 * s, -s])
    loss = lambda s: native.sweep(s, a, b).pow(2).sum()
    torch.testing.assert_close(vmap(grad(loss))(several), torch.stack([grad(loss)(x) for x in several]))
    solver = SOLVERS["walls"]()
    rhs = torch.stack([rand((8, 10, 2), seed=k) for k in range(3)])
    solved = lambda f: solver.solve(f).pow(2).sum()
    torch.testing.assert_close(vmap(grad(solved))(rhs), torch.stack([grad(solved)(f) for f in rhs]))

    def both(s, f):
        return native.sweep(s, a, b).sum() + solver.solve(f).pow(2).sum()

    s0, f0 = s.clone().requires_grad_(), rhs[0].clone().requires_grad_()
    expected = torch.autograd.grad(both(s0, f0), (s0, f0))
    compiled = torch.compile(both, fullgraph=True, dynamic=False)
    s1, f1 = s.clone().requires_grad_(), rhs[0].clone().requires_grad_()
    for got, want in zip(torch.autograd.grad(compiled(s1, f1), (s1, f1)), expected, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


@pytest.mark.slow(seconds=90)
def test_a_cavity_compiles_with_gradients_to_the_eager_gradient():
    """rayleigh-v0 with ``compile=True, differentiable=True`` (its sweep's recurrence
    once made dynamo refuse it), its substeps in chunks (of 2 here: a chunk of 8
    compiles for minutes in float64): one action's reward differentiates to the eager
    env's gradient, float64."""
    from tensordict import TensorDict

    grads = []
    for compiled in (False, True):
        env = beacon_torch.make("rayleigh-v0", 2, dtype="float64", compile=compiled, differentiable=True)
        env.physics.kernels.chunk = 2
        env.reset()
        action = torch.full((2, *env.action_spec.shape[1:]), 0.3, dtype=torch.float64, requires_grad=True)
        reward = env.step(TensorDict({env.action_key: action}, batch_size=env.batch_size))["next", "reward"]
        grads.append(torch.autograd.grad(reward.sum(), action)[0])
    assert grads[0].abs().sum() > 0
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-10, atol=1e-12)


def momentum_inputs(nx: int, ny: int, members: int, seed: int):
    """Ghosted face velocities ``u`` ``[nx + 1, ny + 2, B]``, ``v`` ``[nx + 2, ny + 1, B]``
    and weights of the two components of the terms."""
    u, v = rand((nx + 1, ny + 2, members), seed), rand((nx + 2, ny + 1, members), seed + 1)
    return u, v, rand((nx - 1, ny, members), seed + 2), rand((nx, ny - 1, members), seed + 3)


def stretched_spacings():
    """The two axes of a wake's grid (cells growing away from a refined box), as
    :func:`staggered.tendency` takes them, and their cells."""
    from beacon_torch.numerics.staggered import Axis, Stretched

    x, y = Axis(3.0, 1.0, 1.6, 0.1, 1.3, 0.5), Axis(2.0, 0.8, 1.2, 0.1, 1.2, 0.4)
    shaped = lambda t, dim: t.reshape((-1, 1, 1) if dim == 0 else (1, -1, 1))
    spacings = (
        Stretched(shaped(x.widths, 0), shaped(x.gaps, 0), 0),
        Stretched(shaped(y.widths, 1), shaped(y.gaps, 1), 1),
    )
    return spacings, (x.n, y.n)


def momentum_gradients(terms, u, v, nu, x, y, wu, wv):
    """The gradients of the weighted terms ``terms(u, v, nu, x, y)`` with respect to
    ``u``, ``v`` and (where it is a tensor) ``nu``."""
    inputs = [t.detach().clone().requires_grad_() for t in (u, v, *([nu] if isinstance(nu, torch.Tensor) else []))]
    hu, hv = terms(*inputs[:2], inputs[2] if len(inputs) > 2 else nu, x, y)
    return torch.autograd.grad((hu * wu).sum() + (hv * wv).sum(), inputs)


@pytest.mark.parametrize("grid", ["equal cells", "stretched"])
@pytest.mark.parametrize("viscosity", ["number", "per member"])
@pytest.mark.parametrize("members", [3, 8, 16])
def test_the_momentum_adjoint_is_autograds_gradient_of_the_terms(grid, viscosity, members):
    """Random velocities: the C adjoint of the staggered momentum terms (advection and
    diffusion, both components) against autograd through the terms' slices, for both
    velocities and the viscosity, on equal and on stretched cells, at a count of members
    the loop is inlined for (8, 16) and another; the terms themselves bit for bit; and
    against central differences."""
    from beacon_torch.numerics import staggered

    (x, y), (nx, ny) = stretched_spacings() if grid == "stretched" else ((0.1, 0.07), (9, 6))
    u, v, wu, wv = momentum_inputs(nx, ny, members, seed=nx)
    nu = 0.03 if viscosity == "number" else torch.linspace(0.01, 0.05, members, dtype=torch.float64)
    sx, sy = staggered.spacing(x), staggered.spacing(y)
    got = momentum_gradients(staggered.tendency, u, v, nu, x, y, wu, wv)
    want = momentum_gradients(staggered._terms, u, v, nu, sx, sy, wu, wv)
    assert len(got) == (2 if viscosity == "number" else 3)
    for g, w in zip(got, want, strict=True):
        torch.testing.assert_close(g, w, rtol=1e-13, atol=1e-13 * w.abs().max())
    with torch.enable_grad():
        recorded = staggered.tendency(u.clone().requires_grad_(), v, nu, x, y)
    for a, b in zip(recorded, staggered._terms(u, v, nu, sx, sy), strict=True):
        assert torch.equal(a, b)
    if grid == "equal cells":
        small = [t[..., :1].clone().requires_grad_() for t in momentum_inputs(5, 4, 1, seed=1)[:2]]
        assert torch.autograd.gradcheck(lambda u, v: staggered.tendency(u, v, 0.03, 0.2, 0.25), small)


def test_the_momentum_adjoint_of_a_real_state_is_autograds_gradient(monkeypatch):
    """rayleigh-v0's developed roll, its velocities with the cavity's wall ghosts as a
    substep's predictor reads them: the C adjoint against autograd through the terms,
    float64 and float32 (to float32's round-off)."""
    from beacon_torch.numerics import staggered

    env = beacon_torch.make("rayleigh-v0", 2, dtype="float64")
    env.reset()
    cavity = env.physics.cavity
    flow = cavity.to_solver(env.physics.flow(env.state), env.physics.ghosts)
    u, v = cavity.u_ghosts(flow.u), cavity.v_ghosts(flow.v)
    nx, ny = cavity.nx, cavity.ny
    wu, wv = rand((nx - 1, ny, 2), seed=5), rand((nx, ny - 1, 2), seed=6)
    nu = env.physics.nu(env.params)
    for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 1e-5)):
        cast = [t.to(dtype) for t in (u, v, wu, wv)]
        args = (cavity.dx, cavity.dy)
        got = momentum_gradients(staggered.tendency, cast[0], cast[1], nu, *args, *cast[2:])
        spacings = tuple(staggered.spacing(h) for h in args)
        want = momentum_gradients(staggered._terms, cast[0], cast[1], nu, *spacings, *cast[2:])
        for g, w in zip(got, want, strict=True):
            torch.testing.assert_close(g, w, rtol=tol, atol=tol * w.abs().max())


def test_the_momentum_adjoint_maps_and_compiles():
    """``vmap`` of ``grad`` through the momentum terms is each mapped value's own
    gradient; a compiled function of them differentiates to the eager gradient, on
    stretched cells with a per-member viscosity that requires grad."""
    from beacon_torch.numerics import staggered

    u, v, wu, wv = momentum_inputs(6, 5, 2, seed=11)

    def loss(u):
        hu, hv = staggered.tendency(u, v, 0.02, 0.1, 0.1)
        return (hu * wu).sum() + (hv * wv).sum()

    several = torch.stack([u, 2.0 * u, -u])
    torch.testing.assert_close(vmap(grad(loss))(several), torch.stack([grad(loss)(x) for x in several]))

    (x, y), (nx, ny) = stretched_spacings()
    u, v, wu, wv = momentum_inputs(nx, ny, 2, seed=12)

    def terms(u, v, nu):
        hu, hv = staggered.tendency(u, v, nu, x, y)
        return (hu * wu).sum() + (hv * wv).sum()

    inputs = lambda: [t.clone().requires_grad_() for t in (u, v, torch.tensor([0.01, 0.03], dtype=torch.float64))]
    eager = inputs()
    expected = torch.autograd.grad(terms(*eager), eager)
    compiled_inputs = inputs()
    compiled = torch.compile(terms, fullgraph=True, dynamic=False)
    for got, want in zip(torch.autograd.grad(compiled(*compiled_inputs), compiled_inputs), expected, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12 * want.abs().max())


def tvd_inputs(seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows with the limiters' kinks in them: flat stretches (r = 0, and a zero
    difference under the ratio), a straight ramp (r = 1) and random values."""
    f = rand((3, 2, 40), seed)
    f[..., 5:9] = 0.7
    f[..., 20:24] = torch.tensor([0.0, 1.0, 2.0, 3.0], dtype=torch.float64)
    return f, rand((3, 2, 38), seed + 1)


@pytest.mark.parametrize("limiter", ["van_leer", "minmod"])
@pytest.mark.parametrize("kernel", ["C", "tensors"])
def test_the_tvd_adjoint_is_autograds_gradient_of_the_reconstruction(limiter, kernel, monkeypatch):
    """The TVD derivative's backward pass (a C loop a row, or its tensor form elsewhere)
    gives autograd's gradient of the reconstruction written as slices, on random rows
    with the limiters' kinks and on a real burgers-v0 state, to round-off in float64;
    the forward values are the slices' own, bit for bit."""
    from beacon_torch.numerics import fluxes

    if kernel == "tensors":
        monkeypatch.setenv("BEACON_TORCH_NATIVE", "0")
    lim = getattr(fluxes, limiter)
    env = beacon_torch.make("burgers-v0", 3, dtype="float64", seed=0)
    env.reset()
    for _ in range(50):
        env.step_members(torch.full((3, 1), 0.3, dtype=torch.float64))
    real = env.state.u
    dx = 0.01
    for f, weight in (tvd_inputs(0), (real, rand((3, real.shape[-1] - 2), 5))):
        want = gradients(lambda t: fluxes._tvd_derivative(t, dx, lim), [f], weight)[0]
        got = gradients(lambda t: fluxes.tvd_derivative(t, dx, lim), [f], weight)[0]
        assert want.abs().max() > 0
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12 * want.abs().max().item())
        x = f.clone().requires_grad_()
        assert torch.equal(fluxes.tvd_derivative(x, dx, lim).detach(), fluxes._tvd_derivative(f, dx, lim))


def test_the_adjoint_loops_take_subnormal_gradients_as_zero_and_leave_the_process_as_it_was():
    """Gradients below the smallest normal float32 (they decay there upstream of an
    actuator, where each operation on them is tens of times dearer) count as zero inside
    the C adjoints; normal ones are unchanged, and the caller's arithmetic still keeps
    subnormal numbers after the call."""
    from beacon_torch.numerics import native

    if not native.applies("cpu", torch.float32):
        pytest.skip("no C kernels here")
    f = torch.rand((4, 50), generator=torch.Generator().manual_seed(0))
    tiny = torch.full((4, 48), 1e-39)
    assert torch.equal(native.tvd_adjoint(f, tiny, 0.1, False), torch.zeros_like(f))
    normal = torch.rand((4, 48), generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(
        native.tvd_adjoint(f, normal, 0.1, False), native.tvd_adjoint(f.double(), normal.double(), 0.1, False).float()
    )
    assert float(torch.tensor(1e-39) * torch.tensor(1.0)) > 0.0


@pytest.mark.parametrize("members", [8, 16])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_kernels_inlined_for_a_batch_give_each_member_what_it_gets_alone(members, dtype):
    """The 2-D kernels are compiled apart for 8 and 16 members (whole vectors a row):
    each member of such a batch gets from the sweep, its reverse, the line solve and the
    momentum terms' adjoint exactly what it gets alone, to the last bit."""
    from beacon_torch.numerics.staggered import Uniform, multipliers

    nx, ny = 11, 7
    cast = lambda t: t.to(dtype).contiguous()
    s, g, x = (cast(rand((nx + 2, ny + 2, members), k)) for k in (1, 2, 3))
    a, b = (cast(0.2 * rand((nx, ny, members), k).abs()) for k in (4, 5))
    f = cast(rand((5, ny, members), 6))
    lower, inv, upper = cast(rand((5, ny), 7)), cast(1.0 + rand((5, ny), 8).abs()), cast(rand((ny,), 9))
    u, v, gu, gv = (cast(t) for t in momentum_inputs(nx, ny, members, seed=10))
    nu = cast(0.01 + rand((members,), 11).abs())
    cx, cy = multipliers(Uniform(1 / nx), nx, u), multipliers(Uniform(1 / ny), ny, u)
    width = torch.ones(ny, dtype=dtype)
    kernels = {
        "sweep": lambda k: (native.sweep_kernel(s[..., k], a[..., k], b[..., k]),),
        "sweep_adjoint": lambda k: native.sweep_adjoint(g[..., k], x[..., k], a[..., k], b[..., k]),
        "lines": lambda k: (native.lines_kernel(f[..., k], lower, inv, upper, width),),
        "momentum_adjoint": lambda k: native.momentum_adjoint(
            u[..., k], v[..., k], gu[..., k], gv[..., k], nu[k], cx, cy
        ),
    }
    whole = slice(None)
    for name, kernel in kernels.items():
        batch = kernel(whole)
        for m in range(members):
            alone = kernel(slice(m, m + 1))
            for got, want in zip(batch, alone, strict=True):
                assert torch.equal(got[..., m : m + 1], want), (name, m)


def test_the_float32_kernels_compute_in_float32():
    """Every constant of the C kernels' source is cast to the kernel's type: a bare
    ``0.5`` is a double in C, so the float32 kernel converts each operand to double and
    back in its innermost loop (the momentum adjoint ran a quarter slower so, with the
    same results)."""
    import re

    from beacon_torch.numerics import native

    code = re.sub(r"/\*.*?\*/", " ", native._SOURCE, flags=re.S)
    literal = re.compile(r"(?<![\w.])(\d+\.\d*|\.\d+|\d+(?=[eE]))([eE][+-]?\d+)?(?![\w.])")
    bare = []
    for macro in re.finditer(r"#define (\w+)\(([^)]*)\)(.*?)(?=\n#define|\n\w+\(\w+_f32|\Z)", code, re.S):
        name, params, body = macro.groups()
        if "T" in [p.strip() for p in params.split(",")]:
            for m in literal.finditer(body):
                if not re.search(r"\(T\)-?$", body[: m.start()]):
                    bare.append(f"{name}: {m.group(0)}")
    assert len(re.findall(r"#define \w+\([^)]*\bT\b", code)) >= 8
    assert bare == []


def test_the_tvd_adjoint_maps_and_compiles():
    """``vmap`` of ``grad`` through the TVD derivative is the eager gradient; so is a
    compiled gradient (the adjoint operator inside the compiled backward graph) and the
    adjoint operator called inside a compiled graph."""
    from beacon_torch.numerics import fluxes

    f, weight = tvd_inputs(3)
    rows, flat_weight = f.reshape(6, 40), weight.reshape(6, 38)
    want = gradients(lambda t: fluxes._tvd_derivative(t, 0.01, fluxes.minmod), [rows], flat_weight)[0]
    loss = lambda t, w: (fluxes.tvd_derivative(t, 0.01, fluxes.minmod) * w).sum()
    torch.testing.assert_close(vmap(grad(loss))(rows, flat_weight), want, rtol=1e-12, atol=1e-12)
    compiled = torch.compile(loss, fullgraph=True)
    x = rows.clone().requires_grad_()
    torch.testing.assert_close(torch.autograd.grad(compiled(x, flat_weight), x)[0], want, rtol=1e-12, atol=1e-12)
    adjoint = torch.compile(lambda t, w: 2.0 * fluxes.tvd_adjoint(t, w, 0.01, True), fullgraph=True)
    torch.testing.assert_close(adjoint(rows, flat_weight), 2.0 * want, rtol=1e-12, atol=1e-12)


def burgers_inputs(members: int, seed: int, dtype=torch.float64):
    """A real burgers-v0 state 50 actions in (its kinks: the flat inlet stretch, the
    actuator's jump) and random inlet values and forcing."""
    env = beacon_torch.make("burgers-v0", members, dtype=dtype, seed=seed)
    env.reset()
    for _ in range(50):
        env.step_members(torch.full((members, 1), 0.3, dtype=dtype))
    u, u_prev = env.state.u, env.state.u_prev
    generator = torch.Generator().manual_seed(seed)
    inlet = (0.5 + 0.1 * torch.rand((members, 1), generator=generator, dtype=torch.float64)).to(dtype)
    forcing = torch.zeros_like(u[:, 1:-1])
    forcing[:, env.physics.ctrl - 1] = torch.randn(members, generator=generator, dtype=torch.float64).to(dtype)
    return u, u_prev, inlet, forcing


def burgers_loop(u, u_prev, inlet, forcing):
    """An action of burgers-v0 as the tensor loop of its substeps."""
    from beacon_torch.envs import burgers

    for i in range(burgers.SUBSTEPS):
        u, u_prev = burgers.burgers_substep(i, (u, u_prev), inlet, forcing)
    return u, u_prev


def assert_the_env_takes_the_c_action(module, env_id: str, parameters: dict, compile: bool = False):
    """Three differentiated actions of ``env_id`` (2 members, float64) with the given
    parameters as leaves: the env calls its C action (``module._Action``) once an action,
    and the rewards' gradient with respect to the parameters is the one of the tensor
    loop (the C kernels switched off)."""
    from tensordict import TensorDict

    def gradient():
        leaves = {k: torch.tensor(v, dtype=torch.float64, requires_grad=True) for k, v in parameters.items()}
        env = beacon_torch.make(env_id, 2, dtype="float64", differentiable=True, seed=1, compile=compile, **leaves)
        env.reset()
        total = 0.0
        for k in range(3):
            action = torch.full((2, *env.action_spec.shape[1:]), 0.1 * k, dtype=torch.float64)
            total = total + env.step(TensorDict({"action": action}, batch_size=[2]))["next", "reward"].sum()
        return torch.autograd.grad(total, list(leaves.values()))

    calls = []
    original = module._Action.apply
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(module._Action, "apply", lambda *a: calls.append(1) or original(*a))
        got = gradient()
    assert len(calls) == 3
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("BEACON_TORCH_NATIVE", "0")
        slices = gradient()
    for g, w in zip(got, slices, strict=True):
        assert w.abs().min() > 0
        torch.testing.assert_close(g, w, rtol=1e-10, atol=0)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_burgers_action_in_c_is_the_tensor_loop_and_its_adjoint_autograds_gradient(dtype):
    """A whole action of burgers-v0 as one C loop a member gives the tensor loop's values
    bit for bit; its reverse loop gives autograd's gradient of that loop with respect to
    the state, the previous state, the inlet values and the forcing, to round-off (float64:
    1e-13 of the largest; float32: 1e-5), on a real state and on random rows."""
    from beacon_torch.envs import burgers

    real = burgers_inputs(3, 0, dtype)
    noisy = [t + 0.05 * rand(t.shape, 7 + k).to(dtype) * (k < 2) for k, t in enumerate(real)]
    weights = [rand(real[0].shape, 11).to(dtype), rand(real[0].shape, 12).to(dtype)]
    tol = 1e-13 if dtype == torch.float64 else 1e-5

    def gradient(fn, inputs):
        x = [t.clone().requires_grad_() for t in inputs]
        return torch.autograd.grad(sum((out * w).sum() for out, w in zip(fn(*x), weights, strict=True)), x)

    for inputs in (real, noisy):
        for a, b in zip(burgers.burgers_action(*inputs), burgers_loop(*inputs), strict=True):
            assert torch.equal(a, b)
        for got, want in zip(gradient(burgers.burgers_action, inputs), gradient(burgers_loop, inputs), strict=True):
            assert want.abs().max() > 0
            torch.testing.assert_close(got, want, rtol=0, atol=tol * want.abs().max().item())


def test_the_burgers_action_maps_compiles_and_carries_the_envs_gradient():
    """``vmap`` of ``grad`` through the action, a compiled differentiated action and the
    env's gradient of five actions' rewards with respect to its amplitude (eager and
    compiled) are those of the tensor loop; the recording env takes the C action."""

    from beacon_torch.envs import burgers

    u, u_prev, inlet, forcing = burgers_inputs(2, 1)
    row = lambda fn: lambda *x: fn(*(t[None] for t in x))[0][0].pow(2).sum()
    want = vmap(grad(row(burgers_loop)))(u, u_prev, inlet, forcing)
    torch.testing.assert_close(vmap(grad(row(burgers.burgers_action)))(u, u_prev, inlet, forcing), want)
    loss = lambda fn: lambda x: fn(x, u_prev, inlet, forcing)[0].pow(2).sum()
    x = u.clone().requires_grad_()
    compiled = torch.compile(loss(burgers.burgers_action), fullgraph=True)
    torch.testing.assert_close(torch.autograd.grad(compiled(x), x)[0], torch.autograd.grad(loss(burgers_loop)(x), x)[0])

    for compiled_env in (False, True):
        assert_the_env_takes_the_c_action(burgers, "burgers-v0", {"amp": 10.0}, compile=compiled_env)


def test_an_actions_stored_substeps_are_reused_only_once_nothing_holds_them(monkeypatch):
    """The buffers of the stored substeps (kept between actions, so that their pages stay
    mapped) go to a new action only once the graph that saved them is gone: a horizon of
    three differentiated actions, whose stored substeps are all held at once, has the
    tensor loop's gradient, twice in a row (the second horizon on the first's buffers),
    and with room for one buffer only (the last action's new previous state has no
    gradient: the backward pass takes zeros for it). A buffer held anywhere, a view
    included, is never handed out; the cache keeps at most its bytes, dropping unused
    buffers of other sizes for a new one."""
    from beacon_torch.envs import burgers

    monkeypatch.setattr(native, "_kept", [])
    like = torch.empty(0)
    first = native.stored_substeps(like, (256, 1024))  # 1 MiB of float32: kept
    second = native.stored_substeps(like, (256, 1024))
    assert first.data_ptr() != second.data_ptr() and len(native._kept) == 2
    view, address = first[3:], first.data_ptr()
    del first
    assert native.stored_substeps(like, (256, 1024)).data_ptr() != address  # the view holds it
    del view
    assert native.stored_substeps(like, (256, 1024)).data_ptr() == address
    assert native.stored_substeps(like, (8, 8)).numel() == 64 and len(native._kept) == 3  # small: never kept

    u, u_prev, inlet, forcing = burgers_inputs(12, 2)  # 12 members: 2.8 MB of stored substeps an action

    def horizon(action):
        x = u.clone().requires_grad_()
        fields, total = (x, u_prev), 0.0
        for k in range(3):
            fields = action(*fields, inlet, forcing * (1 + k))
            total = total + fields[0].pow(2).sum() + (fields[1].sum() if k < 2 else 0.0)
        return torch.autograd.grad(total, x)[0]

    want = horizon(burgers_loop)
    for _ in range(2):
        torch.testing.assert_close(horizon(burgers.burgers_action), want, rtol=1e-12, atol=0)
    monkeypatch.setattr(native, "_KEPT_BYTES", 4 << 20)  # room for one action's buffer
    monkeypatch.setattr(native, "_kept", [])
    torch.testing.assert_close(horizon(burgers.burgers_action), want, rtol=1e-12, atol=0)
    assert sum(b.numel() * b.element_size() for b in native._kept) <= 4 << 20
    # a buffer of another size (another batch in the same process) makes room by dropping
    # an unused one, wherever it lies among those held
    monkeypatch.setattr(native, "_kept", [])
    held, unused = native.stored_substeps(like, (256, 1024)), native.stored_substeps(like, (512, 1024))
    del unused
    other = native.stored_substeps(like, (768, 1024))
    assert [b.data_ptr() for b in native._kept] == [held.data_ptr(), other.data_ptr()]


def shkadov_inputs(members: int, seed: int, dtype=torch.float64):
    """A developed shkadov-v0 film a few actions in, random forcings (both ways) and
    inlet values, the interpolation's weights, and delta one value a member."""
    from beacon_torch.envs import shkadov

    env = beacon_torch.make("shkadov-v0", members, dtype=dtype, seed=seed)
    env.reset()
    for _ in range(5):
        env.step_members(torch.full((members, 5), 0.3, dtype=dtype))
    s, n = env.state, env.state.h.shape[-1]
    forcing = [0.1 * rand((members, n - 2), seed + k).to(dtype) for k in (1, 2)]
    inlet = (1.0 + 1e-3 * rand((shkadov.SUBSTEPS, members, 1), seed + 3)).to(dtype)
    alpha = shkadov.interpolation_weights(shkadov.SUBSTEPS, shkadov.N_INTERP, dtype)
    delta = torch.full((members, 1), 0.1, dtype=dtype)
    return (s.h, s.q, s.dh_prev, s.dq_prev, *forcing, inlet, delta), alpha


def shkadov_loop(alpha):
    """An action of shkadov-v0 as the tensor loop of its substeps."""
    from beacon_torch.envs import shkadov

    def loop(h, q, dh, dq, forcing_prev, forcing_new, inlet, delta):
        fields = h, q, dh, dq
        for i in range(shkadov.SUBSTEPS):
            fields = shkadov.action_substep(i, fields, forcing_prev, forcing_new, alpha, inlet, delta, shkadov.DX)
        return fields

    return loop


def shkadov_c(alpha):
    from beacon_torch.envs import shkadov

    return lambda h, q, dh, dq, fp, fn, inlet, delta: shkadov.shkadov_action(
        (h, q, dh, dq), fp, fn, alpha, inlet, delta
    )


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_shkadov_action_in_c_is_the_tensor_loop_and_its_adjoint_autograds_gradient(dtype):
    """A whole action of shkadov-v0 as one C loop a member gives the tensor loop's four
    fields bit for bit; its reverse loop gives autograd's gradient of that loop with
    respect to every input (the fields, both forcings, each substep's inlet value and
    each member's delta) to round-off, on a developed film and on a perturbed one."""
    inputs, alpha = shkadov_inputs(3, 0, dtype)
    perturbed = [t + 0.02 * rand(t.shape, 20 + k).to(dtype) * (k < 2) for k, t in enumerate(inputs)]
    tol = 1e-12 if dtype == torch.float64 else 1e-5

    def gradient(fn, given):
        x = [t.clone().requires_grad_() for t in given]
        out = fn(*x)
        weights = [rand(o.shape, 30 + k).to(dtype) for k, o in enumerate(out)]
        return torch.autograd.grad(sum((o * w).sum() for o, w in zip(out, weights, strict=True)), x)

    for given in (inputs, perturbed):
        for a, b in zip(shkadov_c(alpha)(*given), shkadov_loop(alpha)(*given), strict=True):
            assert torch.equal(a, b)
        for got, want in zip(gradient(shkadov_c(alpha), given), gradient(shkadov_loop(alpha), given), strict=True):
            assert want.abs().max() > 0
            torch.testing.assert_close(got, want, rtol=0, atol=tol * want.abs().max().item())


def test_the_shkadov_action_maps_compiles_and_carries_the_envs_gradient():
    """``vmap`` of ``grad`` through the action, a compiled differentiated action, and the
    env's gradient of three actions' rewards with respect to delta and the jets'
    amplitude are the tensor loop's; the recording env takes the C action."""

    from beacon_torch.envs import shkadov

    inputs, alpha = shkadov_inputs(2, 1)

    def row(fn):  # one member's action: its inlet values [substeps, 1], its delta [1]
        def member(*x):
            *fields, inlet, delta = x
            return fn(*(t[None] for t in fields), inlet[:, None], delta[None])[0].pow(2).sum()

        return member

    batched = [*inputs[:6], inputs[6].movedim(1, 0), inputs[7]]
    want = vmap(grad(row(shkadov_loop(alpha))))(*batched)
    torch.testing.assert_close(vmap(grad(row(shkadov_c(alpha))))(*batched), want)
    loss = lambda fn: lambda x: fn(x, *inputs[1:])[1].pow(2).sum()
    x = inputs[0].clone().requires_grad_()
    compiled = torch.compile(loss(shkadov_c(alpha)), fullgraph=True)
    torch.testing.assert_close(
        torch.autograd.grad(compiled(x), x)[0], torch.autograd.grad(loss(shkadov_loop(alpha))(x), x)[0]
    )

    assert_the_env_takes_the_c_action(shkadov, "shkadov-v0", {"delta": 0.1, "amp": 5.0})


def sloshing_inputs(members: int, seed: int, dtype=torch.float64):
    """A sloshing-v0 tank a few actions in, random accelerations for each substep and
    one gravity a member."""
    from beacon_torch.envs import sloshing

    env = beacon_torch.make("sloshing-v0", members, dtype=dtype, seed=seed)
    env.reset()
    for _ in range(5):
        env.step_members(torch.full((members, 1), 0.3, dtype=dtype))
    s = env.state
    accel = rand((sloshing.SUBSTEPS, members), seed + 1).to(dtype)
    g = (9.81 + rand((members,), seed + 2)).to(dtype)
    return (s.h, s.q, s.fh_prev, s.fq_prev, accel, g), env.physics.dx


def sloshing_loop(dx):
    from beacon_torch.envs import sloshing

    def loop(h, q, fh, fq, accel, g):
        fields = h, q, fh, fq
        for i in range(sloshing.SUBSTEPS):
            fields = sloshing.sloshing_substep(i, fields, accel, g[:, None], dx)
        return fields

    return loop


def sloshing_c(dx):
    from beacon_torch.envs import sloshing

    return lambda h, q, fh, fq, accel, g: sloshing.sloshing_action((h, q, fh, fq), accel, g, dx)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_sloshing_action_in_c_is_the_tensor_loop_and_its_adjoint_autograds_gradient(dtype):
    """A whole action of sloshing-v0 as one C loop a member gives the tensor loop's four
    fields to round-off (torch's CPU square root is not always correctly rounded, C's
    is; one substep of the two is the same bit for bit in float64, and in float32 to
    round-off, as torch's vectorised float32 kernels differ between CPUs); its
    reverse loop gives
    autograd's gradient of that loop with respect to every input (the fields, each
    substep's acceleration, each member's g) to round-off, on a sloshing state and on
    a perturbed one."""
    from beacon_torch.envs import sloshing

    inputs, dx = sloshing_inputs(3, 0, dtype)
    perturbed = [t + 0.01 * rand(t.shape, 40 + k).to(dtype) * (k < 2) for k, t in enumerate(inputs)]
    # float32's round-off over an action's substeps differs between CPUs by up to 2e-5
    # of the largest value; float64 is where exactness is checked
    tol = 1e-12 if dtype == torch.float64 else 1e-4
    one = [*inputs[:4], inputs[4][:1], inputs[5]]
    for a, b in zip(
        sloshing_c(dx)(*one), sloshing.sloshing_substep(0, one[:4], one[4], one[5][:, None], dx), strict=True
    ):
        if dtype == torch.float64:
            assert torch.equal(a, b)
        else:
            torch.testing.assert_close(a, b, rtol=tol, atol=tol)

    def gradient(fn, given):
        x = [t.clone().requires_grad_() for t in given]
        out = fn(*x)
        weights = [rand(o.shape, 50 + k).to(dtype) for k, o in enumerate(out)]
        return torch.autograd.grad(sum((o * w).sum() for o, w in zip(out, weights, strict=True)), x)

    for given in (inputs, perturbed):
        for a, b in zip(sloshing_c(dx)(*given), sloshing_loop(dx)(*given), strict=True):
            torch.testing.assert_close(a, b, rtol=0, atol=tol * b.abs().max().item())
        for got, want in zip(gradient(sloshing_c(dx), given), gradient(sloshing_loop(dx), given), strict=True):
            assert want.abs().max() > 0
            torch.testing.assert_close(got, want, rtol=0, atol=tol * want.abs().max().item())


def test_the_sloshing_action_maps_compiles_and_carries_the_envs_gradient():
    """``vmap`` of ``grad`` through the action, a compiled differentiated action, and the
    env's gradient of three actions' rewards with respect to g and the amplitude are the
    tensor loop's; the recording env takes the C action."""

    from beacon_torch.envs import sloshing

    inputs, dx = sloshing_inputs(2, 1)

    def row(fn):  # one member's action: its accelerations [substeps], its g
        return lambda h, q, fh, fq, accel, g: (
            fn(h[None], q[None], fh[None], fq[None], accel[:, None], g[None])[0].pow(2).sum()
        )

    batched = [*inputs[:4], inputs[4].movedim(1, 0), inputs[5]]
    want = vmap(grad(row(sloshing_loop(dx))))(*batched)
    torch.testing.assert_close(vmap(grad(row(sloshing_c(dx))))(*batched), want)
    loss = lambda fn: lambda x: fn(x, *inputs[1:])[1].pow(2).sum()
    x = inputs[0].clone().requires_grad_()
    compiled = torch.compile(loss(sloshing_c(dx)), fullgraph=True)
    torch.testing.assert_close(
        torch.autograd.grad(compiled(x), x)[0], torch.autograd.grad(loss(sloshing_loop(dx))(x), x)[0]
    )

    assert_the_env_takes_the_c_action(sloshing, "sloshing-v0", {"g": [9.81, 10.0], "amp": 5.0})
