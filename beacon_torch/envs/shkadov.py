"""shkadov-v0: flatten a falling liquid film with jets (Belus et al. 2019; BEACON paper).

Shkadov's model of a film falling along a wall, for the height h and the flow rate q:

    h_t = -q_x
    q_t = -6/5 (q^2 / h)_x + (h (1 + h_xxx) - q / h^2) / (5 delta) - jets

on a domain of L = L0 + jet_space (n_jets + 2) with a noisy inlet
h(0) = 1 + U(-5e-4, 5e-4), q(0) = 1 and zero-gradient outlet. TVD first derivatives with
the minmod limiter, the paper's one-sided third derivative, Adams-Bashforth 2 with
dt = 0.001, 50 substeps per action (interpolated over the first 20), 400 actions.
Each jet removes flow rate under a parabolic profile 4 units wide (``jet_profiles``).

Every episode starts from a film developed without control for 200 time units, the one
stored with the published code (``start="published"``, the default) or our generator's
(``start="generated"``, :func:`developed_film`, shipped for the default delta and cached
for others), advanced at each reset by a random number (0..``random_start``) of
uncontrolled actions.

``shkadov-separable-v0`` is the same physics with each jet an agent (TorchRL's
multi-agent convention): per-jet observation, action and reward under ``"agents"``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from beacon_torch import seeds
from beacon_torch.cache import cached
from beacon_torch.compiled import Kernels, at
from beacon_torch.core.card import Card, FrameInputs, GradCheck
from beacon_torch.core.physics import Physics
from beacon_torch.core.state import Noise, map_state, where_members
from beacon_torch.numerics import (
    ab2_step,
    interpolated_action,
    interpolation_weights,
    minmod,
    native,
    third_derivative,
    tvd_derivative,
)
from beacon_torch.params import number, param
from beacon_torch.starts import PUBLISHED, choose_start, published_table, start_param

CELLS_PER_UNIT = 5
DX = 1.0 / CELLS_PER_UNIT
DT = 1e-3
SUBSTEPS = 50
N_INTERP = 20
EPISODE_LENGTH = 400
NOISE = 5e-4
JET_HALF_WIDTH = 2.0
OBS_LENGTH = 10.0  # upstream of each jet, sampled every unit length
REWARD_LENGTH = 10.0  # downstream of each jet
GUARD = 1e-8  # in q^2/h and q/h^2, as in the published code
H_MAX = 25.0  # the published code's blow-up bound on |h|
# the developed film: 200 time units on a 580-unit domain (L0 = 550, one jet)
# the developed starts' generation: a new one whenever the scheme changes the film
START_VERSION = 1
DEVELOP_TIME = 200.0
DEVELOP_LENGTH = 580.0
DEVELOP_SEED = 0


class ShkadovState(NamedTuple):
    """One member per row; the cells span the film, the interior ones exclude the
    inlet and outlet cells."""

    h: torch.Tensor  # [batch, n_cells] the film thickness
    q: torch.Tensor  # [batch, n_cells] the flow rate
    dh_prev: torch.Tensor  # [batch, n_cells - 2] the thickness's interior increment one substep before
    dq_prev: torch.Tensor  # [batch, n_cells - 2] the flow rate's interior increment one substep before
    u_prev: torch.Tensor  # [batch, n_jets] the last action (its substeps interpolate from it)


class Film(NamedTuple):
    """A developed film on the development domain: the start of every episode."""

    h: torch.Tensor  # [cells] the film thickness
    q: torch.Tensor  # [cells] the flow rate


@dataclass(frozen=True)
class ShkadovParams:
    L0: float = param(
        150.0, low=20.0, high=DEVELOP_LENGTH, per_member=False, doc="domain length before the jets' extension"
    )
    n_jets: int = param(
        5,
        low=1,
        high=100,
        kind="int",
        per_member=False,
        doc="number of jets (the domain, L0 extended by the jets, at most 580 long)",
    )
    jet_pos: float = param(
        150.0,
        low=OBS_LENGTH + 1.0,
        high=DEVELOP_LENGTH,
        per_member=False,
        doc="position of the first jet (the last jet's reward region inside the domain)",
    )
    jet_space: float = param(10.0, low=2 * JET_HALF_WIDTH, high=100.0, per_member=False, doc="spacing of the jets")
    delta: float = param(
        0.1,
        low=0.01,
        high=10.0,
        per_member=False,
        differentiable=True,
        doc="the film parameter delta of the model (inertia against surface tension)",
    )
    amp: float = param(5.0, low=0.0, high=1e8, doc="jet amplitude A (action scaling)")
    random_start: int = param(
        400, low=0, high=10_000, kind="int", per_member=False, doc="most uncontrolled actions run at each reset"
    )
    start: str = start_param("the published stored film, or the one of developed_film()")

    @property
    def length(self) -> float:
        return self.L0 + self.jet_space * (self.n_jets + 2)

    def __post_init__(self):
        choose_start(self, ("L0", "n_jets", "jet_pos", "jet_space", "delta"))
        if self.length > DEVELOP_LENGTH:
            raise ValueError(
                f"parameters 'L0', 'jet_space' and 'n_jets' give a domain of {self.length:g} units, "
                f"longer than the {DEVELOP_LENGTH:g} of the developed film"
            )
        last = self.jet_pos + self.jet_space * (self.n_jets - 1)
        if last + REWARD_LENGTH > self.length - DX:
            raise ValueError(
                f"parameter 'jet_pos' = {self.jet_pos:g} puts the last jet's reward region past the "
                f"domain end ({self.length:g}); it must be at most "
                f"{self.length - DX - REWARD_LENGTH - self.jet_space * (self.n_jets - 1):g}"
            )


def jet_profiles(centres: list[int], n_cells: int, dtype, device) -> torch.Tensor:
    """``[n_jets, n_cells]`` parabolic jet profiles v = (k - s)(e - k) / (0.25 (e - s)^2),
    zero at the jet's edges s, e and 1 at its centre."""
    half = int(round(JET_HALF_WIDTH / DX))
    k = torch.arange(n_cells, dtype=dtype, device=device)
    out = []
    for c in centres:
        s, e = c - half, c + half
        out.append(((k - s) * (e - k) / (0.25 * (e - s) ** 2)).clamp(min=0.0))
    return torch.stack(out)


