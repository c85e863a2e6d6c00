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
    out = lsrk4_step(lambda v, t: torch.full_like(v, 3.0), u, 0.0, 0.25)
    torch.testing.assert_close(out, u + 0.75, rtol=0, atol=1e-15)


def test_lsrk4_integrates_time_dependent_rhs_exactly_for_cubics():
    # du/dt = t^3 is integrated exactly by a 4th-order method
    u = torch.zeros(1, 1, dtype=torch.float64)
    t0, dt = 0.3, 0.2
    out = lsrk4_step(lambda v, t: torch.full_like(v, t**3), u, t0, dt)
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
            u = lsrk4_step(rhs, u, i / n, 1.0 / n)
        exact = torch.tensor([[math.cos(1.0), -math.sin(1.0)]], dtype=torch.float64)
        errors.append((u - exact).abs().max().item())
    orders = [math.log2(errors[i] / errors[i + 1]) for i in range(2)]
    assert all(3.8 < p < 4.3 for p in orders), orders


def test_lsrk4_is_batched_and_differentiable():
    u = torch.tensor([[1.0], [2.0]], dtype=torch.float64, requires_grad=True)
    out = lsrk4_step(lambda v, t: -v, u, 0.0, 0.1)
    out.sum().backward()
    # on u' = -u one step multiplies by a fixed amplification factor, close to e^-dt
    factor = (out / u).detach()
    torch.testing.assert_close(u.grad, factor, rtol=1e-14, atol=0)
    assert abs(factor[0].item() - math.exp(-0.1)) < 1e-6
