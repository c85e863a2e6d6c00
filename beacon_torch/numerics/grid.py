"""The staggered grid's boundaries for the 2-D flows: how a stencil reads past the
walls.

Layout: every field is ``[X, Y, B]``, x first, **batch last**. The members are the
contiguous dimension, so a stencil shift moves whole rows of members: the fused kernels
of the compiled path then vectorise across the batch with no tails and no masks (the
comparison with batch first: docs/performance.md), with vectors as wide as a row of
members fills (:func:`beacon_torch.compiled.member_vectors`).

Ghost values are gathered from the stored values when a stencil needs them
(:class:`Ghosts`: an index map and a factor per position, plus an offset for
prescribed wall values), which the compiler fuses into the stencil's kernel instead of
writing ghost layers.
"""

from __future__ import annotations

import torch

NEUMANN = "neumann"
ZERO_GHOST = "zero_ghost"
ZERO_FACE = "zero_face"  # zero value on the wall face itself (an open boundary's pressure)
PERIODIC = "periodic"  # an axis that wraps around (a pair of sides, not one wall)
# ghost factors: zero normal gradient (ghost = neighbour), a value imposed through the
# ghost (ghost = 2 value - neighbour, the value comes as an offset), a zero ghost
GRADIENT, VALUE, ZERO = 1.0, -1.0, 0.0


class Ghosts:
    """A field with ghost values, gathered from its stored values: along each axis an
    index map into the stored positions and a factor per extended position (the
    product of the two axes' factors multiplies the gathered value), plus an optional
    offset that carries prescribed wall values (``ghost = 2 value - neighbour``)."""

    def __init__(self, index_x, factor_x, index_y, factor_y, *, dtype, device) -> None:
        as_index = lambda i: None if i is None else torch.tensor(i, dtype=torch.int64, device=device)
        self.ix, self.iy = as_index(index_x), as_index(index_y)
        # where the two ghosts of an axis read, for :meth:`fold`: a map that is the stored
        # positions in order with one ghost on each side (None: another map)
        ends = lambda i: (i[0], i[-1]) if i is not None and list(i[1:-1]) == list(range(len(i) - 2)) else None
        self.ends_x, self.ends_y = ends(index_x), ends(index_y)
        fx = torch.tensor(factor_x, dtype=torch.float64)
        fy = torch.tensor(factor_y, dtype=torch.float64)
        self.factor = (fx[:, None, None] * fy[None, :, None]).to(dtype=dtype, device=device)

    @staticmethod
    def _cell_axis(n: int, low, high):
        if PERIODIC in (low, high):
            if low != high:
                raise ValueError("a periodic axis wraps around: both its sides must be PERIODIC")
            return [n - 1, *range(n), 0], [1.0] * (n + 2)
        return [0, *range(n), n - 1], [low, *[1.0] * n, high]

    @classmethod
    def cells(
        cls, nx: int, ny: int, left: float, right: float, bottom: float, top: float, *, corners: bool = True, **kw
    ) -> Ghosts:
        """Cell-centred ``[nx, ny, B]`` to ``[nx + 2, ny + 2, B]``; each wall's factor is
        GRADIENT, VALUE or ZERO (PERIODIC on both sides of an axis that wraps). No
        stencil reads the four corner ghosts; ``corners`` False leaves them at zero (where
        a reward averages over the ghosted array, as the published mixing reward does)."""
        ghosts = cls(*cls._cell_axis(nx, left, right), *cls._cell_axis(ny, bottom, top), **kw)
        if not corners:
            ghosts.factor[[0, 0, -1, -1], [0, -1, 0, -1]] = 0.0
        return ghosts

    @classmethod
    def u_faces(cls, nx: int, ny: int, *, periodic: bool = False, **kw) -> Ghosts:
        """x-face velocity ``[nx + 1, ny, B]`` to ``[nx + 1, ny + 2, B]``: impermeable
        side walls (zeroed; ``periodic``: faces 0 and nx are one face, kept), tangential
        velocity on the bottom and top through the ghosts."""
        side = 1.0 if periodic else 0.0
        return cls(None, [side, *[1.0] * (nx - 1), side], *cls._cell_axis(ny, VALUE, VALUE), **kw)

    @classmethod
    def v_faces(cls, nx: int, ny: int, *, periodic: bool = False, **kw) -> Ghosts:
        """y-face velocity ``[nx, ny + 1, B]`` to ``[nx + 2, ny + 1, B]``."""
        side = PERIODIC if periodic else VALUE
        return cls(*cls._cell_axis(nx, side, side), None, [0.0, *[1.0] * (ny - 1), 0.0], **kw)

    @classmethod
    def periodic_wide(cls, nx: int, before: int, after: int, y_index, y_factor, **kw) -> Ghosts:
        """A field of ``nx`` stored positions along a periodic x, widened by ``before``
        wrapped positions in front and ``after`` behind (a stored ``nx + 1``-th position,
        the faces' duplicate of the first, counts as one of them); y as given."""
        index = [i % nx for i in range(-before, nx + after)]
        return cls(index, [1.0] * len(index), y_index, y_factor, **kw)

    def __call__(self, f: torch.Tensor, offset: torch.Tensor | None = None) -> torch.Tensor:
        if self.ix is not None:
            f = f[self.ix]
        if self.iy is not None:
            f = f[:, self.iy]
        f = f * self.factor
        return f if offset is None else f + offset

    def fold(self, g: torch.Tensor) -> torch.Tensor:
        """The adjoint of the map in its field: the gradient of the stored values from
        ``g``, that of the extended field (each ghost's share added to the position it
        reads). The offset's gradient is ``g`` itself, summed to the offset's shape."""
        g = g * self.factor
        for dim, index, ends in ((1, self.iy, self.ends_y), (0, self.ix, self.ends_x)):
            if index is None:
                continue
            if ends is None:
                raise NotImplementedError("fold: an index map with more than one ghost on a side")
            n = g.shape[dim] - 2
            low, mid, high = g.narrow(dim, 0, 1), g.narrow(dim, 1, n), g.narrow(dim, n + 1, 1)
            first = (low if ends[0] == 0 else 0) + (high if ends[1] == 0 else 0)
            last = (low if ends[0] == n - 1 else 0) + (high if ends[1] == n - 1 else 0)
            g = torch.cat(
                (mid.narrow(dim, 0, 1) + first, mid.narrow(dim, 1, n - 2), mid.narrow(dim, n - 1, 1) + last), dim
            )
        return g


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
