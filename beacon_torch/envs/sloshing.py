"""sloshing-v0: calm the free surface of a shaken tank (BEACON paper, "Sloshing").

Shallow-water (Saint-Venant) equations in the tank frame, driven by the tank's
acceleration amp * u(t):

    h_t + q_x = 0
    q_t + (q^2 / h + g h^2 / 2)_x = -amp u

Finite volumes with Rusanov fluxes and wall ghost cells, Adams-Bashforth 2 in time,
50 substeps of dt = 0.001 per action with the action interpolated over the first 10,
200 actions. Every episode starts from the state stored with the published code
(``start="published"``, the default), or from the state left by a fixed 2-time-unit
excitation of the tank at rest (``start="generated"``, :func:`excited_state`; another
excitation phase than the stored state's).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from beacon_torch.cache import cached, memo
from beacon_torch.compiled import Kernels, at
from beacon_torch.core.card import Card, FrameInputs, GradCheck
from beacon_torch.core.physics import Physics
from beacon_torch.core.state import Noise, map_state, where_members
from beacon_torch.numerics import ab2_step, interpolated_action, interpolation_weights, native, rusanov
from beacon_torch.params import param
from beacon_torch.starts import PUBLISHED, choose_start, published_members, published_table, start_param

CELLS_PER_UNIT = 80
DT = 1e-3
SUBSTEPS = 50
N_INTERP = 10
DT_ACT = DT * SUBSTEPS
EPISODE_LENGTH = 200
EXCITATION_ACTIONS = 40  # 2 time units
# the excited starts' generation: a new one whenever the scheme changes the tank
START_VERSION = 2
EXCITATION_AMP = 5.0  # the published amp: the excitation does not follow the amp parameter
H_MIN, H_MAX = -5.0, 2.0  # the published code's blow-up bounds


class SloshingState(NamedTuple):
    """One member per row; the cells span the tank."""

    h: torch.Tensor  # [batch, n_cells] the depth
    q: torch.Tensor  # [batch, n_cells] the discharge
    fh_prev: torch.Tensor  # [batch, n_cells] the depth's right-hand side one substep before (AB2)
    fq_prev: torch.Tensor  # [batch, n_cells] the discharge's right-hand side one substep before
    u_prev: torch.Tensor  # [batch] the last action (its substeps interpolate from it)


def at_rest(num_envs: int, n_cells: int, dtype: torch.dtype, device) -> SloshingState:
    """A level tank at rest (h = 1, q = 0) with no AB2 history and no action before."""
    h = torch.ones((num_envs, n_cells), dtype=dtype, device=device)
    zero = torch.zeros_like(h)
    return SloshingState(h=h, q=zero, fh_prev=zero, fq_prev=zero, u_prev=zero[:, 0])


@dataclass(frozen=True)
class SloshingParams:
    L: float = param(2.5, low=0.1, high=50.0, per_member=False, doc="tank length (80 cells per unit)")
    amp: float = param(5.0, low=0.0, high=1e6, doc="acceleration amplitude (action scaling)")
    alpha: float = param(5e-4, low=0.0, high=1e3, doc="weight of the actuation in the reward")
    # a g other than the default starts from the published excitation, which leaves the
    # tank wet and finite at every length only in this band (docs/envs/sloshing.md)
    g: float = param(9.81, low=5.0, high=12.0, doc="gravity (the band where the published start stays wet and finite)")
    start: str = start_param("the published stored state, or the one of excited_state()")

    def __post_init__(self):
        choose_start(self, ("L", "g"))


def excitation(t: float) -> float:
    """The published generator's excitation signal, 0.5 (cos(pi t) + 3 cos(4 pi t)),
    applied as an action but not clipped to the action box (it peaks at 2), as the
    published generator script does."""
    return 0.5 * (math.cos(math.pi * t) + 3.0 * math.cos(4.0 * math.pi * t))


def shallow_water_rhs(h: torch.Tensor, q: torch.Tensor, accel: torch.Tensor, g, dx: float):
    """(dh/dt, dq/dt) at the interior cells of ghosted fields ``[B, n+2]``."""
    flux_q = q * q / h + 0.5 * g * h * h
    speed = (q / h).abs() + torch.sqrt(g * h)
    c = torch.maximum(speed[:, :-1], speed[:, 1:])
    face_h = rusanov(h[:, :-1], h[:, 1:], q[:, :-1], q[:, 1:], c)
    face_q = rusanov(q[:, :-1], q[:, 1:], flux_q[:, :-1], flux_q[:, 1:], c)
    fh = -(face_h[:, 1:] - face_h[:, :-1]) / dx
    fq = -(face_q[:, 1:] - face_q[:, :-1]) / dx - accel[:, None]
    return fh, fq


def with_walls(h_in: torch.Tensor, q_in: torch.Tensor):
    """Ghosted fields from interior ones: h mirrored, q = 0 in the ghost cells."""
    zero = torch.zeros_like(q_in[:, :1])
    h = torch.cat((h_in[:, :1], h_in, h_in[:, -1:]), -1)
    q = torch.cat((zero, q_in, zero), -1)
    return h, q


def sloshing_substep(
    i, fields: tuple[torch.Tensor, ...], accel: torch.Tensor, g, dx: float
) -> tuple[torch.Tensor, ...]:
    """Substep ``i`` of an action: one AB2 step of ``(h, q, fh_prev, fq_prev)`` with
    the tank acceleration ``accel[i]`` (``accel``: ``[SUBSTEPS, B]``)."""
    h, q, fh_prev, fq_prev = fields
    gh, gq = with_walls(h, q)
    fh, fq = shallow_water_rhs(gh, gq, at(accel, i), g, dx)
    return ab2_step(h, fh, fh_prev, DT), ab2_step(q, fq, fq_prev, DT), fh, fq


_action = native.operator(
    "sloshing_action(Tensor h, Tensor q, Tensor fh_prev, Tensor fq_prev, Tensor accel, Tensor g, float dx, float c)"
    " -> (Tensor, Tensor, Tensor, Tensor, Tensor)",
    native.sloshing_action,
    lambda h, q, fh, fq, accel, g, dx, c: (
        *(torch.empty_like(t) for t in (h, q, fh, fq)),
        h.new_empty((h.shape[0], accel.shape[0], 2, h.shape[1])),
    ),
    native.rows_vmap("sloshing_action", (0, 0, 0, 0, 1, 0), (0, 0, 0, 0, 0)),
)


def _adjoint_kernel(states, g, gh, gq, gfh, gfq, dx, c):
    return native.sloshing_adjoint(states, g, (gh, gq, gfh, gfq), dx, c)


_adjoint = native.operator(
    "sloshing_adjoint(Tensor states, Tensor g, Tensor gh, Tensor gq, Tensor gfh, Tensor gfq, float dx, float c)"
    " -> (Tensor, Tensor, Tensor, Tensor, Tensor, Tensor)",
    _adjoint_kernel,
    lambda states, g, gh, gq, gfh, gfq, dx, c: (
        *(torch.empty_like(t) for t in (gh, gq, gfh, gfq)),
        gh.new_empty((states.shape[1], gh.shape[0])),
        gh.new_empty(gh.shape[0]),
    ),
    native.rows_vmap("sloshing_adjoint", (0, 0, 0, 0, 0, 0), (0, 0, 0, 0, 1, 0)),
)


class _Action(torch.autograd.Function):
    """An action of :func:`sloshing_substep` as one C loop a member, its backward pass the
    same loop's adjoint run through the substeps in reverse."""

    generate_vmap_rule = True

    @staticmethod
    def forward(h, q, fh_prev, fq_prev, accel, g, dx: float):
        return _action(h, q, fh_prev, fq_prev, accel, g, dx, 0.5 * DT)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        ctx.mark_non_differentiable(output[4])
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(output[4], inputs[5])
        ctx.dx = inputs[6]

    @staticmethod
    def backward(ctx, gh, gq, gfh, gfq, _):
        states, g = ctx.saved_tensors
        gh, gq, gfh, gfq = native.output_grads((gh, gq, gfh, gfq), (states[:, 0, 0],) * 4)
        with torch.no_grad():  # differentiable once: the adjoint keeps no graph
            return (*_adjoint(states, g, gh, gq, gfh, gfq, ctx.dx, 0.5 * DT), None)