def shkadov_rhs(h: torch.Tensor, q: torch.Tensor, forcing: torch.Tensor, delta, dx: float):
    """(dh/dt, dq/dt) at the interior cells; ``forcing`` is the jets' flow-rate removal
    at the interior cells."""
    hi, qi = h[:, 1:-1], q[:, 1:-1]
    dh = -tvd_derivative(q, dx, minmod)
    dq = (
        -1.2 * tvd_derivative(q * q / (h + GUARD), dx, minmod)
        + (hi * (third_derivative(h, dx) + 1.0) - qi / (hi * hi + GUARD)) / (5.0 * delta)
        - forcing
    )
    return dh, dq


def shkadov_substep(
    fields: tuple[torch.Tensor, ...], forcing: torch.Tensor, inlet: torch.Tensor, delta, dx: float
) -> tuple[torch.Tensor, ...]:
    """One AB2 step of ``(h, q, dh_prev, dq_prev)`` with the jets' forcing ``[B, n - 2]``
    and the inlet film thickness ``inlet`` ``[B, 1]`` (the inlet flow rate is 1)."""
    h, q, dh_prev, dq_prev = fields
    dh, dq = shkadov_rhs(h, q, forcing, delta, dx)
    hi, qi = ab2_step(h[:, 1:-1], dh, dh_prev, DT), ab2_step(q[:, 1:-1], dq, dq_prev, DT)
    h = torch.cat((inlet, hi, hi[:, -1:]), -1)
    q = torch.cat((torch.ones_like(inlet), qi, qi[:, -1:]), -1)
    return h, q, dh, dq


def action_substep(
    i,
    fields: tuple[torch.Tensor, ...],
    forcing_prev: torch.Tensor,
    forcing_new: torch.Tensor,
    alpha: torch.Tensor,
    inlet: torch.Tensor,
    delta,
    dx: float,
) -> tuple[torch.Tensor, ...]:
    """Substep ``i`` of an action: :func:`shkadov_substep` with the forcing
    interpolated by ``alpha[i]`` (:func:`interpolation_weights`) and the inlet
    ``inlet[i]`` (``inlet``: ``[SUBSTEPS, B, 1]``)."""
    return shkadov_substep(
        fields, interpolated_action(forcing_prev, forcing_new, at(alpha, i)), at(inlet, i), delta, dx
    )


