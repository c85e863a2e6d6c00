"""Operators of the staggered grid, batch last: the explicit momentum terms, the
predictor, the divergence and the projection that removes it. Velocities come with
their ghosts (:class:`~beacon_torch.numerics.grid.Ghosts`); everything is out of place,
so the graph survives when gradients are wanted.

The spacing of each axis is a :class:`Uniform` one (the cavities) or a
:class:`Stretched` one (the cylinder's channel, whose cells grow away from the body):
the stencils are the same, and each difference is taken over its own distance."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from beacon_torch.numerics import native
from beacon_torch.numerics.grid import ZERO_FACE


class Uniform:
    """An axis of equal cells of width ``h``."""

    def __init__(self, h: float) -> None:
        self.h = h

    def difference(self, d: torch.Tensor, faces: bool) -> torch.Tensor:
        """A difference of fluxes across the control volumes of the interior faces of
        this axis (``faces``) or of its cells, over their widths."""
        return d / self.h

    def second(self, minus: torch.Tensor, mid: torch.Tensor, plus: torch.Tensor, faces: bool) -> torch.Tensor:
        """The second derivative along this axis at the interior faces (``faces``) or the
        cells, from the values ``minus``, ``mid``, ``plus`` one node apart."""
        # the published form, which the reference rollouts match to the last bit
        return (plus - 2.0 * mid + minus) / self.h**2

    def second_weights(self, g: torch.Tensor, faces: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """The gradients of :meth:`second`'s ``minus`` and ``plus`` from ``g``, the
        gradient of its result (``mid``'s is minus their sum)."""
        side = g / self.h**2
        return side, side


class Stretched:
    """An axis of unequal cells: their ``widths`` and the ``gaps`` between neighbouring
    centres, the two ends' ghost centres included (``widths.numel() + 1`` values), each
    shaped to broadcast against ``[X, Y, B]`` along dimension ``dim``."""

    def __init__(self, widths: torch.Tensor, gaps: torch.Tensor, dim: int) -> None:
        self.widths, self.gaps, self.dim = widths, gaps, dim

    def _part(self, t: torch.Tensor, start: int, stop: int) -> torch.Tensor:
        return t.narrow(self.dim, start, t.shape[self.dim] + stop - start)

    def difference(self, d: torch.Tensor, faces: bool) -> torch.Tensor:
        # an interior face's control volume spans the centres on each side of it
        return d / (self._part(self.gaps, 1, -1) if faces else self.widths)

    def second(self, minus: torch.Tensor, mid: torch.Tensor, plus: torch.Tensor, faces: bool) -> torch.Tensor:
        # between faces, the nodes are a cell apart; between cells, a gap apart
        inner, outer = (self.widths, self._part(self.gaps, 1, -1)) if faces else (self.gaps, self.widths)
        return ((plus - mid) / self._part(inner, 1, 0) - (mid - minus) / self._part(inner, 0, -1)) / outer

    def second_weights(self, g: torch.Tensor, faces: bool) -> tuple[torch.Tensor, torch.Tensor]:
        inner, outer = (self.widths, self._part(self.gaps, 1, -1)) if faces else (self.gaps, self.widths)
        g = g / outer
        return g / self._part(inner, 0, -1), g / self._part(inner, 1, 0)


class Axis:
    """One axis of the stretched grid (float64): the faces, the cells' centres and
    widths, and the distances between neighbouring centres, the mirrored ghost centres
    beyond the ends included (``gaps[0]`` and ``gaps[-1]``: a cell's width). Cells of
    size ``h`` fill ``[low, high]``; outside, they grow by ``growth`` a cell up to
    ``widest``, as few as fit the ends at 0 and ``length``."""

    def __init__(self, length: float, low: float, high: float, h: float, growth: float, widest: float) -> None:
        def outwards(extent: float) -> np.ndarray:
            # the ends of cells growing by a common ratio up to ``widest`` from the box
            # outwards, as few as ``growth`` allows, the ratio then lowered to end there
            def ends(ratio: float, n: int) -> np.ndarray:
                return np.concatenate(([0.0], np.cumsum(np.minimum(h * ratio ** np.arange(1, n + 1), widest))))

            n = 1
            while ends(growth, n)[-1] < extent:
                n += 1
            if n * h >= extent:  # too short to grow: equal cells
                return np.linspace(0.0, extent, round(extent / h) + 1)
            low_ratio, high_ratio = 1.0, growth
            for _ in range(80):
                mid = 0.5 * (low_ratio + high_ratio)
                low_ratio, high_ratio = (mid, high_ratio) if ends(mid, n)[-1] < extent else (low_ratio, mid)
            e = ends(high_ratio, n)
            return e * (extent / e[-1])

        left, right = np.diff(outwards(low))[::-1], np.diff(outwards(length - high))
        if math.isclose(low, length - high):
            right = left[::-1]  # exactly mirror-symmetric, so that the solve folds
        self._set(torch.from_numpy(np.concatenate((left, np.full(round((high - low) / h), h), right))))

    @classmethod
    def of_widths(cls, widths: torch.Tensor) -> Axis:
        """The axis of the cells ``widths`` (float64), from 0."""
        axis = cls.__new__(cls)
        axis._set(widths.double())
        return axis

    def _set(self, widths: torch.Tensor) -> None:
        self.widths = widths
        self.faces = torch.cat((widths.new_zeros(1), widths.cumsum(0)))
        self.centres = self.faces[:-1] + 0.5 * widths
        self.gaps = torch.cat((widths[:1], 0.5 * (widths[1:] + widths[:-1]), widths[-1:]))
        self.n = len(self.widths)

    def laplacian(self, low: str, high: str) -> torch.Tensor:
        """The cells' ``[n, n]`` divergence of the gradient with zero gradient
        (``NEUMANN``) or a zero value on the end face (``ZERO_FACE``) at each end."""
        n, g = self.n, self.gaps
        a = torch.zeros((n, n), dtype=torch.float64)
        i = torch.arange(n - 1)
        a[i, i + 1] = 1.0 / g[1:-1]
        a[i + 1, i] = 1.0 / g[1:-1]
        a[i, i] -= 1.0 / g[1:-1]
        a[i + 1, i + 1] -= 1.0 / g[1:-1]
        for end, kind in ((0, low), (n - 1, high)):
            if kind == ZERO_FACE:
                a[end, end] -= 2.0 / self.widths[end]
        return a / self.widths[:, None]


def spacing(h) -> Uniform | Stretched:
    """An axis's spacing: a number is the width of equal cells."""
    return h if isinstance(h, Uniform | Stretched) else Uniform(h)


def tendency(u: torch.Tensor, v: torch.Tensor, nu, dx, dy) -> tuple[torch.Tensor, torch.Tensor]:
    """The explicit terms -(u.grad)u + nu lap u on the interior faces, with centred
    fluxes of face-averaged velocities: ``[nx - 1, ny, B]`` on the x-faces 1..nx-1 and
    ``[nx, ny - 1, B]`` on the y-faces 1..ny-1. ``u`` (``[nx + 1, ny + 2, B]``) and
    ``v`` (``[nx + 2, ny + 1, B]``) carry their ghosts (:class:`Ghosts`). ``dx`` and
    ``dy`` are the axes' spacings (:class:`Uniform`, :class:`Stretched`, or a number:
    equal cells). On a stretched axis the velocities are carried to a control volume's
    faces by plain averages: exact where the cells are equal, first order where they
    grow."""
    x, y = spacing(dx), spacing(dy)
    one_per_member = not isinstance(nu, torch.Tensor) or nu.numel() in (1, u.shape[-1])
    tensors = [t for t in (u, v, nu) if isinstance(t, torch.Tensor)]
    if native.recording(*tensors) and one_per_member and native.applies(u.device, u.dtype) and native.takes(*tensors):
        return _Tendency.apply(u, v, nu, x, y)
    return _terms(u, v, nu, x, y)


def _terms(u, v, nu, x, y) -> tuple[torch.Tensor, torch.Tensor]:
    # one function per component, so that the first one's temporaries are freed before
    # the second allocates its own (a lower peak: fewer fresh pages at large batches)
    return _x_momentum(u, v, nu, x, y), _y_momentum(u, v, nu, x, y)


class _Tendency(torch.autograd.Function):
    """:func:`tendency` with the C kernel :func:`~beacon_torch.numerics.native.momentum_adjoint`
    as its backward pass: each velocity gathers in one loop what the terms that read it
    send back, where autograd's backward of the dozen slices a component reads is a
    zero padding apiece, which the compiled backward reads under masks (about three
    times the forward's work on the cavities)."""

    generate_vmap_rule = True

    @staticmethod
    def forward(u, v, nu, x, y):
        return _terms(u, v, nu, x, y)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        u, v, nu, ctx.x, ctx.y = inputs
        if isinstance(nu, torch.Tensor):
            ctx.save_for_backward(u, v, nu)
        else:
            ctx.save_for_backward(u, v)
            ctx.nu = nu

    @staticmethod
    def backward(ctx, gu, gv):
        u, v, *nu = ctx.saved_tensors
        nu = nu[0] if nu else ctx.nu
        with torch.no_grad():  # differentiable once: the adjoint keeps no graph
            du, dv = _momentum_adjoint(u, v, gu, gv, nu, ctx.x, ctx.y)
            dnu = _nu_gradient(u, v, nu, ctx.x, ctx.y, gu, gv) if ctx.needs_input_grad[2] else None
        return du, dv, dnu, None, None


def _momentum_adjoint(u, v, gu, gv, nu, x, y) -> tuple[torch.Tensor, torch.Tensor]:
    """The C adjoint of :func:`tendency` (the gradients of the ghosted ``u``, ``v`` from
    ``gu``, ``gv``, those of its results), a viscosity per member or one for all."""
    nx, ny, members = u.shape[0] - 1, u.shape[1] - 2, u.shape[2]
    per_member = torch.as_tensor(nu, dtype=u.dtype, device=u.device).reshape(-1).expand(members).contiguous()
    return native.momentum_adjoint(u, v, gu, gv, per_member, multipliers(x, nx, u), multipliers(y, ny, u))


def _x_momentum(u: torch.Tensor, v: torch.Tensor, nu, x, y) -> torch.Tensor:
    """:func:`tendency`'s x-component: u on the interior x-faces 1..nx-1, cells
    0..ny-1 (ghost rows 0 and ny + 1 in y)."""
    uf = u[1:-1, 1:-1]
    ue = 0.5 * (uf + u[2:, 1:-1])  # the cell centre east of the face
    uw = 0.5 * (u[:-2, 1:-1] + uf)
    duu = x.difference(ue * ue - uw * uw, faces=True)
    un = 0.5 * (uf + u[1:-1, 2:])
    vn = 0.5 * (v[1:-2, 1:] + v[2:-1, 1:])
    us = 0.5 * (u[1:-1, :-2] + uf)
    vs = 0.5 * (v[1:-2, :-1] + v[2:-1, :-1])
    duv = y.difference(un * vn - us * vs, faces=False)
    return -duu - duv + nu * _laplacian_u(u, x, y)


def _y_momentum(u: torch.Tensor, v: torch.Tensor, nu, x, y) -> torch.Tensor:
    """:func:`tendency`'s y-component: v on the interior y-faces 1..ny-1, cells
    0..nx-1 (ghost columns 0 and nx + 1 in x)."""
    vf = v[1:-1, 1:-1]
    vn = 0.5 * (vf + v[1:-1, 2:])
    vs = 0.5 * (v[1:-1, :-2] + vf)
    dvv = y.difference(vn * vn - vs * vs, faces=True)
    ve = 0.5 * (vf + v[2:, 1:-1])
    ue = 0.5 * (u[1:, 1:-2] + u[1:, 2:-1])
    vw = 0.5 * (v[:-2, 1:-1] + vf)
    uw = 0.5 * (u[:-1, 1:-2] + u[:-1, 2:-1])
    duv = x.difference(ue * ve - uw * vw, faces=False)
    return -dvv - duv + nu * _laplacian_v(v, x, y)


def _laplacian_u(u: torch.Tensor, x, y) -> torch.Tensor:
    uf = u[1:-1, 1:-1]
    return x.second(u[:-2, 1:-1], uf, u[2:, 1:-1], faces=True) + y.second(u[1:-1, :-2], uf, u[1:-1, 2:], faces=False)


def _laplacian_v(v: torch.Tensor, x, y) -> torch.Tensor:
    vf = v[1:-1, 1:-1]
    return x.second(v[:-2, 1:-1], vf, v[2:, 1:-1], faces=False) + y.second(v[1:-1, :-2], vf, v[1:-1, 2:], faces=True)


def _nu_gradient(u, v, nu, x, y, gu, gv) -> torch.Tensor:
    """The gradient of :func:`tendency`'s ``nu`` from those of its results: its
    second differences, read against them."""
    lap_u, lap_v = _laplacian_u(u, x, y), _laplacian_v(v, x, y)
    return ((gu * lap_u).sum((0, 1)) + (gv * lap_v).sum((0, 1))).sum_to_size(nu.shape)


def multipliers(axis, n: int, like: torch.Tensor) -> torch.Tensor:
    """An axis's multipliers as the C adjoint of the momentum terms reads them
    (``[6 n - 3]``, ``n`` cells; see :func:`beacon_torch.numerics.native.momentum_adjoint`),
    from its own :meth:`difference` and :meth:`second_weights` of ones."""
    dim = axis.dim if isinstance(axis, Stretched) else 0

    def ones(k):
        shape = [1, 1, 1]
        shape[dim] = k
        return torch.ones(shape, dtype=like.dtype, device=like.device)

    face_minus, face_plus = axis.second_weights(ones(n - 1), faces=True)
    cell_minus, cell_plus = axis.second_weights(ones(n), faces=False)
    parts = (
        axis.difference(ones(n - 1), faces=True),
        axis.difference(ones(n), faces=False),
        face_minus,
        face_plus,
        cell_minus,
        cell_plus,
    )
    return torch.cat([t.reshape(-1) for t in parts])


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
    x, y = spacing(dx), spacing(dy)
    gpx = x.difference(p[1:] - p[:-1], faces=True)
    u_star = u[1:-1, 1:-1] + dt * (hu - gpx)
    gpy = y.difference(p[:, 1:] - p[:, :-1], faces=True)
    dv = hv - gpy
    if v_source is not None:
        dv = dv + v_source
    v_star = v[1:-1, 1:-1] + dt * dv
    return F.pad(u_star, (0, 0, 0, 0, 1, 1)), F.pad(v_star, (0, 0, 1, 1))


def predict_adjoint(
    u: torch.Tensor, v: torch.Tensor, gu: torch.Tensor, gv: torch.Tensor, nu, dt: float, dx: float, dy: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The gradients of :func:`predict`'s ghosted ``u`` and ``v``, its ``p`` and its
    ``v_source`` from ``gu`` and ``gv``, those of its results, on equal cells and where
    the C kernels apply (the caller has asked): the momentum terms' C adjoint, and the
    pressure gradient's adjoint, minus the divergence of the faces' gradients."""
    gui, gvi = gu[1:-1], gv[:, 1:-1]
    du, dv = _momentum_adjoint(u, v, dt * gui, dt * gvi, nu, Uniform(dx), Uniform(dy))
    # u* reads the interior faces themselves
    du = du + F.pad(gui, (0, 0, 1, 1, 1, 1))
    dv = dv + F.pad(gvi, (0, 0, 1, 1, 1, 1))
    # -dt (p[k] - p[k - 1]) / h on each interior face: p[k] gets -dt (g[k - 1] - g[k]) / h
    gp = (dt / dx) * (F.pad(gui, (0, 0, 0, 0, 0, 1)) - F.pad(gui, (0, 0, 0, 0, 1, 0))) + (dt / dy) * (
        F.pad(gvi, (0, 0, 0, 1)) - F.pad(gvi, (0, 0, 1, 0))
    )
    return du, dv, gp, dt * gvi


def project_adjoint(
    gu: torch.Tensor, gv: torch.Tensor, gp: torch.Tensor, solver, dt: float, dx: float, dy: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The gradients of :func:`project`'s ``u``, ``v`` and ``p`` from ``gu``, ``gv``
    and ``gp``, those of its results, between walls on equal cells: the projection is
    its own adjoint (the divergence and the gradient are each other's adjoints, up to
    sign, and the solve is symmetric), so it is the same projection of the faces'
    gradients, with the pressure's gradient joining the increment's source. ``solver``
    is a :class:`~beacon_torch.numerics.poisson.PoissonSolver` with its C line solves."""
    inner = lambda g, dim: g.narrow(dim, 1, g.shape[dim] - 2)
    walls_u = F.pad(inner(gu, 0), (0, 0, 0, 0, 1, 1))
    walls_v = F.pad(inner(gv, 1), (0, 0, 1, 1))
    source = gp + dt * divergence(walls_u, walls_v, dx, dy)
    if any(mode is not None for mode in solver.singular):
        # the solve takes the constant off its solution, so its transpose takes it off
        # the source first (between walls on equal cells the constant is the mean); what
        # it leaves in the solution is a constant, which the gradient below does not see
        source = source - source.mean((0, 1))
    gx, gy = _wall_gradient(solver.solve(source), dx, dy)
    return gu - gx / dt, gv - gy / dt, gp


def divergence(u: torch.Tensor, v: torch.Tensor, dx, dy) -> torch.Tensor:
    """Discrete divergence in the cells, ``[nx, ny, B]``, of face velocities
    ``[nx + 1, ny, B]`` and ``[nx, ny + 1, B]`` (spacings as :func:`tendency`'s)."""
    x, y = spacing(dx), spacing(dy)
    return x.difference(u[1:] - u[:-1], faces=False) + y.difference(v[:, 1:] - v[:, :-1], faces=False)


def project(
    u: torch.Tensor, v: torch.Tensor, p: torch.Tensor, solver, dt: float, dx, dy
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Incremental projection: L phi = div(u*) / dt, u = u* - dt grad phi on the interior
    faces, p += phi (``solver``: :class:`PoissonSolver` or :class:`JacobiSolver`).

    The walls keep zero normal velocity, as in the published corrector (a periodic x
    axis has none: its first and last faces, one face, are corrected alike). Where the
    increment has zero normal gradient that is also what the correction would give;
    on a zero-ghost wall (mixing's top) the cells next to it keep the divergence the
    increment's condition leaves there, as published. A periodic x axis has equal
    cells (``dx`` a number); ``dy`` may be :class:`Stretched`."""
    phi = solver.solve(divergence(u, v, dx, dy) / dt)
    gx, gy = _wall_gradient(phi, dx, dy, x_walls=not solver.periodic)
    if solver.periodic:
        # no side walls: every x-face is corrected, the first and the last alike, the
        # two reading the increment across the wrap
        ext = solver.ghosts(phi)
        gx = (ext[1:, 1:-1] - ext[:-1, 1:-1]) / dx
    return u - dt * gx, v - dt * gy, p + phi


def _wall_gradient(phi: torch.Tensor, dx, dy, x_walls: bool = True) -> tuple[torch.Tensor | None, torch.Tensor]:
    """The gradient of a cell field on the faces between walls (x too where
    ``x_walls``; else None for x): zero on the wall faces, the interior faces reading
    interior cells only (no ghost values, whose gathers' backward is a scatter over the
    ghosted field)."""
    gx = F.pad(spacing(dx).difference(phi[1:] - phi[:-1], faces=True), (0, 0, 0, 0, 1, 1)) if x_walls else None
    gy = F.pad(spacing(dy).difference(phi[:, 1:] - phi[:, :-1], faces=True), (0, 0, 1, 1))
    return gx, gy