def sloshing_action(fields: tuple[torch.Tensor, ...], accel: torch.Tensor, g, dx: float) -> tuple[torch.Tensor, ...]:
    """The substeps of :func:`sloshing_substep` over an action (``accel``'s rows) where
    autograd records, on the CPU: the tensor loop's values to round-off (torch's square
    root on the CPU is not always the correctly rounded one that C's is), and its
    gradient to round-off from a reverse loop in C over the stored substeps, instead of
    a graph of some forty operations a substep, whose calls cost more than their
    arithmetic at sloshing's small rows."""
    h = fields[0]
    rows = h.shape[0]
    g = (g if isinstance(g, torch.Tensor) else torch.tensor(g)).to(h.dtype).reshape(-1).expand(rows)
    return _Action.apply(*fields, accel.expand(-1, rows), g, dx)[:4]


def run_actions(state: SloshingState, actions: list[torch.Tensor], amp, g, dx: float, substeps=None) -> SloshingState:
    """Advance ``state`` through a sequence of action batches (each ``[B]``) scaled by
    ``amp`` (a number or ``[B]``), each interpolated from the one before; ``substeps``
    is the loop of :func:`sloshing_substep` (an env's ``kernels.loop``; None: eager)."""
    substeps = Kernels().loop(sloshing_substep) if substeps is None else substeps
    fields = state.h, state.q, state.fh_prev, state.fq_prev
    u_prev = state.u_prev
    alpha = interpolation_weights(SUBSTEPS, N_INTERP, u_prev.dtype, u_prev.device)[:, None]
    for u in actions:
        accel = amp * interpolated_action(u_prev, u, alpha)
        given = (*fields, accel, *([g] if isinstance(g, torch.Tensor) else []))
        if native.applies(u.device, u.dtype) and native.recording(*given):
            fields = sloshing_action(fields, accel, g, dx)
        else:
            fields = substeps(SUBSTEPS, fields, accel, g, dx)
        u_prev = u
    h, q, fh_prev, fq_prev = fields
    return SloshingState(h=h, q=q, fh_prev=fh_prev, fq_prev=fq_prev, u_prev=u_prev)


