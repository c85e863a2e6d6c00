"""Transport of a scalar (temperature, concentration) by the corrected velocity: the
published in-place sweep, batch last."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from beacon_torch.numerics import native
from beacon_torch.numerics.staggered import Stretched


class Sweep:
    """The published scalar transport: explicit centred advection-diffusion written in
    place, cell after cell (x outer, y inner), so that each cell's update already reads
    the new values of its west and south neighbours and the old ones of its east and
    north neighbours. That ordering is part of the scheme: it is what keeps the
    published forward-Euler transport stable at rayleigh's diffusion number (2.37 for
    the grid-scale mode, beyond plain forward Euler's 2) and at mixing's cell Peclet
    number of 100.

    Written out, each new value is ``c + a * west_new + b * south_new`` with ``a``,
    ``b``, ``c`` from the old field and the velocities, a recurrence along the
    anti-diagonals ``i + j = k``: the cells of one anti-diagonal depend only on the
    previous one. So the sweep runs as ``nx + ny - 1`` batched vector steps over skewed
    copies of the fields (each anti-diagonal one row), exact to round-off, with no loop
    over cells or members. Ghost values are those the field carries in (the published
    code refreshes them before the sweep only).

    On the CPU the loop itself runs in C (:mod:`beacon_torch.numerics.native`), its
    gradient the reverse loop: the anti-diagonal steps cost a few microseconds each
    whatever their size, which at small batches is most of a cavity step, and a graph
    of them most of a differentiated one. The tensor recurrence is the path everywhere
    else (GPU, no C compiler)."""

    def __init__(self, nx: int, ny: int, device=None, dtype=torch.float32) -> None:
        self.nx, self.ny = nx, ny
        # decided once, so that a compiled substep sees a constant
        self.native = native.applies(device, dtype)
        width, height = nx + 2, ny + 2
        k = torch.arange(nx + ny + 3)[:, None]
        i = torch.arange(width)[None, :]
        j = k - i
        inside = (j >= 0) & (j < height)
        # skewed row k, position i <- ghosted cell (i, k - i); outside the grid, a zero
        # appended after the flattened field
        self.skew = torch.where(inside, i * height + j, width * height).to(device)
        ii, jj = torch.meshgrid(torch.arange(1, nx + 1), torch.arange(1, ny + 1), indexing="ij")
        # interior cell (i, j) is row i + j, position i of the skewed field
        self.unskew_k, self.unskew_i = (ii + jj).to(device), ii.to(device)

    def _skewed(self, f: torch.Tensor) -> torch.Tensor:
        flat = f.reshape(-1, f.shape[-1])
        flat = torch.cat((flat, flat.new_zeros((1, flat.shape[1]))))
        return flat[self.skew]

    def __call__(
        self, s: torch.Tensor, u: torch.Tensor, v: torch.Tensor, kappa, dt: float, dx: float, dy: float
    ) -> torch.Tensor:
        """New cell values ``[nx, ny, B]`` of the scalar ``s`` given with its ghosts
        (``[nx + 2, ny + 2, B]``), transported by the face velocities ``u``
        ``[nx + 1, ny, B]`` and ``v`` ``[nx, ny + 1, B]`` over ``dt``."""
        sc = s[1:-1, 1:-1]
        c, a, b = _coefficients(s, u, v, kappa, dt, dx, dy)
        pad = lambda f: F.pad(f, (0, 0, 1, 1, 1, 1))
        if self.native and native.takes(s, u, v, c):
            return native.sweep(s + pad(c - sc), a, b)[1:-1, 1:-1]
        recording = native.recording(s, u, v, c)
        # the ghosts keep their values (a = b = 0 there)
        c = self._skewed(s + pad(c - sc))
        a, b = self._skewed(pad(a)), self._skewed(pad(b))
        last = self.nx + self.ny  # the last anti-diagonal with interior cells
        if recording or torch.compiler.is_compiling():
            rows = _graph_rows(c, a, b, last)
        else:
            rows = _rows(c, a, b, last)
        return rows[self.unskew_k, self.unskew_i]


def _coefficients(s: torch.Tensor, u: torch.Tensor, v: torch.Tensor, kappa, dt: float, dx: float, dy):
    """The explicit centred update of the cells written as ``c + a * west + b * south``:
    ``c`` holds every term but the west and south neighbours', ``a`` and ``b`` their
    weights, each ``[nx, ny, B]``. ``dy`` is a number (equal cells) or a
    :class:`~beacon_torch.numerics.staggered.Stretched` axis."""
    sc, se, sn = s[1:-1, 1:-1], s[2:, 1:-1], s[1:-1, 2:]
    uw, ue, vs, vn = u[:-1], u[1:], v[:, :-1], v[:, 1:]
    if isinstance(dy, Stretched):
        # conservative on unequal rows: each face's flux over its cell's width, the
        # diffusive ones over the distance between the centres beside the face
        width = dy.widths
        kx, ks, kn = kappa / dx**2, kappa / (dy.gaps[:, :-1] * width), kappa / (dy.gaps[:, 1:] * width)
        c = sc + dt * (
            kx * (se - 2.0 * sc)
            + kn * (sn - sc)
            - ks * sc
            - (ue * 0.5 * (se + sc) - uw * 0.5 * sc) / dx
            - (vn * 0.5 * (sn + sc) - vs * 0.5 * sc) / width
        )
        return c, dt * (kx + 0.5 * uw / dx), dt * (ks + 0.5 * vs / width)
    kx, ky = kappa / dx**2, kappa / dy**2
    c = sc + dt * (
        kx * (se - 2.0 * sc)
        + ky * (sn - 2.0 * sc)
        - (ue * 0.5 * (se + sc) - uw * 0.5 * sc) / dx
        - (vn * 0.5 * (sn + sc) - vs * 0.5 * sc) / dy
    )
    return (c, *_weights(u, v, kappa, dt, dx, dy))


def _weights(u: torch.Tensor, v: torch.Tensor, kappa, dt: float, dx: float, dy: float):
    """The west and south neighbours' weights of :func:`_coefficients` on equal cells."""
    return dt * (kappa / dx**2 + 0.5 * u[:-1] / dx), dt * (kappa / dy**2 + 0.5 * v[:, :-1] / dy)


