"""Pressure-increment solvers of the projection step, batch last (``[X, Y, B]``): the
direct solve (:class:`PoissonSolver`, eigenvectors of the 1-D second differences)
and the published Jacobi iterations (:class:`JacobiSolver`, for exact comparisons
with the published code)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F

from beacon_torch.numerics import native
from beacon_torch.numerics.grid import GRADIENT, NEUMANN, PERIODIC, VALUE, ZERO, ZERO_FACE, ZERO_GHOST, Ghosts


def laplacian_1d(n: int, h: float, low: str, high: str) -> torch.Tensor:
    """The ``[n, n]`` second-difference matrix with the boundary rows of each condition:
    zero normal gradient (ghost = neighbour), a zero ghost value, or a zero value on the
    wall face (ghost = -neighbour); or an axis that wraps around (PERIODIC, both ends)."""
    a = torch.diag(torch.full((n,), -2.0, dtype=torch.float64))
    a += torch.diag(torch.ones(n - 1, dtype=torch.float64), 1) + torch.diag(torch.ones(n - 1, dtype=torch.float64), -1)
    if PERIODIC in (low, high):
        if low != high:
            raise ValueError("a periodic axis wraps around: both its ends must be PERIODIC")
        a[0, -1] += 1.0
        a[-1, 0] += 1.0
        return a / h**2
    for index, kind in ((0, low), (n - 1, high)):
        if kind == NEUMANN:
            a[index, index] = -1.0
        elif kind == ZERO_FACE:
            a[index, index] = -3.0
        elif kind != ZERO_GHOST:
            raise ValueError(f"boundary condition must be {NEUMANN!r}, {ZERO_GHOST!r} or {ZERO_FACE!r}, got {kind!r}")
    return a / h**2


def _mm(a: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
    """``a`` applied along the first axis of a batch-last field ``[n, m, B]``."""
    n, m, b = f.shape
    return (a @ f.reshape(n, m * b)).reshape(a.shape[0], m, b)


def _mm_second(a: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
    """``a`` applied along the second axis of ``[n, m, B]`` as one matrix product over
    every row and member (a transposed view back, contiguous as ``[m, n, B]``)."""
    n, m, b = f.shape
    return (a @ f.transpose(0, 1).reshape(m, n * b)).reshape(a.shape[0], n, b).transpose(0, 1)


# below this many members the y products of the Poisson solve run as one matrix product
# over all x rows, as a batch of matrix-vector products is slow for few members; from
# here on the batched products are faster (docs/performance.md)
FEW_MEMBERS = 32


class _Basis:
    """Orthonormal eigenvectors ``q`` of a 1-D operator, applied along the first axis
    of batch-last fields. When the operator is symmetric under reversal of the axis (the
    same condition on both walls) and ``n`` is even, every eigenvector is even or odd,
    and each product is two half-size products of the folded field: half the work of
    the dense one (the products are most of the Poisson solve)."""

    def __init__(self, q: torch.Tensor, symmetric: bool, dtype, device, scale: torch.Tensor | None = None) -> None:
        n = q.shape[0]
        self.n = n
        self.folded = symmetric and n % 2 == 0
        # on a stretched grid the eigenvectors are orthonormal in the cell widths' inner
        # product: forward with q^T diag(scale), back with diag(1 / scale) q
        fwd, inv = (q, q) if scale is None else (q * scale[:, None], q / scale[:, None])
        if self.folded:
            h = n // 2
            even = (q - q.flip(0)).abs().amax(0) < 1e-8
            if int(even.sum()) != h or not ((q + q.flip(0)).abs().amax(0)[~even] < 1e-8).all():
                raise AssertionError("eigenvectors of a reversal-symmetric operator must be even or odd")
            self.order = torch.cat((even.nonzero()[:, 0], (~even).nonzero()[:, 0]))
            self.qe = inv[:h, even].to(dtype=dtype, device=device)  # [h, h]: top half of the even ones
            self.qo = inv[:h, ~even].to(dtype=dtype, device=device)
            self.qet = fwd[:h, even].T.contiguous().to(dtype=dtype, device=device)
            self.qot = fwd[:h, ~even].T.contiguous().to(dtype=dtype, device=device)
        # copies of their own: eigh's vectors are column-major, so q^T would otherwise
        # share q's storage, which a compiled loop refuses as aliased inputs
        self.q = inv.to(dtype=dtype, device=device).clone()
        self.qt = fwd.T.to(dtype=dtype, device=device).contiguous().clone()

    def forward(self, f: torch.Tensor) -> list[torch.Tensor]:
        """q^T f: the coefficients, as one block or as the (even, odd) blocks."""
        if not self.folded:
            return [_mm(self.qt, f)]
        h = self.n // 2
        top, bottom = f[:h], f[h:].flip(0)
        return [_mm(self.qet, top + bottom), _mm(self.qot, top - bottom)]

    def inverse(self, c: list[torch.Tensor]) -> torch.Tensor:
        """q c, for coefficient blocks as :meth:`forward` returns them."""
        if not self.folded:
            return _mm(self.q, c[0])
        even, odd = _mm(self.qe, c[0]), _mm(self.qo, c[1])
        return torch.cat((even + odd, (even - odd).flip(0)))

    def blocks(self, values: torch.Tensor) -> list[torch.Tensor]:
        """Per-eigenvector values (along the first axis, eigh's order) split into the
        blocks of :meth:`forward`."""
        if not self.folded:
            return [values]
        h = self.n // 2
        ordered = values[self.order]
        return [ordered[:h], ordered[h:]]


def _eliminate(ly: torch.Tensor, shifts: torch.Tensor, tol: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Gaussian elimination (no pivoting: the systems are diagonally dominant) of the
    tridiagonal ``ly + shift`` for each shift: the multipliers below the diagonal and
    the inverse pivots, ``[shifts, n]`` each, and which systems are singular (their last
    pivot is zero to ``tol``; its inverse is set to zero)."""
    n = ly.shape[0]
    diag = ly.diagonal()[None, :] + shifts[:, None]
    sub, sup = ly.diagonal(-1), ly.diagonal(1)
    lower, pivot = torch.zeros_like(diag), torch.zeros_like(diag)
    pivot[:, 0] = diag[:, 0]
    for j in range(1, n):
        lower[:, j] = sub[j - 1] / pivot[:, j - 1]
        pivot[:, j] = diag[:, j] - lower[:, j] * sup[j - 1]
    singular = pivot[:, -1].abs() < tol
    if (pivot[:, :-1].abs() < tol).any():
        raise AssertionError("only the last pivot of a diagonally dominant system can vanish")
    inv = 1.0 / pivot
    inv[singular, -1] = 0.0
    return lower, inv, singular


def _increment_ghosts(nx: int, ny: int, bc: Sequence[str], dtype, device) -> Ghosts:
    """The ghost map of an increment solved with the conditions ``bc`` (left, right,
    bottom, top)."""
    factor = {NEUMANN: GRADIENT, ZERO_GHOST: ZERO, ZERO_FACE: VALUE, PERIODIC: PERIODIC}
    return Ghosts.cells(nx, ny, *(factor[kind] for kind in bc), dtype=dtype, device=device)


class PoissonSolver:
    """Direct solver of the 5-point Poisson equation on an ``nx x ny`` cell grid, for
    batch-last fields ``[nx, ny, B]``.

    The 2-D operator is separable, L = Lx (x) I + I (x) Ly; with the eigendecompositions
    Lx = Qx diag(ex) Qx^T and Ly = Qy diag(ey) Qy^T (computed once, in float64), the
    solve is four matrix products and a division, exact to round-off (the x products
    are folded in halves when both side walls have the same condition). With zero normal
    gradient on every wall the constant mode has eigenvalue 0 and is dropped: the
    solution has zero mean and the source must have zero sum (it does, for the
    divergence of a field with no flux through the walls).

    On the CPU the two y products and the division are replaced by what they compute
    (differentiable: the adjoint of a solve is the same solve): in the x eigenbasis each x mode k is the
    tridiagonal system (Ly + ex_k) phi_k = rhs_k along y, eliminated once here and solved
    in C (:func:`beacon_torch.numerics.native.lines`), a few operations a cell instead
    of ``2 ny`` multiply-adds (the y products were two thirds of a mixing substep's
    solve). The singular mode of the all-walls-Neumann problem keeps a zero last value
    and then loses its mean along y, which is the same zero-mean solution.

    ``bc`` gives the conditions on the (left, right, bottom, top) walls.
    """

    def __init__(
        self,
        nx: int,
        ny: int,
        dx: float,
        dy: float,
        bc: Sequence[str] = (NEUMANN,) * 4,
        *,
        dtype: torch.dtype = torch.float64,
        device="cpu",
    ) -> None:
        left, right, bottom, top = bc
        if PERIODIC in (bottom, top):
            raise ValueError("only the x axis of the Poisson solve may be periodic")
        lx, ly = laplacian_1d(nx, dx, left, right), laplacian_1d(ny, dy, bottom, top)
        # a periodic axis's eigenvectors come in degenerate pairs, neither even nor odd
        self.periodic = left == PERIODIC
        self._build(lx, ly, None, None, left == right and not self.periodic, min(dx, dy), dtype, device)
        self.bc = tuple(bc)
        # the increment's ghost values, for its gradient on the wall faces
        self.ghosts = _increment_ghosts(nx, ny, bc, dtype, device)

    @classmethod
    def stretched(
        cls,
        lx: torch.Tensor,
        wx: torch.Tensor | None,
        ly: torch.Tensor,
        wy: torch.Tensor,
        *,
        bc: Sequence[str] | None = None,
        dtype,
        device,
    ) -> PoissonSolver:
        """The solver of a stretched tensor-product grid, from its float64 1-D operators
        ``lx`` (``[nx, nx]``) and ``ly``: each is ``diag(1 / w) S`` with ``S`` symmetric
        and ``w`` the cells' widths ``wx``, ``wy`` (a divergence of a gradient; ``wx``
        None: ``lx`` is symmetric itself, equal cells, periodic if it couples its two
        ends). The x products are folded when the x grid and its conditions are mirror
        images. ``bc`` (left, right, bottom, top) gives the increment's ghosts, for
        :func:`~beacon_torch.numerics.staggered.project`."""
        solver = cls.__new__(cls)
        solver.periodic = lx.shape[0] > 2 and bool(lx[0, -1] != 0)
        mirrored = wx is None or torch.equal(wx, wx.flip(0))
        symmetric = not solver.periodic and torch.equal(lx, lx.flip(0, 1)) and mirrored
        # the narrowest cell, the scale of the singular mode's threshold
        hx = float((2.0 / lx.diagonal().abs().max()) ** 0.5) if wx is None else float(wx.min())
        solver._build(lx, ly, wx, wy, symmetric, min(hx, float(wy.min())), dtype, device)
        if bc is not None:
            solver.bc = tuple(bc)
            solver.ghosts = _increment_ghosts(lx.shape[0], ly.shape[0], bc, dtype, device)
        return solver

    @staticmethod
    def _eigen(a: torch.Tensor, w: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Eigenvalues and vectors of ``a`` = ``diag(1 / w) S`` through the symmetric
        ``diag(w)^(1/2) a diag(w)^(-1/2)``, and the scale ``sqrt(w)`` (None: ``a`` is
        symmetric itself)."""
        if w is None:
            e, q = torch.linalg.eigh(a)
            return e, q, None
        scale = w.sqrt()
        m = scale[:, None] * a / scale[None, :]
        e, q = torch.linalg.eigh(0.5 * (m + m.T))
        return e, q, scale

    def _build(self, lx, ly, wx, wy, symmetric: bool, h: float, dtype, device) -> None:
        ex, qx, sx = self._eigen(lx, wx)
        ey, qy, sy = self._eigen(ly, wy)
        self.lx = lx.to(dtype=dtype, device=device)
        self.ly = ly.to(dtype=dtype, device=device)
        self.x = _Basis(qx, symmetric, dtype, device, sx)
        eig = ex[:, None] + ey[None, :]
        scale = 1.0 / h**2
        inv = torch.where(eig.abs() < 1e-9 * scale, torch.zeros_like(eig), 1.0 / eig)
        qy_inv, qy_fwd = (qy, qy) if sy is None else (qy / sy[:, None], qy * sy[:, None])
        self.qy = qy_inv.to(dtype=dtype, device=device)
        self.qyt = qy_fwd.T.contiguous().to(dtype=dtype, device=device)
        self.inv = [block[:, :, None].to(dtype=dtype, device=device).contiguous() for block in self.x.blocks(inv)]
        # decided once, so that a compiled step sees a constant
        self.native = native.applies(device, dtype)
        if self.native:
            cast = lambda t: t.to(dtype=dtype, device=device)
            self.upper = cast(torch.cat((ly.diagonal(1), ly.new_zeros(1))))
            # what the solves' adjoint reads: ly = diag(1 / wy) S with S symmetric
            self.width = cast(wy if wy is not None else torch.ones(ly.shape[0], dtype=torch.float64))
            self.lines, self.singular = [], []
            for shift in self.x.blocks(ex):
                lower, inverse, singular = _eliminate(ly, shift, 1e-9 * scale)
                self.lines.append((cast(lower), cast(inverse)))
                # per block, a 0/1 factor on the modes whose mean along y goes
                self.singular.append(cast(singular)[:, None, None] if bool(singular.any()) else None)

    def solve(self, rhs: torch.Tensor) -> torch.Tensor:
        """phi with L phi = rhs, both ``[nx, ny, B]``."""
        if self.native and native.takes(rhs, self.upper):
            hat = []
            for c, (lower, inv), singular in zip(self.x.forward(rhs), self.lines, self.singular, strict=True):
                c = native.lines(c, lower, inv, self.upper, self.width)
                hat.append(c if singular is None else c - singular * c.mean(1, keepdim=True))
            return self.x.inverse(hat)
        blocks = zip(self.x.forward(rhs), self.inv, strict=True)
        if rhs.shape[-1] < FEW_MEMBERS:
            hat = [_mm_second(self.qy, _mm_second(self.qyt, c) * inv) for c, inv in blocks]
        else:
            # the y products broadcast over x
            hat = [self.qy @ ((self.qyt @ c) * inv) for c, inv in blocks]
        return self.x.inverse(hat)

    def apply(self, phi: torch.Tensor) -> torch.Tensor:
        """L phi, with the solver's boundary conditions (for checks and tests)."""
        return _mm(self.lx, phi) + self.ly @ phi


class JacobiSolver:
    """The published pressure-increment solve, for exact comparisons with the published
    code: Jacobi iterations from zero, each member stopping as soon as the sum of the
    squared updates over its ghosted array (corners excluded, as there) falls to
    ``tol`` (rayleigh 1e-8, mixing 1e-4). The answer depends on that tolerance; the
    direct :class:`PoissonSolver` gives the converged increment, about 1e-4 from it
    relative on rayleigh's rewards. One host synchronisation per iteration, so it runs
    eagerly only."""

    def __init__(self, nx: int, ny: int, dx: float, dy: float, bc: Sequence[str], tol: float, *, dtype, device) -> None:
        self.nx, self.ny, self.dx, self.dy, self.tol = nx, ny, dx, dy, tol
        self.periodic = False
        self.top_zero = bc[3] == ZERO_GHOST
        if tuple(bc[:3]) != (NEUMANN,) * 3:
            raise ValueError("the published Jacobi solve has zero normal gradient on the left, right and bottom walls")
        factor = {NEUMANN: GRADIENT, ZERO_GHOST: ZERO}
        self.ghosts = Ghosts.cells(nx, ny, *(factor[kind] for kind in bc), dtype=dtype, device=device)

    def _ghosted(self, inner: torch.Tensor) -> torch.Tensor:
        top = inner[:, -1:] * (0.0 if self.top_zero else 1.0)
        middle = torch.cat((inner[:, :1], inner, top), 1)
        side = lambda row: F.pad(row, (0, 0, 1, 1))
        return torch.cat((side(inner[:1]), middle, side(inner[-1:])))

    def solve(self, rhs: torch.Tensor) -> torch.Tensor:
        if torch.compiler.is_compiling():
            raise RuntimeError(
                "solver='jacobi' stops on each member's own tolerance and runs eagerly only; use compile=False"
            )
        dx2, dy2 = self.dx**2, self.dy**2
        phi = rhs.new_zeros((self.nx + 2, self.ny + 2, rhs.shape[-1]))
        active = torch.ones(rhs.shape[-1], dtype=torch.bool, device=rhs.device)
        while True:
            inner = (
                0.5
                * ((phi[2:, 1:-1] + phi[:-2, 1:-1]) * dy2 + (phi[1:-1, 2:] + phi[1:-1, :-2]) * dx2 - rhs * dx2 * dy2)
                / (dx2 + dy2)
            )
            new = self._ghosted(inner)
            err = ((new - phi) ** 2).sum((0, 1))
            phi = torch.where(active, new, phi)
            active = active & (err > self.tol)
            if not bool(active.any()):
                break
        return phi[1:-1, 1:-1]
