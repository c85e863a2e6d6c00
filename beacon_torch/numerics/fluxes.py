"""Spatial operators of the 1-D environments (burgers, sloshing, shkadov).

All act on the last dimension of a ``[..., n]`` tensor of cell values and return values
at the interior cells ``1..n-2`` (``[..., n-2]``): the end cells are boundary cells that
each env sets itself.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

Limiter = Callable[[torch.Tensor], torch.Tensor]

# keeps the slope ratio finite on flat data, as in the published code
RATIO_EPS = 1e-8


def van_leer(r: torch.Tensor) -> torch.Tensor:
    """van Leer limiter (r + |r|) / (1 + |r|): 0 for r <= 0, 2r / (1 + r) otherwise.

    The published code divides by (1 + r), which is the same for r >= 0 but 0/0 at
    r = -1; the modulus removes that singularity without changing any other value.
    """
    return (r + r.abs()) / (1.0 + r.abs())


def minmod(r: torch.Tensor) -> torch.Tensor:
    """minmod limiter max(0, min(r, 1))."""
    return r.clamp(0.0, 1.0)


def tvd_faces(f: torch.Tensor, limiter: Limiter) -> torch.Tensor:
    """Limited upwind-biased face values f_{i+1/2}, i = 0..n-2 (``[..., n-1]``).

    f_{i+1/2} = f_i + phi(r_i) (f_{i+1} - f_i) / 2 with the slope ratio
    r_i = (f_i - f_{i-1}) / (f_{i+1} - f_i + 1e-8), and phi = 0 at the first cell
    (it has no upstream neighbour). The reconstruction assumes flow in +x, as in every
    1-D env of the benchmark.
    """
    d = f[..., 1:] - f[..., :-1]
    r = d[..., :-1] / (d[..., 1:] + RATIO_EPS)
    phi = torch.cat((torch.zeros_like(d[..., :1]), limiter(r)), -1)
    return f[..., :-1] + 0.5 * phi * d


def tvd_derivative(f: torch.Tensor, dx: float, limiter: Limiter) -> torch.Tensor:
    """df/dx at the interior cells from the TVD face values, (f_{i+1/2} - f_{i-1/2}) / dx.

    In flux form: summed over cells, the derivative telescopes to the difference of the
    two boundary faces, so a conservation law updated with it conserves its integral.
    """
    faces = tvd_faces(f, limiter)
    return (faces[..., 1:] - faces[..., :-1]) / dx


def rusanov(
    u_left: torch.Tensor,
    u_right: torch.Tensor,
    f_left: torch.Tensor,
    f_right: torch.Tensor,
    speed: torch.Tensor,
) -> torch.Tensor:
    """Rusanov (local Lax-Friedrichs) numerical flux between a left and a right state:
    (f_L + f_R) / 2 - c (u_R - u_L) / 2, with ``speed`` c the largest local wave speed."""
    return 0.5 * (f_left + f_right) - 0.5 * speed * (u_right - u_left)


def third_derivative(h: torch.Tensor, dx: float) -> torch.Tensor:
    """d3h/dx3 at the interior cells ``1..n-2``.

    The second-order one-sided stencil of the BEACON paper (a centred second derivative
    combined with a forward difference),
    (-h_{j+3} + 6 h_{j+2} - 12 h_{j+1} + 10 h_j - 3 h_{j-1}) / (2 dx^3),
    where h_{j+3} exists; at the last two interior cells, which lack it, the plain
    backward third difference (h_j - 3 h_{j-1} + 3 h_{j-2} - h_{j-3}) / dx^3. (A stencil
    reaching the outlet cell there lets the large pulses of a developed film blow up at
    the outlet; the backward one keeps the outflow stable.)
    """
    one_sided = (-h[..., 4:] + 6.0 * h[..., 3:-1] - 12.0 * h[..., 2:-2] + 10.0 * h[..., 1:-3] - 3.0 * h[..., :-4]) / (
        2.0 * dx**3
    )
    # j = n-3, n-2:  h_j, h_{j-1}, h_{j-2}, h_{j-3}
    backward = (h[..., -3:-1] - 3.0 * h[..., -4:-2] + 3.0 * h[..., -5:-3] - h[..., -6:-4]) / dx**3
    return torch.cat((one_sided, backward), -1)