def sweep_adjoint(
    grad: torch.Tensor, swept: torch.Tensor, s: torch.Tensor, u: torch.Tensor, v: torch.Tensor, kappa, dt, dx, dy
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The gradients of the ghosted scalar ``s`` and the velocities ``u``, ``v`` that
    the C :class:`Sweep` read (equal cells), from ``grad``, that of its result given with
    the ghosts as the substep keeps them (``[nx + 2, ny + 2, B]``: the ghosts are ``s``'s
    own), and ``swept``, that result: the reverse sweep, then the adjoint of
    :func:`_coefficients` in its own stencil form (each cell gathering what the
    neighbours' updates that read it send back)."""
    a, b = _weights(u, v, kappa, dt, dx, dy)
    pad = lambda f: F.pad(f, (0, 0, 1, 1, 1, 1))
    interior = grad[1:-1, 1:-1]
    gf, ga, gb = native.sweep_adjoint(pad(interior), swept, a, b)
    gc = gf[1:-1, 1:-1]
    sc, se, sn = s[1:-1, 1:-1], s[2:, 1:-1], s[1:-1, 2:]
    uw, ue, vs, vn = u[:-1], u[1:], v[:, :-1], v[:, 1:]
    kx, ky = kappa / dx**2, kappa / dy**2
    h = 0.5 * dt
    g_sc = gc * (1.0 + dt * (-2.0 * kx - 2.0 * ky) - (h / dx) * (ue - uw) - (h / dy) * (vn - vs))
    g_se = gc * (dt * kx - (h / dx) * ue)
    g_sn = gc * (dt * ky - (h / dy) * vn)
    # the ghosts' own gradients: the result's ghosts are s's, and the reverse sweep's
    gs = gf + (grad - pad(interior)) + pad(g_sc) + F.pad(g_se, (0, 0, 1, 1, 2, 0)) + F.pad(g_sn, (0, 0, 2, 0, 1, 1))
    g_w = (h / dx) * (gc * sc + ga)
    g_s = (h / dy) * (gc * sc + gb)
    gu = F.pad(g_w, (0, 0, 0, 0, 0, 1)) - F.pad((h / dx) * gc * (se + sc), (0, 0, 0, 0, 1, 0))
    gv = F.pad(g_s, (0, 0, 0, 1)) - F.pad((h / dy) * gc * (sn + sc), (0, 0, 1, 0))
    return gs - pad(gf[1:-1, 1:-1]), gu, gv


class Explicit:
    """The same centred advection-diffusion with every neighbour's old value: plain
    forward Euler. Where the x axis wraps around (a channel), an ordered sweep would
    favour the cell where it starts and break the flow's invariance under translation;
    this update keeps it (the price: the forward-Euler limit on the time step)."""

    def __call__(
        self, s: torch.Tensor, u: torch.Tensor, v: torch.Tensor, kappa, dt: float, dx: float, dy: float
    ) -> torch.Tensor:
        """New cell values ``[nx, ny, B]``, as :meth:`Sweep.__call__`."""
        c, a, b = _coefficients(s, u, v, kappa, dt, dx, dy)
        return c + a * s[:-2, 1:-1] + b * s[1:-1, :-2]


# The in-place recurrence runs eagerly: a chain of hundreds of dependent steps cannot be
# fused. A compiled step (a GPU's, or a CPU's without the C kernels) takes the
# out-of-place one into its graph instead, unrolled: a graph break is refused there (the
# whole step is one graph, its substeps a while_loop), and compiling it takes longer.
@torch.compiler.disable
def _rows(c: torch.Tensor, a: torch.Tensor, b: torch.Tensor, last: int) -> torch.Tensor:
    """The skewed rows of the swept field, in place in one buffer. Rows have width
    w + 1 with a zero in front: row k's west cells are then row k - 1 without its last
    element, its south cells row k - 1 without the zero, and every view is taken once,
    outside the loop."""
    buf = F.pad(c[: last + 1], (0, 0, 1, 0))
    rows, wests = buf[:, 1:].unbind(0), buf[:, :-1].unbind(0)
    a, b = a.unbind(0), b.unbind(0)
    for k in range(2, last + 1):
        rows[k].addcmul_(a[k], wests[k - 1]).addcmul_(b[k], rows[k - 1])
    return buf[:, 1:]


def _graph_rows(c: torch.Tensor, a: torch.Tensor, b: torch.Tensor, last: int) -> torch.Tensor:
    """The same recurrence out of place, so that autograd keeps every row and a
    compiled graph can hold it."""
    rows = [c[0], c[1]]  # ghosts only
    for k in range(2, last + 1):
        # roll: position i reads the previous row's i - 1 (the west cell); position 0 is
        # a ghost, whose a is zero
        rows.append(c[k] + a[k] * rows[-1].roll(1, 0) + b[k] * rows[-1])
    return torch.stack(rows)
