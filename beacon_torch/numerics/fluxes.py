"""Spatial operators of the 1-D environments (burgers, sloshing, shkadov).

All act on the last dimension of a ``[..., n]`` tensor of cell values and return values
at the interior cells ``1..n-2`` (``[..., n-2]``): the end cells are boundary cells that
each env sets itself.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from beacon_torch.numerics import native

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

    Where autograd records it (van Leer's or minmod's limiter), eagerly or in a compiled
    graph, its backward pass is :func:`tvd_adjoint`, written in the forward's stencil
    form, instead of autograd's graph of a dozen operations on shifted slices, whose
    compiled form re-reads each neighbour under masks (with its C loop vectorised, a
    differentiated compiled transition of burgers-v0 went from 12.1 to 8.9 times the
    compiled forward one, shkadov-v0's from 11.5 to 9.2). The forward's values are the
    same either way.
    """
    if limiter in _MINMOD and torch.is_grad_enabled() and f.requires_grad:
        return _TVDDerivative.apply(f, dx, _MINMOD[limiter])
    return _tvd_derivative(f, dx, limiter)


def _tvd_derivative(f: torch.Tensor, dx: float, limiter: Limiter) -> torch.Tensor:
    faces = tvd_faces(f, limiter)
    return (faces[..., 1:] - faces[..., :-1]) / dx


def _limiter_slope(r: torch.Tensor, minmod_limiter: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """The limiter's value and its derivative as autograd takes it: minmod's is 1 on
    [0, 1] (clamp's backward), van Leer's comes from the sign of r (0 at r = 0 for |r|)."""
    if minmod_limiter:
        return minmod(r), ((r >= 0.0) & (r <= 1.0)).to(r.dtype)
    a, s = r.abs(), torch.sign(r)
    q = 1.0 + a
    return (r + a) / q, (1.0 + s) / q - (r + a) * s / (q * q)


def tvd_adjoint_tensors(f: torch.Tensor, grad: torch.Tensor, dx: float, minmod_limiter: bool) -> torch.Tensor:
    """:func:`tvd_adjoint` as tensor operations (any device and dtype): per face j its
    gradient G_j, then what it hands the differences it read (A_j to d_j, W_j to
    d_{j-1}, the limiter's slope included), then each cell's share of the differences
    next to it."""
    pad = torch.nn.functional.pad
    d = f[..., 1:] - f[..., :-1]
    den = d[..., 1:] + RATIO_EPS
    r = d[..., :-1] / den
    phi, slope = _limiter_slope(r, minmod_limiter)
    scaled = grad / dx
    faces = pad(scaled, (1, 0)) - pad(scaled, (0, 1))  # G_j, j = 0..n-2
    w = 0.5 * faces[..., 1:] * d[..., 1:] * slope / den
    a = 0.5 * faces[..., 1:] * phi - w * r
    differences = pad(a, (1, 0)) + pad(w, (0, 1))  # the gradient of d_j, j = 0..n-2
    return pad(faces, (0, 1)) - pad(differences, (0, 1)) + pad(differences, (1, 0))


def _tvd_adjoint(f: torch.Tensor, grad: torch.Tensor, dx: float, minmod_limiter: bool) -> torch.Tensor:
    """The gradient of ``f`` (``[..., n]``) of :func:`tvd_derivative` with van Leer's
    limiter (or minmod's) from the gradient ``grad`` (``[..., n - 2]``) of its result:
    the C loop on the CPU (one pass a row), :func:`tvd_adjoint_tensors` elsewhere. An
    operator, so that a compiled backward pass calls it as it is."""
    if native.applies(f.device, f.dtype) and native.takes(f, grad):
        return native.tvd_adjoint(f, grad, dx, minmod_limiter)
    return tvd_adjoint_tensors(f, grad, dx, minmod_limiter)


def _rows_vmap(info, in_dims, f, grad, dx, minmod_limiter):
    # every leading dimension is a row: the mapped one joins them at the front
    front = lambda t, dim: t.unsqueeze(0).expand(info.batch_size, *t.shape) if dim is None else t.movedim(dim, 0)
    return tvd_adjoint(front(f, in_dims[0]), front(grad, in_dims[1]), dx, minmod_limiter), 0


tvd_adjoint = native.operator(
    "tvd_adjoint(Tensor f, Tensor grad, float dx, bool minmod_limiter) -> Tensor",
    _tvd_adjoint,
    lambda f, grad, dx, minmod_limiter: torch.empty_like(f, memory_format=torch.contiguous_format),
    _rows_vmap,
    key="CompositeExplicitAutograd",
)


class _TVDDerivative(torch.autograd.Function):
    """:func:`_tvd_derivative` with :func:`tvd_adjoint` as its backward pass."""

    generate_vmap_rule = True

    @staticmethod
    def forward(f: torch.Tensor, dx: float, minmod_limiter: bool) -> torch.Tensor:
        return _tvd_derivative(f, dx, minmod if minmod_limiter else van_leer)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        f, ctx.dx, ctx.minmod = inputs
        ctx.save_for_backward(f)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        (f,) = ctx.saved_tensors
        with torch.no_grad():  # differentiable once: the adjoint keeps no graph
            return tvd_adjoint(f, grad, ctx.dx, ctx.minmod), None, None


# the limiters whose slope the adjoint knows (is it minmod?)
_MINMOD = {van_leer: False, minmod: True}


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