def excited_state(L: float, g, num_envs: int, dtype: torch.dtype, device) -> SloshingState:
    """The tank after the published excitation: from rest (h = 1, q = 0) 40 actions
    :func:`excitation` (t = 0, 0.05, ...) scaled by the published amplitude 5 and
    interpolated like any action; the published code stores this state and starts every
    episode from it. ``g`` is a number or one value per member ``[num_envs, 1]``."""
    n = int(round(L * CELLS_PER_UNIT))
    dx = L / n
    state = at_rest(num_envs, n, dtype, device)
    actions = [
        torch.full((num_envs,), excitation(k * DT_ACT), dtype=dtype, device=device) for k in range(EXCITATION_ACTIONS)
    ]
    return run_actions(state, actions, EXCITATION_AMP, g, dx)


class SloshingPhysics(Physics):
    """The shallow water in a tank driven by its acceleration."""

    Params = SloshingParams
    state_type = SloshingState
    episode_length = EPISODE_LENGTH
    grad_action_in_c = True
    diagnostics = {
        "surface_deviation": "dx ||h - 1||, the free surface's distance from rest (the reward without actuation)",
        "max_depth": "the largest depth h in the tank",
    }
    # Below every episode that completes: it keeps 0 <= h <= 2 (a negative depth makes
    # the wave speed non-finite, which ends the episode too), so each step earns at least
    # -(dx sqrt(n_cells) + alpha amp) = -0.179 and 200 steps at least -35.9 at the
    # defaults (the measured episodes: docs/envs/sloshing.md). The published code meant
    # -10, which its own step then overwrites with the step's reward.
    blowup_reward = -40.0

    @classmethod
    def sizes(cls, p) -> tuple[int, int]:
        return (int(round(p.L * CELLS_PER_UNIT)) + 1) // 2, 1  # q in every second cell

    def member_floats(self) -> int:
        return 5 * self.n_cells  # h, q and their previous slopes

    def setup(self, p) -> None:
        self.n_cells = int(round(p.L * CELLS_PER_UNIT))
        self.dx = p.L / self.n_cells
        self._substeps = self.kernels.loop(sloshing_substep)

    def _start_state(self, p) -> SloshingState:

        def published() -> SloshingState:
            table = published_table("sloshing", self.n_cells, 3)  # rows: x, h, q of the interior cells
            h, q = table[:, 1].expand(self.num_envs, -1), table[:, 2].expand(self.num_envs, -1)
            zero = torch.zeros_like(h)
            return SloshingState(h=h, q=q, fh_prev=zero, fq_prev=zero, u_prev=zero[:, 0])

        if p.start == PUBLISHED:
            start = published()
        elif bool((p.g != p.g[0]).any()):  # one start per member
            g = p.g.detach().to(torch.float64)[:, None]
            # excited once per process for these members' g, in the one memo of starts
            key = ("sloshing-excited members", START_VERSION, p.L, tuple(g[:, 0].tolist()), str(self.device))
            start = memo(key, lambda: excited_state(p.L, g, self.num_envs, torch.float64, self.device))
            # a member at the published g (and length) starts as it would alone
            chosen = published_members(p, ("L", "g"))
            if chosen is not None:
                stored = map_state(lambda v: v.to(self.device), published())
                start = where_members(chosen.to(self.device), stored, start)
        else:  # one start for all, cached
            g = float(p.g[0])
            key = dict(L=p.L, g=g)
            like = at_rest(1, self.n_cells, torch.float64, "cpu")
            excite = lambda: excited_state(p.L, g, 1, torch.float64, "cpu")
            bounds = {"h": (H_MIN, H_MAX)}  # out_of_bounds's
            start = cached("sloshing-excited", START_VERSION, key, excite, like, bounds)
            start = map_state(lambda v: v.expand(self.num_envs, *v.shape[1:]), start)
        # generated in float64 like the published code, then cast
        return map_state(lambda v: v.to(device=self.device, dtype=self.dtype).clone(), start)

    def initial_state(self, p, generator, mask=None) -> SloshingState:
        start = self._start_state(p)
        zero = torch.zeros_like(start.h)
        # the published reset reloads h and q only: the AB2 history and the previous
        # action start from zero
        return SloshingState(h=start.h, q=start.q, fh_prev=zero, fq_prev=zero, u_prev=zero[:, 0])

    def advance(self, p, state: SloshingState, action: torch.Tensor, count: torch.Tensor, noise: Noise):
        u = action[:, 0]
        new = run_actions(state, [u], p.amp, self.member(p.g), self.dx, self._substeps)
        h = new.h
        reward = -self.dx * torch.linalg.vector_norm(h - 1.0, dim=-1) - p.alpha * (p.amp * u).abs()
        return new, reward

    def diagnose(self, p, state: SloshingState) -> dict[str, torch.Tensor]:
        return {
            "surface_deviation": self.dx * torch.linalg.vector_norm(state.h - 1.0, dim=-1),
            "max_depth": state.h.amax(-1),
        }

    def observe(self, p, state: SloshingState) -> torch.Tensor:
        return state.q[:, ::2]

    def out_of_bounds(self, p, state: SloshingState) -> torch.Tensor:
        h = state.h
        return ((h < H_MIN) | (h > H_MAX)).any(-1)


def frame(f: FrameInputs) -> np.ndarray:
    """The free surface in the tank and its acceleration."""
    from beacon_torch.render import sloshing_frame

    last = f.states[-1]
    x = f.physics.dx * (np.arange(f.physics.n_cells) + 0.5)
    return sloshing_frame(x, last.h.double().numpy(), float(last.u_prev), DT_ACT * f.step)


CARD = Card(
    family="1-D",
    published_speed=1_060.0,
    speed_target=5.0,
    paper_ppo=-1.1,
    gradcheck=GradCheck("g", 9.81, warmup=5, steps=4),
    frame=frame,
)