def inlet_noise(generator: torch.Generator | None, members: int, dtype: torch.dtype, device=None) -> torch.Tensor:
    """The random numbers of one action's inlet, ``[SUBSTEPS, members, 1]`` uniform in
    [0, 1): one draw per substep and member."""
    return torch.rand((SUBSTEPS, members, 1), generator=generator, dtype=dtype, device=device)


_CONSTANTS = (DX, 0.5 * DT, 2.0 * DX**3, DX**3)  # dx, AB2's dt / 2, the third derivative's divisors
_action = native.operator(
    "shkadov_action(Tensor h, Tensor q, Tensor dh_prev, Tensor dq_prev, Tensor forcing_prev, Tensor forcing_new,"
    " Tensor alpha, Tensor inlet, Tensor scale, float dx, float c, float third_a, float third_b)"
    " -> (Tensor, Tensor, Tensor, Tensor, Tensor)",
    native.shkadov_action,
    lambda h, q, dh, dq, fp, fn, alpha, inlet, scale, *numbers: (
        *(torch.empty_like(t) for t in (h, q, dh, dq)),
        h.new_empty((h.shape[0], alpha.shape[0], 2, h.shape[1])),
    ),
    native.rows_vmap("shkadov_action", (0, 0, 0, 0, 0, 0, None, 1, 0), (0, 0, 0, 0, 0)),
)


def _adjoint_kernel(states, alpha, scale, gh, gq, gdh, gdq, dx, c, third_a, third_b):
    return native.shkadov_adjoint(states, alpha, scale, (gh, gq, gdh, gdq), dx, c, third_a, third_b)


_adjoint = native.operator(
    "shkadov_adjoint(Tensor states, Tensor alpha, Tensor scale, Tensor gh, Tensor gq, Tensor gdh, Tensor gdq,"
    " float dx, float c, float third_a, float third_b)"
    " -> (Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor)",
    _adjoint_kernel,
    lambda states, alpha, scale, gh, gq, gdh, gdq, *numbers: (
        *(torch.empty_like(t) for t in (gh, gq, gdh, gdq, gdh, gdh)),
        gh.new_empty((alpha.shape[0], gh.shape[0], 1)),
        gh.new_empty(gh.shape[0]),
    ),
    native.rows_vmap("shkadov_adjoint", (0, None, 0, 0, 0, 0, 0), (0, 0, 0, 0, 0, 0, 1, 0)),
)


class _Action(torch.autograd.Function):
    """An action of :func:`action_substep` as one C loop a member, its backward pass the
    same loop's adjoint run through the substeps in reverse."""

    generate_vmap_rule = True

    @staticmethod
    def forward(h, q, dh_prev, dq_prev, forcing_prev, forcing_new, alpha, inlet, scale):
        return _action(h, q, dh_prev, dq_prev, forcing_prev, forcing_new, alpha, inlet, scale, *_CONSTANTS)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        ctx.mark_non_differentiable(output[4])
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(output[4], inputs[6], inputs[8])

    @staticmethod
    def backward(ctx, gh, gq, gdh, gdq, _):
        states, alpha, scale = ctx.saved_tensors
        field, inner = states[:, 0, 0], states[:, 0, 0, 1:-1]
        gh, gq, gdh, gdq = native.output_grads((gh, gq, gdh, gdq), (field, field, inner, inner))
        with torch.no_grad():  # differentiable once: the adjoint keeps no graph
            gh, gq, gdh, gdq, g_prev, g_new, g_inlet, g_scale = _adjoint(
                states, alpha, scale, gh, gq, gdh, gdq, *_CONSTANTS
            )
        return gh, gq, gdh, gdq, g_prev, g_new, None, g_inlet, g_scale


