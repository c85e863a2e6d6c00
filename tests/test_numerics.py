import math

import pytest
import torch

from beacon_torch.numerics import LSRK4_A, LSRK4_B, LSRK4_C, lsrk4_step


def test_lsrk4_coefficients_are_consistent():
    # C_i is the time reached by the stage's argument: C_i = sum_{j<i} of the effective
    # weights, which for the 2N form gives C_1 = B_0 and C_4 < 1.
    assert LSRK4_A[0] == 0.0 and LSRK4_C[0] == 0.0
    assert LSRK4_C[1] == pytest.approx(LSRK4_B[0], rel=1e-15)
    # the effective weights of k_i in the final update must sum to 1 (consistency)
    weights = [0.0] * 5
    for i in range(5):
        # k_i contributes B_i, and via A_{i+1} k_i to later stages
        w, carry = 0.0, 1.0
        for j in range(i, 5):
            if j > i:
                carry *= LSRK4_A[j]
            w += LSRK4_B[j] * carry
        weights[i] = w
    assert sum(weights) == pytest.approx(1.0, abs=1e-14)


def test_lsrk4_exact_on_linear_growth_constant_rhs():
    u = torch.tensor([[1.0, -2.0]], dtype=torch.float64)
    out, _ = lsrk4_step(lambda v, t: torch.full_like(v, 3.0), u, 0.0, 0.25)
    torch.testing.assert_close(out, u + 0.75, rtol=0, atol=1e-15)


def test_lsrk4_integrates_time_dependent_rhs_exactly_for_cubics():
    # du/dt = t^3 is integrated exactly by a 4th-order method
    u = torch.zeros(1, 1, dtype=torch.float64)
    t0, dt = 0.3, 0.2
    out, _ = lsrk4_step(lambda v, t: torch.full_like(v, t**3), u, t0, dt)
    exact = ((t0 + dt) ** 4 - t0**4) / 4
    # the published rationals satisfy the order conditions to about 1e-11, not to round-off
    assert out.item() == pytest.approx(exact, rel=1e-8)


def test_lsrk4_is_fourth_order_on_an_oscillator():
    # u = (cos t, -sin t) solves u' = (u1, -u0); the error after T = 1 shrinks as dt^4
    def rhs(u, t):
        return torch.stack((u[:, 1], -u[:, 0]), -1)

    errors = []
    for n in (10, 20, 40):
        u = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
        for i in range(n):
            u, _ = lsrk4_step(rhs, u, i / n, 1.0 / n)
        exact = torch.tensor([[math.cos(1.0), -math.sin(1.0)]], dtype=torch.float64)
        errors.append((u - exact).abs().max().item())
    orders = [math.log2(errors[i] / errors[i + 1]) for i in range(2)]
    assert all(3.8 < p < 4.3 for p in orders), orders


def test_lsrk4_returns_the_last_stage_rhs_not_the_rhs_at_the_new_state():
    # the published envs observe this value as the state's time derivative
    u = torch.tensor([[1.0]], dtype=torch.float64)
    seen = []

    def rhs(v, t):
        seen.append(v.clone())
        return -v

    out, rate = lsrk4_step(rhs, u, 0.0, 0.1)
    assert len(seen) == 5
    torch.testing.assert_close(rate, -seen[-1], rtol=0, atol=0)
    assert not torch.equal(rate, -out)


def test_lsrk4_is_batched_and_differentiable():
    u = torch.tensor([[1.0], [2.0]], dtype=torch.float64, requires_grad=True)
    out, _ = lsrk4_step(lambda v, t: -v, u, 0.0, 0.1)
    out.sum().backward()
    # on u' = -u one step multiplies by a fixed amplification factor, close to e^-dt
    factor = (out / u).detach()
    torch.testing.assert_close(u.grad, factor, rtol=1e-14, atol=0)
    assert abs(factor[0].item() - math.exp(-0.1)) < 1e-6


# ---------------------------------------------------------------- 1-D operators
from beacon_torch.numerics import (  # noqa: E402
    ab2_step,
    bdf2_explicit_step,
    interpolated_action,
    interpolation_weights,
    minmod,
    rusanov,
    third_derivative,
    tvd_derivative,
    tvd_faces,
    van_leer,
)


