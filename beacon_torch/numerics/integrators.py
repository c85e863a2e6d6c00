"""Time integrators.

The five-stage, fourth-order low-storage Runge-Kutta scheme of Carpenter & Kennedy (1994,
NASA TM-109112, "solution 3"), in its 2N-storage form::

    k <- A_i k + dt f(u, t + C_i dt)
    u <- u + B_i k,            i = 0..4,  k = 0 before the first stage.

The coefficients are the exact rationals of the paper; the published BEACON code uses
their 15-digit decimal expansions, which agree to round-off.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

LSRK4_A = (
    0.0,
    -567301805773.0 / 1357537059087.0,
    -2404267990393.0 / 2016746695238.0,
    -3550918686646.0 / 2091501179385.0,
    -1275806237668.0 / 842570457699.0,
)
LSRK4_B = (
    1432997174477.0 / 9575080441755.0,
    5161836677717.0 / 13612068292357.0,
    1720146321549.0 / 2090206949498.0,
    3134564353537.0 / 4481467310338.0,
    2277821191437.0 / 14882151754819.0,
)
LSRK4_C = (
    0.0,
    1432997174477.0 / 9575080441755.0,
    2526269341429.0 / 6820363183573.0,
    2006345519317.0 / 3224310063776.0,
    2802321613138.0 / 2924317926251.0,
)


def lsrk4_step(
    rhs: Callable[[torch.Tensor, float], torch.Tensor],
    u: torch.Tensor,
    t: float,
    dt: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Advance ``u`` by one LSRK4 step of size ``dt``; returns the new ``u`` and the
    right-hand side of the last stage.

    ``rhs(u, t)`` returns du/dt with the shape of ``u``; ``t`` is only passed through
    (the autonomous systems of the benchmark ignore it). Out-of-place, so the graph
    through ``u`` survives when gradients are wanted. The last stage's right-hand side
    (evaluated before the last update, not at the new ``u``) is what the published
    envs observe as the "time derivatives" of their state.
    """
    k = torch.zeros_like(u)
    f = k
    for a, b, c in zip(LSRK4_A, LSRK4_B, LSRK4_C, strict=True):
        f = rhs(u, t + c * dt)
        k = a * k + dt * f
        u = u + b * k
    return u, f


def ab2_step(u: torch.Tensor, f: torch.Tensor, f_prev: torch.Tensor, dt: float) -> torch.Tensor:
    """Second-order Adams-Bashforth: u + dt/2 (3 f^n - f^(n-1)).

    The published code starts every episode with f^(-1) = 0 (a first step of 3/2 dt f),
    which the envs reproduce by passing zeros after a reset.
    """
    return u + 0.5 * dt * (3.0 * f - f_prev)


def bdf2_explicit_step(u: torch.Tensor, u_prev: torch.Tensor, f: torch.Tensor, dt: float) -> torch.Tensor:
    """Second-order backward differences with an explicit right-hand side f = f(u^n):
    u^(n+1) = (4 u^n - u^(n-1) + 2 dt f) / 3."""
    return (4.0 * u - u_prev + 2.0 * dt * f) / 3.0


def interpolation_weights(substeps: int, n_interp: int, dtype: torch.dtype, device=None) -> torch.Tensor:
    """``[substeps]``: the weight of the new action at each substep of an action period,
    alpha_i = min(i / n_interp, 1) (linear from the previous action to the new one over
    the first ``n_interp`` substeps, then held)."""
    alphas = [min(i / n_interp, 1.0) if n_interp > 0 else 1.0 for i in range(substeps)]
    return torch.tensor(alphas, dtype=dtype, device=device)


def interpolated_action(previous: torch.Tensor, new: torch.Tensor, alpha) -> torch.Tensor:
    """The action applied at a substep of weight ``alpha`` (:func:`interpolation_weights`)."""
    return previous + alpha * (new - previous)


def frequency_damping(
    fields: tuple[torch.Tensor, ...], filtered: tuple[torch.Tensor, ...], dt: float, chi: float, delta: float
) -> tuple[tuple[torch.Tensor, ...], tuple[torch.Tensor, ...]]:
    """One step of selective frequency damping (Akervik et al., Phys. Fluids 18, 2006):
    each field ``q`` is pulled towards its low-pass filtered self ``qbar`` at the rate
    ``chi``, ``q <- q - dt chi (q - qbar)``, and the filter, of width ``delta`` in time,
    follows, ``qbar <- qbar + dt (q - qbar) / delta``. Both updates are linear in the
    fields, so divergence-free fields stay divergence-free, and a steady solution
    (``q = qbar``) is left alone: what the damping converges to is a steady solution of
    the undamped equations, stable or not. Returns the damped fields and the new
    filtered ones."""
    gaps = [q - bar for q, bar in zip(fields, filtered, strict=True)]
    damped = tuple(q - dt * chi * gap for q, gap in zip(fields, gaps, strict=True))
    followed = tuple(bar + dt * gap / delta for bar, gap in zip(filtered, gaps, strict=True))
    return damped, followed