def shkadov_action(
    fields: tuple[torch.Tensor, ...],
    forcing_prev: torch.Tensor,
    forcing_new: torch.Tensor,
    alpha: torch.Tensor,
    inlet: torch.Tensor,
    delta,
) -> tuple[torch.Tensor, ...]:
    """The substeps of :func:`action_substep` over an action (``alpha``'s length) where
    autograd records, on the CPU: the tensor loop's values bit for bit, and its gradient
    to round-off from a reverse loop in C over the stored substeps, instead of a graph
    of some forty slices a substep."""
    h = fields[0]
    rows = h.shape[0]
    scale = 5.0 * (delta if isinstance(delta, torch.Tensor) else torch.tensor(delta, dtype=torch.float64))
    scale = scale.to(h.dtype).reshape(-1).expand(rows)
    return _Action.apply(*fields, forcing_prev, forcing_new, alpha, inlet.expand(-1, rows, 1), scale)[:4]


def run_action(
    state: ShkadovState,
    action: torch.Tensor,
    profiles: torch.Tensor,
    delta,
    dx: float,
    noise: torch.Tensor,
    amp=5.0,
    substeps=None,
) -> ShkadovState:
    """One action period (``SUBSTEPS`` AB2 steps) of jet amplitudes ``action`` ``[B, n_jets]``
    with the inlet drawn from ``noise`` (:func:`inlet_noise`); ``amp`` is a number or a
    ``[B, 1]`` tensor; ``substeps`` is the loop of :func:`action_substep` (an env's
    ``kernels.loop``; None: eager)."""
    inlet = 1.0 + NOISE * (2.0 * noise - 1.0)
    # the forcing is linear in the jet amplitudes: interpolate it, not the amplitudes,
    # so that the profiles are summed twice per action instead of at every substep
    forcing_prev, forcing_new = amp * (state.u_prev @ profiles), amp * (action @ profiles)
    alpha = interpolation_weights(SUBSTEPS, N_INTERP, action.dtype, action.device)
    fields = state.h, state.q, state.dh_prev, state.dq_prev
    given = (*fields, forcing_prev, forcing_new, inlet, *([delta] if isinstance(delta, torch.Tensor) else []))
    if dx == DX and native.applies(state.h.device, state.h.dtype) and native.recording(*given):
        h, q, dh_prev, dq_prev = shkadov_action(fields, forcing_prev, forcing_new, alpha, inlet, delta)
    else:
        substeps = Kernels().loop(action_substep) if substeps is None else substeps
        h, q, dh_prev, dq_prev = substeps(SUBSTEPS, fields, forcing_prev, forcing_new, alpha, inlet, delta, dx)
    return ShkadovState(h=h, q=q, dh_prev=dh_prev, dq_prev=dq_prev, u_prev=action)


def flat_state(num_envs: int, n_cells: int, n_jets: int, dtype, device) -> ShkadovState:
    one = torch.ones((num_envs, n_cells), dtype=dtype, device=device)
    zero = torch.zeros((num_envs, n_cells - 2), dtype=dtype, device=device)
    u_prev = torch.zeros((num_envs, n_jets), dtype=dtype, device=device)
    return ShkadovState(h=one, q=one.clone(), dh_prev=zero, dq_prev=zero.clone(), u_prev=u_prev)


def developed_film(delta: float = 0.1, *, seed: int = DEVELOP_SEED, time: float = DEVELOP_TIME, device="cpu") -> Film:
    """The published initial film: from the flat film (h = q = 1) on a 580-unit domain,
    ``time`` time units without control, in float64, with the inlet noise drawn from a
    generator seeded by ``seed``. Returns ``h`` and ``q`` of shape ``[n_cells]``.

    200 time units are 200,000 substeps: minutes on a CPU. The default-delta film ships
    with the package; others are cached by :func:`beacon_torch.cache.cached`.
    """
    n = int(round(DEVELOP_LENGTH / DX))
    g = seeds.generator(seed, device)
    state = flat_state(1, n, 1, torch.float64, device)
    profiles = torch.zeros((1, n - 2), dtype=torch.float64, device=device)
    zero = torch.zeros((1, 1), dtype=torch.float64, device=device)
    from tqdm.auto import tqdm

    for _ in tqdm(range(int(round(time / (DT * SUBSTEPS)))), desc="shkadov film", unit="actions", leave=False):
        state = run_action(state, zero, profiles, delta, DX, inlet_noise(g, 1, torch.float64, device))
    return Film(h=state.h[0], q=state.q[0])