def test_limiter_values():
    r = torch.tensor([-2.0, -1.0, 0.0, 0.5, 1.0, 3.0, 1e6], dtype=torch.float64)
    torch.testing.assert_close(
        van_leer(r), torch.tensor([0, 0, 0, 2 / 3, 1, 1.5, 2 * 1e6 / (1 + 1e6)], dtype=torch.float64)
    )
    torch.testing.assert_close(minmod(r), torch.tensor([0, 0, 0, 0.5, 1, 1, 1], dtype=torch.float64))


@pytest.mark.parametrize("limiter", [van_leer, minmod])
def test_tvd_faces_on_monotone_and_extremal_data(limiter):
    # linear data: r = 1, phi(1) = 1, so faces are the exact midpoints (but the first,
    # which has no upstream neighbour and is first-order upwind)
    f = torch.arange(8, dtype=torch.float64)[None] * 0.3
    faces = tvd_faces(f, limiter)
    torch.testing.assert_close(faces[0, 1:], (f[0, 1:-1] + f[0, 2:]) / 2)
    assert faces[0, 0] == f[0, 0]
    # at a local maximum r < 0: the limiter falls back to the upwind value
    peak = torch.tensor([[0.0, 1.0, 3.0, 1.0, 0.0]], dtype=torch.float64)
    faces = tvd_faces(peak, limiter)
    assert faces[0, 2] == 3.0
    # monotone data never give face values outside their two cells (no new extrema)
    x = torch.linspace(0, 1, 50, dtype=torch.float64)[None]
    steps = torch.tanh(20 * (x - 0.5)) + 0.1 * x
    faces = tvd_faces(steps, limiter)
    lo = torch.minimum(steps[:, :-1], steps[:, 1:])
    hi = torch.maximum(steps[:, :-1], steps[:, 1:])
    assert ((faces >= lo - 1e-12) & (faces <= hi + 1e-12)).all()


@pytest.mark.parametrize("limiter", [van_leer, minmod])
def test_tvd_derivative_is_second_order_on_smooth_monotone_data(limiter):
    errors = []
    for n in (50, 100, 200, 400):
        x = torch.linspace(0.0, 1.0, n, dtype=torch.float64)[None]
        dx = 1.0 / (n - 1)
        d = tvd_derivative(torch.exp(x), dx, limiter)
        # away from the first cells, whose upwind fallback is first order
        errors.append((d - torch.exp(x[:, 1:-1]))[:, 5:].abs().max().item())
    orders = [math.log2(errors[i] / errors[i + 1]) for i in range(3)]
    assert all(o > 1.8 for o in orders), orders


def test_tvd_derivative_is_in_flux_form():
    g = torch.Generator().manual_seed(0)
    f = torch.rand((3, 40), generator=g, dtype=torch.float64)
    dx = 0.1
    faces = tvd_faces(f, van_leer)
    total = (tvd_derivative(f, dx, van_leer) * dx).sum(-1)
    torch.testing.assert_close(total, faces[:, -1] - faces[:, 0], rtol=0, atol=1e-13)


def test_rusanov_is_consistent_and_upwinds_linear_advection():
    u = torch.tensor([0.3, -1.2], dtype=torch.float64)
    torch.testing.assert_close(rusanov(u, u, 2 * u, 2 * u, torch.tensor(5.0)), 2 * u)
    a = 1.5
    ul, ur = torch.tensor([1.0]), torch.tensor([4.0])
    assert rusanov(ul, ur, a * ul, a * ur, torch.tensor(a)).item() == pytest.approx(a * 1.0)
    assert rusanov(ul, ur, -a * ul, -a * ur, torch.tensor(a)).item() == pytest.approx(-a * 4.0)


def test_third_derivative_exact_on_cubics_and_second_order_inside():
    x = torch.linspace(-1.0, 2.0, 31, dtype=torch.float64)[None]
    dx = 0.1
    d = third_derivative(2 * x**3 - x**2 + 5, dx)
    assert d.shape == (1, 29)
    torch.testing.assert_close(d, torch.full_like(d, 12.0), rtol=0, atol=1e-8)
    errors = []
    for n in (40, 80, 160):
        x = torch.linspace(0.0, 1.0, n, dtype=torch.float64)[None]
        dx = 1.0 / (n - 1)
        d = third_derivative(torch.sin(3 * x), dx)[:, :-2]  # the one-sided stencil
        errors.append((d + 27 * torch.cos(3 * x[:, 1:-3])).abs().max().item())
    orders = [math.log2(errors[i] / errors[i + 1]) for i in range(2)]
    assert all(1.8 < o < 2.3 for o in orders), orders


