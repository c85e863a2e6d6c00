"""Batched incompressible flow on a staggered grid, for rayleigh and mixing.

Layout: every field is ``[X, Y, B]``, x first, **batch last**. The members are the
contiguous dimension, so a stencil shift moves whole rows of members: the fused kernels
of the compiled path then vectorise across the batch with no tails and no masks (the
comparison with batch first: docs/performance.md). Envs keep their state batch first
with ghost layers (``[B, nx + 2, ny + 2]``, what probes and rendering read) and convert
once per action with :meth:`Cavity.fields` and :meth:`Cavity.stored`.

What the solver carries (no ghost values):
- ``u``: x-velocity on the x-faces ``0..nx`` of the ``nx`` cells (faces 0 and nx are the
  left and right walls), ``[nx + 1, ny, B]``;
- ``v``: y-velocity on the y-faces ``0..ny`` (bottom and top walls), ``[nx, ny + 1, B]``;
- pressure and scalars (temperature, concentration): cell-centred, ``[nx, ny, B]``.

Ghost values are gathered from these when a stencil needs them (:class:`Ghosts`: an
index map and a factor per position, plus an offset for prescribed wall values), which
the compiler fuses into the stencil's kernel instead of writing ghost layers.

One substep of the published scheme: an explicit predictor with centred fluxes
(face-averaged velocities) and the current pressure, a projection with the pressure
increment from a direct Poisson solve (or, to compare with the published code to
round-off, its Jacobi iterations), then the published in-place sweep of explicit
centred transport of the scalar by the corrected velocity (:class:`Sweep`). Everything
is out of place, so the graph survives when gradients are wanted.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F

from beacon_torch.numerics import native

NEUMANN = "neumann"
ZERO_GHOST = "zero_ghost"
ZERO_FACE = "zero_face"  # zero value on the wall face itself (an open boundary's pressure)
# ghost factors: zero normal gradient (ghost = neighbour), a value imposed through the
# ghost (ghost = 2 value - neighbour, the value comes as an offset), a zero ghost
GRADIENT, VALUE, ZERO = 1.0, -1.0, 0.0


def laplacian_1d(n: int, h: float, low: str, high: str) -> torch.Tensor:
    """The ``[n, n]`` second-difference matrix with the boundary rows of each condition:
    zero normal gradient (ghost = neighbour), a zero ghost value, or a zero value on the
    wall face (ghost = -neighbour)."""
    a = torch.diag(torch.full((n,), -2.0, dtype=torch.float64))
    a += torch.diag(torch.ones(n - 1, dtype=torch.float64), 1) + torch.diag(torch.ones(n - 1, dtype=torch.float64), -1)
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
        self.q = inv.to(dtype=dtype, device=device)
        self.qt = fwd.T.contiguous().to(dtype=dtype, device=device)

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

    On the CPU, where autograd has nothing to record, the two y products and the
    division are replaced by what they compute: in the x eigenbasis each x mode k is the
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
        lx, ly = laplacian_1d(nx, dx, left, right), laplacian_1d(ny, dy, bottom, top)
        self._build(lx, ly, None, None, left == right, min(dx, dy), dtype, device)
        self.bc = tuple(bc)
        factor = {NEUMANN: GRADIENT, ZERO_GHOST: ZERO, ZERO_FACE: VALUE}
        # the increment's ghost values, for its gradient on the wall faces
        self.ghosts = Ghosts.cells(nx, ny, *(factor[kind] for kind in bc), dtype=dtype, device=device)

    @classmethod
    def stretched(
        cls, lx: torch.Tensor, wx: torch.Tensor, ly: torch.Tensor, wy: torch.Tensor, *, dtype, device
    ) -> PoissonSolver:
        """The solver of a stretched tensor-product grid, from its float64 1-D operators
        ``lx`` (``[nx, nx]``) and ``ly``: each is ``diag(1 / w) S`` with ``S`` symmetric
        and ``w`` the cells' widths ``wx``, ``wy`` (a divergence of a gradient). The x
        products are folded when the x grid and its conditions are mirror images."""
        solver = cls.__new__(cls)
        symmetric = torch.equal(lx, lx.flip(0, 1)) and torch.equal(wx, wx.flip(0))
        solver._build(lx, ly, wx, wy, symmetric, float(min(wx.min(), wy.min())), dtype, device)
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
                c = native.lines(c, lower, inv, self.upper)
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


class Ghosts:
    """A field with ghost values, gathered from its stored values: along each axis an
    index map into the stored positions and a factor per extended position (the
    product of the two axes' factors multiplies the gathered value), plus an optional
    offset that carries prescribed wall values (``ghost = 2 value - neighbour``)."""

    def __init__(self, index_x, factor_x, index_y, factor_y, *, dtype, device) -> None:
        as_index = lambda i: None if i is None else torch.tensor(i, dtype=torch.int64, device=device)
        self.ix, self.iy = as_index(index_x), as_index(index_y)
        fx = torch.tensor(factor_x, dtype=torch.float64)
        fy = torch.tensor(factor_y, dtype=torch.float64)
        self.factor = (fx[:, None, None] * fy[None, :, None]).to(dtype=dtype, device=device)

    @staticmethod
    def _cell_axis(n: int, low: float, high: float):
        return [0, *range(n), n - 1], [low, *[1.0] * n, high]

    @classmethod
    def cells(
        cls, nx: int, ny: int, left: float, right: float, bottom: float, top: float, *, corners: bool = True, **kw
    ) -> Ghosts:
        """Cell-centred ``[nx, ny, B]`` to ``[nx + 2, ny + 2, B]``; each wall's factor is
        GRADIENT, VALUE or ZERO. No stencil reads the four corner ghosts; ``corners``
        False leaves them at zero (where a reward averages over the ghosted array, as
        the published mixing reward does)."""
        ghosts = cls(*cls._cell_axis(nx, left, right), *cls._cell_axis(ny, bottom, top), **kw)
        if not corners:
            ghosts.factor[[0, 0, -1, -1], [0, -1, 0, -1]] = 0.0
        return ghosts

    @classmethod
    def u_faces(cls, nx: int, ny: int, **kw) -> Ghosts:
        """x-face velocity ``[nx + 1, ny, B]`` to ``[nx + 1, ny + 2, B]``: impermeable
        side walls (zeroed), tangential velocity on the bottom and top through the
        ghosts."""
        return cls(None, [0.0, *[1.0] * (nx - 1), 0.0], *cls._cell_axis(ny, VALUE, VALUE), **kw)

    @classmethod
    def v_faces(cls, nx: int, ny: int, **kw) -> Ghosts:
        """y-face velocity ``[nx, ny + 1, B]`` to ``[nx + 2, ny + 1, B]``."""
        return cls(*cls._cell_axis(nx, VALUE, VALUE), None, [0.0, *[1.0] * (ny - 1), 0.0], **kw)

    def __call__(self, f: torch.Tensor, offset: torch.Tensor | None = None) -> torch.Tensor:
        if self.ix is not None:
            f = f[self.ix]
        if self.iy is not None:
            f = f[:, self.iy]
        f = f * self.factor
        return f if offset is None else f + offset


def edge_offset(n: int, axis: int, low, high, like: torch.Tensor) -> torch.Tensor:
    """A ghost offset that is ``2 low`` on the first and ``2 high`` on the last of ``n``
    positions along ``axis`` (0 or 1) and zero elsewhere; ``low``/``high`` are numbers
    or tensors that broadcast against ``[X, Y, B]`` (``[B]`` for one value per member)."""
    edge = torch.zeros(n, dtype=like.dtype, device=like.device)
    first, last = edge.clone(), edge.clone()
    first[0], last[-1] = 2.0, 2.0
    first, last = (e.reshape((n, 1, 1) if axis == 0 else (1, n, 1)) for e in (first, last))
    low, high = (torch.as_tensor(w, dtype=like.dtype, device=like.device) for w in (low, high))
    return first * low + last * high


class Cavity:
    """The grid of one rectangular cavity: sizes, the pressure-increment solver
    (``poisson_bc`` on left, right, bottom, top), the ghost maps of the velocities and
    the scalar transport sweep. ``jacobi_tol`` None solves for the increment directly;
    a number runs the published Jacobi iterations to that tolerance instead."""

    def __init__(
        self,
        nx: int,
        ny: int,
        dx: float,
        dy: float,
        poisson_bc: Sequence[str] = (NEUMANN,) * 4,
        *,
        jacobi_tol: float | None = None,
        dtype,
        device,
    ) -> None:
        self.nx, self.ny, self.dx, self.dy = nx, ny, dx, dy
        if jacobi_tol is None:
            self.solver = PoissonSolver(nx, ny, dx, dy, poisson_bc, dtype=dtype, device=device)
        else:
            self.solver = JacobiSolver(nx, ny, dx, dy, poisson_bc, jacobi_tol, dtype=dtype, device=device)
        self.sweep = Sweep(nx, ny, device, dtype)
        self.u_ghosts = Ghosts.u_faces(nx, ny, dtype=dtype, device=device)
        self.v_ghosts = Ghosts.v_faces(nx, ny, dtype=dtype, device=device)

    def walls(
        self, u_bottom=0.0, u_top=0.0, v_left=0.0, v_right=0.0, *, like: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The ghost offsets of the tangential wall velocities (numbers or ``[B]``):
        ``(u offset [1, ny + 2, B'], v offset [nx + 2, 1, B'])``."""
        return (
            edge_offset(self.ny + 2, 1, u_bottom, u_top, like),
            edge_offset(self.nx + 2, 0, v_left, v_right, like),
        )

    def predict(
        self, fields: dict[str, torch.Tensor], walls, nu, dt: float, v_source: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """:func:`predict` on the solver's fields, with the wall ghost offsets ``walls``
        (:meth:`walls`; None for walls at rest)."""
        off_u, off_v = walls if walls is not None else (None, None)
        u, v = self.u_ghosts(fields["u"], off_u), self.v_ghosts(fields["v"], off_v)
        return predict(u, v, fields["p"], nu, dt, self.dx, self.dy, v_source)

    def fields(self, state: dict[str, torch.Tensor], scalars: dict[str, tuple]) -> dict[str, torch.Tensor]:
        """The solver's fields from a batch-first ghosted state (``u``, ``v`` and the
        scalars ``[B, nx + 2, ny + 2]``, ``p`` ``[B, nx, ny]``). ``scalars`` maps each
        scalar's name to its ``(ghosts, offset or None)``: scalars travel through the
        substeps with their ghost layer, refreshed from the interior."""
        last = lambda f: f.movedim(0, -1).contiguous()
        out = {"u": last(state["u"][:, 1:, 1:-1]), "v": last(state["v"][:, 1:-1, 1:]), "p": last(state["p"])}
        for name, (ghosts, offset) in scalars.items():
            out[name] = ghosts(last(state[name][:, 1:-1, 1:-1]), offset)
        return out

    def stored(self, fields: dict[str, torch.Tensor], walls) -> dict[str, torch.Tensor]:
        """Back to the batch-first ghosted state, with the velocities' wall ghosts of
        ``walls`` (:meth:`walls`)."""
        first = lambda f: f.movedim(-1, 0).contiguous()
        u, v = fields["u"], fields["v"]
        # the stored layout has one ghost position before the first face, none after
        u_full = F.pad(self.u_ghosts(u, walls[0]), (0, 0, 0, 0, 1, 0))
        v_full = F.pad(self.v_ghosts(v, walls[1]), (0, 0, 1, 0))
        # the ghost maps zero the wall faces for the predictor; keep what projection left
        u_full[1:, 1:-1] = u
        v_full[1:-1, 1:] = v
        out = {name: first(f) for name, f in fields.items()}
        out.update(u=first(u_full), v=first(v_full))
        return out


def tendency(u: torch.Tensor, v: torch.Tensor, nu, dx: float, dy: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The explicit terms -(u.grad)u + nu lap u on the interior faces, with centred
    fluxes of face-averaged velocities: ``[nx - 1, ny, B]`` on the x-faces 1..nx-1 and
    ``[nx, ny - 1, B]`` on the y-faces 1..ny-1. ``u`` (``[nx + 1, ny + 2, B]``) and
    ``v`` (``[nx + 2, ny + 1, B]``) carry their ghosts (:class:`Ghosts`)."""
    # u on the interior x-faces 1..nx-1, cells 0..ny-1 (ghost rows 0 and ny + 1 in y)
    uf = u[1:-1, 1:-1]
    ue = 0.5 * (uf + u[2:, 1:-1])  # the cell centre east of the face
    uw = 0.5 * (u[:-2, 1:-1] + uf)
    duu = (ue * ue - uw * uw) / dx
    un = 0.5 * (uf + u[1:-1, 2:])
    vn = 0.5 * (v[1:-2, 1:] + v[2:-1, 1:])
    us = 0.5 * (u[1:-1, :-2] + uf)
    vs = 0.5 * (v[1:-2, :-1] + v[2:-1, :-1])
    duv = (un * vn - us * vs) / dy
    lap_u = (u[2:, 1:-1] - 2.0 * uf + u[:-2, 1:-1]) / dx**2 + (u[1:-1, 2:] - 2.0 * uf + u[1:-1, :-2]) / dy**2
    hu = -duu - duv + nu * lap_u

    # v on the interior y-faces 1..ny-1, cells 0..nx-1 (ghost columns 0 and nx + 1 in x)
    vf = v[1:-1, 1:-1]
    vn_c = 0.5 * (vf + v[1:-1, 2:])
    vs_c = 0.5 * (v[1:-1, :-2] + vf)
    dvv = (vn_c * vn_c - vs_c * vs_c) / dy
    ve = 0.5 * (vf + v[2:, 1:-1])
    ue_c = 0.5 * (u[1:, 1:-2] + u[1:, 2:-1])
    vw = 0.5 * (v[:-2, 1:-1] + vf)
    uw_c = 0.5 * (u[:-1, 1:-2] + u[:-1, 2:-1])
    duv_x = (ue_c * ve - uw_c * vw) / dx
    lap_v = (v[2:, 1:-1] - 2.0 * vf + v[:-2, 1:-1]) / dx**2 + (v[1:-1, 2:] - 2.0 * vf + v[1:-1, :-2]) / dy**2
    return hu, -dvv - duv_x + nu * lap_v


def predict(
    u: torch.Tensor,
    v: torch.Tensor,
    p: torch.Tensor,
    nu,
    dt: float,
    dx: float,
    dy: float,
    v_source: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Explicit predictor u* = u + dt (:func:`tendency` - grad p [+ source]) on the
    interior faces of a closed cavity. ``u`` (``[nx + 1, ny + 2, B]``) and ``v``
    (``[nx + 2, ny + 1, B]``) carry their wall ghosts (:class:`Ghosts`); ``v_source``
    (``[nx, ny - 1, B]``) is added on the interior v faces (buoyancy). Returns u*
    ``[nx + 1, ny, B]`` and v* ``[nx, ny + 1, B]`` with zero normal velocity on the
    walls. (Computing every face and zeroing the walls instead, to save the padding
    pass, is slower compiled: the wider ghosted inputs cost more than the pad;
    docs/performance.md.)"""
    hu, hv = tendency(u, v, nu, dx, dy)
    gpx = (p[1:] - p[:-1]) / dx
    u_star = u[1:-1, 1:-1] + dt * (hu - gpx)
    gpy = (p[:, 1:] - p[:, :-1]) / dy
    dv = hv - gpy
    if v_source is not None:
        dv = dv + v_source
    v_star = v[1:-1, 1:-1] + dt * dv
    return F.pad(u_star, (0, 0, 0, 0, 1, 1)), F.pad(v_star, (0, 0, 1, 1))


def divergence(u: torch.Tensor, v: torch.Tensor, dx: float, dy: float) -> torch.Tensor:
    """Discrete divergence in the cells, ``[nx, ny, B]``, of face velocities
    ``[nx + 1, ny, B]`` and ``[nx, ny + 1, B]``."""
    return (u[1:] - u[:-1]) / dx + (v[:, 1:] - v[:, :-1]) / dy


def project(
    u: torch.Tensor, v: torch.Tensor, p: torch.Tensor, solver, dt: float, dx: float, dy: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Incremental projection: L phi = div(u*) / dt, u = u* - dt grad phi on the interior
    faces, p += phi (``solver``: :class:`PoissonSolver` or :class:`JacobiSolver`).

    The walls keep zero normal velocity, as in the published corrector. Where the
    increment has zero normal gradient that is also what the correction would give;
    on a zero-ghost wall (mixing's top) the cells next to it keep the divergence the
    increment's condition leaves there, as published."""
    phi = solver.solve(divergence(u, v, dx, dy) / dt)
    ext = solver.ghosts(phi)
    gx = F.pad((ext[2:-1, 1:-1] - ext[1:-2, 1:-1]) / dx, (0, 0, 0, 0, 1, 1))
    gy = F.pad((ext[1:-1, 2:-1] - ext[1:-1, 1:-2]) / dy, (0, 0, 1, 1))
    return u - dt * gx, v - dt * gy, p + phi


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

    On the CPU, where autograd has nothing to record, the loop itself runs in C
    (:mod:`beacon_torch.numerics.native`): the anti-diagonal steps cost a few
    microseconds each whatever their size, which at small batches is most of a cavity
    step. The tensor recurrence is the path everywhere else (GPU, gradients, no C
    compiler)."""

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
        sc, se, sn = s[1:-1, 1:-1], s[2:, 1:-1], s[1:-1, 2:]
        uw, ue, vs, vn = u[:-1], u[1:], v[:, :-1], v[:, 1:]
        kx, ky = kappa / dx**2, kappa / dy**2
        # everything but the new west and south values
        c = sc + dt * (
            kx * (se - 2.0 * sc)
            + ky * (sn - 2.0 * sc)
            - (ue * 0.5 * (se + sc) - uw * 0.5 * sc) / dx
            - (vn * 0.5 * (sn + sc) - vs * 0.5 * sc) / dy
        )
        a = dt * (kx + 0.5 * uw / dx)
        b = dt * (ky + 0.5 * vs / dy)
        pad = lambda f: F.pad(f, (0, 0, 1, 1, 1, 1))
        recording = native.recording(s, u, v, c)
        if self.native and native.takes(s, u, v, c):
            return native.sweep(s + pad(c - sc), a, b)[1:-1, 1:-1]
        # the ghosts keep their values (a = b = 0 there)
        c = self._skewed(s + pad(c - sc))
        a, b = self._skewed(pad(a)), self._skewed(pad(b))
        last = self.nx + self.ny  # the last anti-diagonal with interior cells
        if recording:
            rows = _graph_rows(c, a, b, last)
        else:
            rows = _rows(c, a, b, last)
        return rows[self.unskew_k, self.unskew_i]


# The two recurrences run eagerly even in a compiled substep: a chain of hundreds of
# dependent steps cannot be fused, and unrolling it into a graph takes minutes to compile.
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


@torch.compiler.disable
def _graph_rows(c: torch.Tensor, a: torch.Tensor, b: torch.Tensor, last: int) -> torch.Tensor:
    """The same recurrence out of place, so that autograd keeps every row."""
    rows = [c[0], c[1]]  # ghosts only
    for k in range(2, last + 1):
        # roll: position i reads the previous row's i - 1 (the west cell); position 0 is
        # a ghost, whose a is zero
        rows.append(c[k] + a[k] * rows[-1].roll(1, 0) + b[k] * rows[-1])
    return torch.stack(rows)


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