class ShkadovPhysics(Physics):
    """The falling liquid film with jets (one continuous action per jet)."""

    Params = ShkadovParams
    state_type = ShkadovState
    episode_length = EPISODE_LENGTH
    # Below every completed episode of the policies tried (docs/envs/shkadov.md); every
    # reward is negative, so a blown-up episode scores below this whenever it happens
    blowup_reward = -100.0
    grad_action_in_c = True
    deterministic = False
    diagnostics = {
        "film_deviation": "the mean over the jets of dx sum (h - 1)^2 / cells downstream of each (minus the reward)",
        "max_thickness": "the largest film thickness h",
    }

    @classmethod
    def sizes(cls, p) -> tuple[int, int]:
        return p.n_jets * int(round(OBS_LENGTH)), p.n_jets  # the flow rates upstream of every jet

    def member_floats(self) -> int:
        return 4 * self.n_cells  # h, q and their previous slopes

    def setup(self, p) -> None:
        self.n_cells = int(round(p.length / DX))
        self.n_jets = p.n_jets
        step = int(round(p.jet_space / DX))
        self.jet_centres = [int(round(p.jet_pos / DX)) + j * step for j in range(p.n_jets)]
        profiles = jet_profiles(self.jet_centres, self.n_cells, self.dtype, self.device)
        self._profiles = profiles[:, 1:-1].contiguous()
        self._substeps = self.kernels.loop(action_substep)
        obs = [
            c - int(round(OBS_LENGTH / DX)) + CELLS_PER_UNIT * m
            for c in self.jet_centres
            for m in range(int(round(OBS_LENGTH)))
        ]
        self._obs_index = torch.tensor(obs, device=self.device)
        width = int(round(REWARD_LENGTH / DX))
        self._reward_index = torch.tensor([[c + m for m in range(width)] for c in self.jet_centres], device=self.device)

    def _film(self, p) -> Film:
        # loaded at the first reset: an env started by set_state never develops its film
        if p.start == PUBLISHED:
            table = published_table(
                "shkadov", int(round(DEVELOP_LENGTH / DX)), 3
            )  # rows: x, h, q on the development domain
            film = map_state(lambda v: v.to(device=self.device, dtype=self.dtype), Film(h=table[:, 1], q=table[:, 2]))
        else:
            delta = number(p.delta)
            n = int(round(DEVELOP_LENGTH / DX))
            like = Film(h=torch.ones(n, dtype=torch.float64), q=torch.ones(n, dtype=torch.float64))
            develop = lambda: developed_film(delta)
            bounds, where = {"h": (-H_MAX, H_MAX)}, dict(device=self.device, dtype=self.dtype)
            film = cached("shkadov-film", START_VERSION, dict(delta=delta), develop, like, bounds, **where)
        return map_state(lambda v: v[: self.n_cells], film)

    def noise(self, p, generator) -> Noise:
        return {"inlet": inlet_noise(generator, self.num_envs, self.dtype, self.device)}

    def _advance_state(self, p, state: ShkadovState, action: torch.Tensor, noise: Noise) -> ShkadovState:
        amp = self.member(p.amp)
        return run_action(state, action, self._profiles, p.delta, DX, noise["inlet"], amp, self._substeps)

    def state_like(self, p) -> ShkadovState:
        return flat_state(self.num_envs, self.n_cells, self.n_jets, self.dtype, self.device)

    def initial_state(self, p, generator, mask=None) -> ShkadovState:
        film = self._film(p)
        state = flat_state(self.num_envs, self.n_cells, self.n_jets, self.dtype, self.device)._replace(
            h=film.h.expand(self.num_envs, -1).clone(), q=film.q.expand(self.num_envs, -1).clone()
        )
        if p.random_start == 0:
            return state
        # each member being reset runs its own random number of uncontrolled actions;
        # only those members are computed, and each stops at its own count
        n_run = torch.randint(0, p.random_start + 1, (self.num_envs,), generator=generator, device=self.device)
        if mask is not None:
            n_run = torch.where(mask, n_run, torch.zeros_like(n_run))
        idx = (n_run > 0).nonzero()[:, 0]
        if idx.numel() == 0:
            return state
        # the members being reset are run as a batch of a power-of-two size (padded with
        # copies of the first, whose results are dropped): a compiled action then
        # exists for a few batch sizes, not for every count of members reset at once
        n = idx.numel()
        size = min(self.num_envs, 1 << (n - 1).bit_length())
        rows = torch.cat((idx, idx[:1].expand(size - n)))
        runs = torch.cat((n_run[idx], n_run.new_zeros(size - n)))
        sub = map_state(lambda v: v[rows], state)
        zero = torch.zeros((size, self.n_jets), dtype=self.dtype, device=self.device)
        for a in range(int(n_run.max())):
            # uncontrolled: no jet forcing, whatever the (per-member) amplitude; the
            # padding draws nothing from the generator
            noise = inlet_noise(generator, n, self.dtype, self.device)
            noise = torch.cat((noise, noise.new_zeros((SUBSTEPS, size - n, 1))), 1)
            new = run_action(sub, zero, self._profiles, p.delta, DX, noise, 0.0, self._substeps)
            sub = where_members(runs > a, new, sub)
        return type(state)(*(v.index_copy(0, idx, w[:n]) for v, w in zip(state, sub, strict=True)))

    def jet_rewards(self, h: torch.Tensor) -> torch.Tensor:
        """``[B, n_jets]``: -dx sum (h - 1)^2 over the cells downstream of each jet,
        normalised by the region's cell count."""
        region = h[:, self._reward_index]  # [B, n_jets, cells]
        return -DX * ((region - 1.0) ** 2).sum(-1) / region.shape[-1]

    def advance(self, p, state: ShkadovState, action: torch.Tensor, count: torch.Tensor, noise: Noise):
        new = self._advance_state(p, state, action, noise)
        return new, self.jet_rewards(new.h).mean(-1)

    def diagnose(self, p, state: ShkadovState) -> dict[str, torch.Tensor]:
        return {"film_deviation": -self.jet_rewards(state.h).mean(-1), "max_thickness": state.h.amax(-1)}

    def observe(self, p, state: ShkadovState) -> torch.Tensor:
        return state.q[:, self._obs_index]

    def out_of_bounds(self, p, state: ShkadovState) -> torch.Tensor:
        return (state.h.abs() > H_MAX).any(-1)


