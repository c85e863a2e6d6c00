"""ks-v0: hold the chaotic Kuramoto-Sivashinsky flow on one of its unstable equilibria
(Bucci, Semeraro, Allauzen, Wisniewski, Cordier & Mathelin, Proc. R. Soc. A 475, 2019).

    u_t + u u_x + u_xx + u_xxxx = f(x, t),   f = amp sum_i a_i psi_i(x),   x in [0, L), periodic

L = 22 (chaotic), 64 points. Four Gaussian actuators psi_i (width sigma = 0.4, peak 1)
at x = 0, L/4, L/2, 3L/4; eight sensors, equally spaced, observe u. One step of the
semi-implicit low-storage Runge-Kutta scheme of Spalart, Moser & Rogers (1991) per
action, dt = 0.05: the linear terms (-u_xx - u_xxxx) by Crank-Nicolson, the advection
and the forcing by third-order Runge-Kutta, in Fourier space. The reward is minus the
2-norm, over the 64 points, of the distance to the target equilibrium (E1, E2 or E3 of
Cvitanovic, Davidchack & Siminos 2010), which the env finds by Newton's method on its
own discrete equations. Episodes start from states on the chaotic attractor.

Every operator of the scheme is diagonal in Fourier space, so each Runge-Kutta stage is
one product of ``[u, u^2, (u^2 of the stage before), a]`` with a real matrix built once
(the circulant matrices of the Fourier multipliers): at 64 points that costs what the
transforms would, and keeps the step free of complex tensors for the compiler and for
autograd.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from beacon_torch import seeds
from beacon_torch.cache import cached
from beacon_torch.core.card import PHYSICAL_LIMIT, Card, FrameInputs, GradCheck, Reference
from beacon_torch.core.physics import Physics
from beacon_torch.core.state import Noise
from beacon_torch.params import param

DT = 0.05
# the start bank's generation: a new one whenever the scheme changes the attractor's states
START_VERSION = 1
EPISODE_LENGTH = 3000
N_SENSORS = 8
ACTUATORS = (0.0, 0.25, 0.5, 0.75)  # positions, as fractions of L
# Spalart, Moser & Rogers (1991): the stages' implicit (beta), explicit linear (alpha)
# and nonlinear (gamma, zeta: this stage's and the previous stage's) weights
ALPHA = (29.0 / 96.0, -3.0 / 40.0, 1.0 / 6.0)
BETA = (37.0 / 160.0, 5.0 / 24.0, 1.0 / 6.0)
GAMMA = (8.0 / 15.0, 5.0 / 12.0, 3.0 / 4.0)
ZETA = (0.0, -17.0 / 60.0, -5.0 / 12.0)
TARGETS = ("E1", "E2", "E3")
# Newton starts from a sine of the equilibrium's dominant wavenumber, of the amplitude
# that gives its published energy at L = 22 (2 sqrt(E))
GUESS = {"E1": (1, 1.0), "E2": (2, 1.3), "E3": (3, 2.5)}
# the start bank: trajectories from small random fields, the transient dropped, then
# one state every SPACING time units
BANK_TRAJECTORIES = 32
BANK_TRANSIENT = 100.0
BANK_SPACING = 5.0
BANK_STATES = 32  # per trajectory


# Cvitanovic, Davidchack & Siminos (SIAM J. Appl. Dyn. Syst. 9, 2010), L = 22: the
# equilibria's energy, the mean of u^2 / 2 (their table of properties), and their
# leading stability eigenvalues (their table of eigenvalues: E1's two unstable pairs,
# E2's pair, E3's double real one); the chaotic attractor's leading Lyapunov exponent
# (their section on the L = 22 state space)
PUBLISHED_ENERGY = {"E1": 0.2609, "E2": 0.4382, "E3": 1.5876}
PUBLISHED_EIGENVALUES = {"E1": (0.1308 + 0.3341j, 0.0824 + 0.3402j), "E2": (0.1390 + 0.2384j,), "E3": (0.0933,)}
PUBLISHED_LYAPUNOV = 0.048


class KSState(NamedTuple):
    """One member per row."""

    u: torch.Tensor  # [batch, n] the field at the grid points x_j = j L / n
    a: torch.Tensor  # [batch, 4] the last action (the actuators' amplitudes)


@dataclass(frozen=True)
class KSParams:
    L: float = param(22.0, low=6.3, high=400.0, per_member=False, doc="domain length (chaotic at the default 22)")
    n: int = param(64, low=16, high=1024, kind="int", per_member=False, doc="grid points (a multiple of 8)")
    target: str = param("E1", kind="choice", choices=TARGETS, doc="the equilibrium to hold (E1, E2 or E3)")
    amp: float = param(0.5, low=0.0, high=1e3, doc="forcing amplitude of an actuator at a = 1")
    sigma: float = param(0.4, low=0.01, high=10.0, per_member=False, doc="actuator width (Gaussian standard deviation)")

    def __post_init__(self):
        if self.n % N_SENSORS:
            raise ValueError(f"parameter 'n' must be a multiple of {N_SENSORS}, got {self.n!r}")


def wavenumbers(L: float, n: int) -> np.ndarray:
    """q_k = 2 pi k / L of the real transform's modes k = 0 .. n/2."""
    return 2.0 * np.pi * np.arange(n // 2 + 1) / L


def symbols(L: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The Fourier symbols of the real transform's modes: the linear operator
    -d_xx - d_xxxx (q^2 - q^4) and the advection -(u^2)_x / 2 (-i q / 2, none at the
    Nyquist mode, which a real field's derivative does not have)."""
    q = wavenumbers(L, n)
    advect = -0.5j * q
    advect[-1] = 0.0
    return q**2 - q**4, advect


def circulant(symbol: np.ndarray, n: int) -> np.ndarray:
    """The real ``[n, n]`` matrix M with M u = irfft(symbol * rfft(u)) (a Fourier
    multiplier; the imaginary part at the Nyquist mode is dropped, as irfft does)."""
    return np.fft.irfft(symbol[:, None] * np.fft.rfft(np.eye(n), axis=0), n=n, axis=0)


def actuators(L: float, n: int, sigma: float) -> np.ndarray:
    """``[n, 4]``: the actuators' shapes at the grid points, Gaussians of peak 1 at the
    periodic distance from their centres."""
    x = L * np.arange(n) / n
    centres = L * np.asarray(ACTUATORS)
    d = (x[:, None] - centres[None, :] + L / 2) % L - L / 2
    return np.exp(-0.5 * (d / sigma) ** 2)


def stage_matrices(L: float, n: int, sigma: float, dt: float = DT) -> np.ndarray:
    """``[3, 3n + 4, n]`` float64: per stage, W with u_next = [u, u^2, u_prev^2, a] @ W,
    where u_prev is the previous stage's input and a the actuators' amplitudes (the
    forcing, amp included, enters like the advection, with gamma + zeta)."""
    lam, advect = symbols(L, n)
    psi = actuators(L, n, sigma)
    out = []
    for alpha, beta, gamma, zeta in zip(ALPHA, BETA, GAMMA, ZETA, strict=True):
        implicit = 1.0 / (1.0 - beta * dt * lam)
        keep = circulant((1.0 + alpha * dt * lam) * implicit, n)
        now = circulant(gamma * dt * advect * implicit, n)
        before = circulant(zeta * dt * advect * implicit, n)
        force = circulant((gamma + zeta) * dt * implicit, n) @ psi
        out.append(np.concatenate((keep.T, now.T, before.T, force.T), 0))
    return np.stack(out)


def ks_step(u: torch.Tensor, forcing: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """One step of the scheme: ``u`` ``[B, n]``, ``forcing`` ``[B, 4]`` (amp a, held
    over the step), ``weights`` the ``[3, 3n + 4, n]`` of :func:`stage_matrices`."""
    square = u * u
    previous = torch.zeros_like(u)
    for w in weights.unbind(0):
        u, previous = torch.cat((u, square, previous, forcing), -1) @ w, square
        square = u * u
    return u


def rhs(u: torch.Tensor, L: float) -> torch.Tensor:
    """The uncontrolled equations' right-hand side -u u_x - u_xx - u_xxxx at the grid
    points (``u`` ``[..., n]``, spectral derivatives)."""
    n = u.shape[-1]
    lam, advect = (torch.as_tensor(s, device=u.device) for s in symbols(L, n))
    return torch.fft.irfft(lam * torch.fft.rfft(u) + advect * torch.fft.rfft(u * u), n=n)


def jacobian(u: torch.Tensor, L: float) -> np.ndarray:
    """``[n, n]`` float64: the derivative of :func:`rhs` at the field ``u`` ``[n]``,
    whose eigenvalues are an equilibrium's stability exponents."""
    lam, advect = symbols(L, u.shape[-1])
    # the advection's derivative at u: -(u v)_x, the symbol -2 x advect applied to u v
    return circulant(lam, u.shape[-1]) + circulant(2.0 * advect, u.shape[-1]) @ np.diag(u.double().cpu().numpy())


def equilibrium(target: str, L: float = 22.0, n: int = 64, tol: float = 1e-10) -> torch.Tensor:
    """The equilibrium ``target`` (E1, E2 or E3) of the uncontrolled equations, ``[n]``
    float64: Newton's method in the subspace of odd fields u(-x) = -u(x), which holds
    every equilibrium of L = 22 and fixes their phase (Cvitanovic et al.'s reference
    states), from a sine of the equilibrium's dominant wavenumber. Raises ValueError
    where Newton's method does not converge (another L may not have this equilibrium)."""
    k, amplitude = GUESS[target]
    x = torch.arange(n, dtype=torch.float64) * L / n
    modes = torch.arange(1, n // 2, dtype=torch.float64)
    basis = torch.sin(2.0 * np.pi * modes[:, None] * x[None, :] / L)  # [n/2 - 1, n]
    b = torch.zeros(n // 2 - 1, dtype=torch.float64)
    b[k - 1] = -amplitude
    found = "Newton's method did not converge"

    def equations(coeffs):
        # the odd part of the right-hand side, in the sine coefficients
        return 2.0 / n * basis @ rhs(coeffs @ basis, L)

    for _ in range(50):
        f = equations(b)
        if float(f.abs().max()) < tol:
            u = b @ basis
            if float(u.abs().max()) > 1e-6:
                return u
            found = "Newton's method converged to the flat state u = 0"
            break
        jac = torch.autograd.functional.jacobian(equations, b)
        b = b - torch.linalg.solve(jac, f)
    raise ValueError(f"no equilibrium {target} found at L = {L:g} with {n} points ({found})")


def attractor_bank(L: float, n: int, sigma: float) -> KSState:
    """Start states on the uncontrolled chaotic attractor, float64: the fields of
    :data:`BANK_TRAJECTORIES` trajectories from small random fields (a fixed seed),
    after :data:`BANK_TRANSIENT` time units, every :data:`BANK_SPACING`."""
    generator = seeds.generator(0)
    u = 0.1 * torch.randn(BANK_TRAJECTORIES, n, dtype=torch.float64, generator=generator)
    u = u - u.mean(-1, keepdim=True)  # the equilibria's mean: the flow keeps it
    weights = torch.as_tensor(stage_matrices(L, n, sigma))
    zero = torch.zeros(BANK_TRAJECTORIES, len(ACTUATORS), dtype=torch.float64)
    for _ in range(round(BANK_TRANSIENT / DT)):
        u = ks_step(u, zero, weights)
    states = []
    for _ in range(BANK_STATES):
        for _ in range(round(BANK_SPACING / DT)):
            u = ks_step(u, zero, weights)
        states.append(u)
    fields = torch.stack(states, 1).reshape(-1, n)
    return KSState(u=fields, a=torch.zeros(len(fields), len(ACTUATORS), dtype=torch.float64))


class KSPhysics(Physics):
    """The forced Kuramoto-Sivashinsky flow on a periodic domain."""

    Params = KSParams
    state_type = KSState
    episode_length = EPISODE_LENGTH
    # an action is three matrix products: differentiated, the calls around them cost most
    grad_whole_action = True
    deterministic = False  # each episode starts from a state of the bank, drawn
    # an episode's reward is above -3000 x 200 (|u| stays below 10 on the attractor and
    # under the bounded forcing): a blow-up scores below any completed episode
    blowup_reward = -1e6
    diagnostics = {
        "distance": "the 2-norm of u - u_E over the grid points (minus the reward)",
        "energy": "the mean of u^2 / 2 (E1: 0.2609, E2: 0.4382, E3: 1.5876 at L = 22)",
        "mean": "the mean of u (zero on the equilibria; the actuators' forcing moves it)",
    }

    @classmethod
    def sizes(cls, p) -> tuple[int, int]:
        return N_SENSORS, len(ACTUATORS)

    def member_floats(self) -> int:
        return self.n + len(ACTUATORS)

    def setup(self, p) -> None:
        self.L, self.n, self.sigma = float(p.L), int(p.n), float(p.sigma)
        self._weights = self.tensor(stage_matrices(self.L, self.n, self.sigma))
        self.target = self.tensor(equilibrium(p.target, self.L, self.n))
        self._sensors = slice(0, self.n, self.n // N_SENSORS)
        self._step = self.kernels(ks_step)

    def starts(self) -> torch.Tensor:
        """``[1024, n]``: the start fields, in the physics' dtype and on its device (the
        bank is computed once per L, n and sigma in float64, and cached)."""
        key = dict(L=self.L, n=self.n, sigma=self.sigma)
        size = BANK_TRAJECTORIES * BANK_STATES
        zeros = torch.zeros(size, self.n + len(ACTUATORS), dtype=torch.float64)
        like = KSState(u=zeros[:, : self.n], a=zeros[:, self.n :])
        bank = lambda: attractor_bank(self.L, self.n, self.sigma)
        return cached("ks-attractor", START_VERSION, key, bank, like, device=self.device, dtype=self.dtype).u

    def initial_state(self, p, generator, mask=None) -> KSState:
        starts = self.starts()
        pick = torch.randint(len(starts), (self.num_envs,), generator=generator, device=self.device)
        return KSState(
            u=starts[pick], a=torch.zeros(self.num_envs, len(ACTUATORS), dtype=self.dtype, device=self.device)
        )

    def advance(self, p, state: KSState, action: torch.Tensor, count: torch.Tensor, noise: Noise):
        u = self._step(state.u, self.member(p.amp) * action, self._weights)
        reward = -torch.linalg.vector_norm(u - self.target, dim=-1)
        return KSState(u=u, a=action), reward

    def diagnose(self, p, state: KSState) -> dict[str, torch.Tensor]:
        u = state.u
        return {
            "distance": torch.linalg.vector_norm(u - self.target, dim=-1),
            "energy": 0.5 * (u * u).mean(-1),
            "mean": u.mean(-1),
        }

    def observe(self, p, state: KSState) -> torch.Tensor:
        return state.u[:, self._sensors]


def frame(f: FrameInputs) -> np.ndarray:
    """The field against the target equilibrium, and the actuators' amplitudes."""
    from beacon_torch.render import ks_frame

    last, physics = f.states[-1], f.physics
    x = physics.L * np.arange(physics.n) / physics.n
    target = physics.target.double().numpy()
    return ks_frame(x, last.u.double().numpy(), target, last.a.double().numpy(), DT * f.step)


CARD = Card(
    family="1-D",
    # no published controller's distance can be read; the distance cannot go below 0
    reference=Reference(
        PHYSICAL_LIMIT, "the target equilibrium held exactly from the first action: distance 0", score=0.0
    ),
    gradcheck=GradCheck("amp", 0.5, warmup=20, steps=5),
    frame=frame,
)