def test_ab2_is_second_order():
    errors = []
    for n in (20, 40, 80):
        dt = 1.0 / n
        u = torch.tensor([1.0], dtype=torch.float64)
        f_prev = -torch.exp(torch.tensor([dt], dtype=torch.float64))  # exact f at t = -dt
        for _ in range(n):
            f = -u
            u, f_prev = ab2_step(u, f, f_prev, dt), f
        errors.append(abs(u.item() - math.exp(-1.0)))
    orders = [math.log2(errors[i] / errors[i + 1]) for i in range(2)]
    assert all(1.8 < o < 2.2 for o in orders), orders


def test_explicit_bdf2_is_consistent_and_first_order():
    # the right-hand side lags one level behind the implicit BDF2, which costs an order
    errors = []
    for n in (50, 100, 200):
        dt = 1.0 / n
        u_prev = torch.tensor([math.exp(dt)], dtype=torch.float64)
        u = torch.tensor([1.0], dtype=torch.float64)
        for _ in range(n):
            u, u_prev = bdf2_explicit_step(u, u_prev, -u, dt), u
        errors.append(abs(u.item() - math.exp(-1.0)))
    orders = [math.log2(errors[i] / errors[i + 1]) for i in range(2)]
    assert all(0.9 < o < 1.2 for o in orders), orders
    # a constant state is a fixed point
    c = torch.full((2, 3), 0.5, dtype=torch.float64)
    assert torch.equal(bdf2_explicit_step(c, c, torch.zeros_like(c), 0.1), c)


def test_interpolated_action():
    prev, new = torch.tensor([0.0, 1.0]), torch.tensor([1.0, -1.0])
    alpha = interpolation_weights(50, 10, torch.float32)
    assert alpha.shape == (50,) and alpha[10:].eq(1.0).all()
    torch.testing.assert_close(interpolated_action(prev, new, alpha[0]), prev)
    torch.testing.assert_close(interpolated_action(prev, new, alpha[5]), torch.tensor([0.5, 0.0]))
    torch.testing.assert_close(interpolated_action(prev, new, alpha[10]), new)
    torch.testing.assert_close(interpolated_action(prev, new, alpha[49]), new)
    # the weights are those of the Python numbers i / n, rounded once to the dtype
    assert interpolation_weights(50, 10, torch.float32)[3].item() == torch.tensor(3 / 10, dtype=torch.float32).item()
    assert interpolation_weights(5, 0, torch.float64).eq(1.0).all()


def test_frequency_damping_finds_an_unstable_focus_and_leaves_a_steady_state_alone():
    from beacon_torch.numerics import frequency_damping

    # an unstable focus at (1, -2): growth 0.1, angular frequency 6 (a shedding-like mode)
    centre = torch.tensor([1.0, -2.0], dtype=torch.float64)
    a = torch.tensor([[0.1, -6.0], [6.0, 0.1]], dtype=torch.float64)
    dt = 1e-3

    def march(chi: float, n: int):
        x = centre + torch.tensor([0.3, 0.0], dtype=torch.float64)
        filtered = (x.clone(),)
        for _ in range(n):
            x = x + dt * a @ (x - centre)
            (x,), filtered = frequency_damping((x,), filtered, dt, chi, delta=1.0)
        return x

    assert (march(0.0, 30_000) - centre).norm() > 1.0  # left alone, the focus throws the state off
    torch.testing.assert_close(march(1.0, 30_000), centre, atol=1e-8, rtol=0)
    # a steady state is a fixed point of the damping, whatever its rate
    fields = (torch.randn(3, 4, dtype=torch.float64), torch.randn(5, dtype=torch.float64))
    damped, filtered = frequency_damping(fields, fields, 0.1, 7.0, 0.5)
    assert all(torch.equal(q, d) and torch.equal(q, f) for q, d, f in zip(fields, damped, filtered, strict=True))