class ShkadovSeparablePhysics(ShkadovPhysics):
    """The film with each jet an agent: actions ``[B, n_jets, 1]``, observations
    ``[B, n_jets, 10]`` and one reward per jet ``[B, n_jets]``."""

    @property
    def action_shape(self) -> tuple[int, ...]:
        return (self.n_jets, 1)

    def advance(self, p, state: ShkadovState, action: torch.Tensor, count: torch.Tensor, noise: Noise):
        new = self._advance_state(p, state, action[..., 0], noise)
        return new, self.jet_rewards(new.h)

    def observe(self, p, state: ShkadovState) -> torch.Tensor:
        return super().observe(p, state).reshape(self.num_envs, self.n_jets, -1)


def frame(f: FrameInputs) -> np.ndarray:
    """The film's height and the jets' actions, over the space-time diagram of the
    episode when it is recorded."""
    from beacon_torch import render

    x = DX * np.arange(f.physics.n_cells)
    h = torch.stack([s.h for s in f.states]).double().numpy()
    actions = f.states[-1].u_prev.double().numpy().ravel()
    jets_x = [DX * c for c in f.physics.jet_centres]
    return render.shkadov_frame(x, h, jets_x, JET_HALF_WIDTH, actions, DT * SUBSTEPS, f.step, space_time=f.recorded)


# shkadov-separable-v0 has the same card: the jets as agents of TorchRL's multi-agent
# layout, under the "agents" sub-TensorDict (agent dimension after the batch):
# observation [B, n_jets, 10] (the flow rate upstream of each jet), action
# [B, n_jets, 1] and reward [B, n_jets, 1] (each jet's own downstream flatness; their
# mean is the shkadov-v0 reward); the done flags are shared, at the root
CARD = Card(
    family="1-D",
    published_speed=300.0,
    speed_target=5.0,
    paper_ppo=-0.8,
    gradcheck=GradCheck("delta", 0.1, warmup=3, steps=3),
    # a reset runs up to 3 uncontrolled actions instead of 400
    test_settings={"random_start": 3},
    frame=frame,
)
