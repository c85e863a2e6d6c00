"""vortex-v0: lock a vortex-induced vibration in its high-energy cycle (Meliga et al.).

Coupled amplitude equations for the flow disturbance A and the cylinder position Y::

    dA/dt = lambda (1/Re* - 1/Re) A - mu A |A|^2 + alpha Y + k e^{i phi} A
    dY/dt = (-omega* gamma + i (omega_s - omega*)) Y + beta / (omega* m) A

with the proportional feedback k e^{i phi} A as control. Five LSRK4 steps of dt = 0.1
per action (dt_act = 0.5), 800 actions. Actions a in [-1, 1]^2 give the gain
k = 0.15 (a0 + 1) in [0, 0.3] and the phase phi = pi a1.

The state is carried as four reals (Re A, Im A, Re Y, Im Y), so the kernels stay real
arithmetic (cheap to compile and to differentiate).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from beacon_torch.core.card import Card, FrameInputs, GradCheck
from beacon_torch.core.physics import Physics
from beacon_torch.core.state import Noise
from beacon_torch.numerics import lsrk4_step
from beacon_torch.params import param

LAMBDA = complex(9.153, 3.239)
MU = complex(308.9, -1025.0)
ALPHA = complex(0.03492, 0.01472)
BETA = 1.0
RE_STAR = 46.6
OMEGA_STAR = 0.74
OMEGA_S = 1.1
GAMMA = 0.023
MASS = 10.0
K_MAX = 0.3

DT = 0.1
SUBSTEPS = 5
DT_ACT = DT * SUBSTEPS
EPISODE_LENGTH = 800


class VortexState(NamedTuple):
    """One member per row."""

    ay: torch.Tensor  # [batch, 4] (Re A, Im A, Re Y, Im Y)
    rate: torch.Tensor  # [batch, 4] the right-hand side of the last LSRK4 stage
    k: torch.Tensor  # [batch] the control gain of the last action
    phi: torch.Tensor  # [batch] the control phase of the last action
    y_prev: torch.Tensor  # [batch] the cylinder's displacement at the last action


@dataclass(frozen=True)
class VortexParams:
    re: float = param(50.0, low=0.0, high=1e4, low_open=True, doc="Reynolds number")
    w: float = param(50.0, low=0.0, high=1e6, doc="weight of the actuation cost in the reward")
    a0: complex = param(
        complex(-0.00385, -0.00378), low=0.0, high=10.0, kind="complex", doc="initial flow amplitude A0"
    )
    y0: complex = param(
        complex(0.00118, -0.00131), low=0.0, high=10.0, kind="complex", doc="initial cylinder amplitude Y0"
    )


def vortex_rhs(s: torch.Tensor, k: torch.Tensor, phi: torch.Tensor, re) -> torch.Tensor:
    """Time derivative of (Re A, Im A, Re Y, Im Y) under the feedback k e^{i phi} A."""
    ar, ai, yr, yi = s.unbind(-1)
    growth = 1.0 / RE_STAR - 1.0 / re
    a2 = ar * ar + ai * ai
    # lambda g A - mu |A|^2 A + alpha Y + k e^{i phi} A, written out in real arithmetic
    cr = LAMBDA.real * growth - MU.real * a2 + k * torch.cos(phi)
    ci = LAMBDA.imag * growth - MU.imag * a2 + k * torch.sin(phi)
    dar = cr * ar - ci * ai + ALPHA.real * yr - ALPHA.imag * yi
    dai = cr * ai + ci * ar + ALPHA.real * yi + ALPHA.imag * yr
    # (-omega* gamma + i (omega_s - omega*)) Y + beta / (omega* m) A
    lr, li = -OMEGA_STAR * GAMMA, OMEGA_S - OMEGA_STAR
    coupling = BETA / (OMEGA_STAR * MASS)
    dyr = lr * yr - li * yi + coupling * ar
    dyi = lr * yi + li * yr + coupling * ai
    return torch.stack((dar, dai, dyr, dyi), -1)


def displacement(s: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """y = 2 Re[Y e^{i omega* t}], the cylinder displacement."""
    c, sn = torch.cos(OMEGA_STAR * t), torch.sin(OMEGA_STAR * t)
    return 2.0 * (s[:, 2] * c - s[:, 3] * sn)


def vortex_substep(
    i, carry: tuple[torch.Tensor, torch.Tensor], k: torch.Tensor, phi: torch.Tensor, re
) -> tuple[torch.Tensor, torch.Tensor]:
    """Substep ``i`` of an action: one LSRK4 step of dt = 0.1 with the feedback gain ``k`` and phase ``phi`` ``[B]``
    on ``(state, rate)``; the rate carried in is replaced by the right-hand side of the
    step's last stage (what the published env observes)."""
    return lsrk4_step(lambda u, t: vortex_rhs(u, k, phi, re), carry[0], 0.0, DT)


class VortexPhysics(Physics):
    """The vortex-induced vibration model with a feedback of gain and phase."""

    Params = VortexParams
    state_type = VortexState
    episode_length = EPISODE_LENGTH
    # 5 substeps of a 4-variable ODE: differentiated, the calls around them cost most
    grad_whole_action = True
    diagnostics = {
        "flow_amplitude": "|A|, the amplitude of the flow disturbance",
        "vibration_amplitude": "|Y|, the amplitude of the cylinder's vibration",
        "displacement": "the cylinder's displacement y at the end of the action",
    }

    @classmethod
    def sizes(cls, p) -> tuple[int, int]:
        return 8, 2

    def setup(self, p) -> None:
        self._substeps = self.kernels.loop(vortex_substep)

    def null_action(self) -> torch.Tensor:
        a = torch.zeros((self.num_envs, 2), dtype=self.dtype, device=self.device)
        a[:, 0] = -1.0
        return a

    def initial_state(self, p, generator, mask=None) -> VortexState:
        # complex128 for float64: a Python complex would become complex64 and round the
        # start to float32
        cdtype = torch.complex128 if self.dtype == torch.float64 else torch.complex64
        a0 = torch.as_tensor(p.a0, dtype=cdtype, device=self.device).expand(self.num_envs)
        y0 = torch.as_tensor(p.y0, dtype=cdtype, device=self.device).expand(self.num_envs)
        s = torch.stack((a0.real, a0.imag, y0.real, y0.imag), -1).to(self.dtype)
        zero = torch.zeros_like(s[:, 0])
        # the published reset observes zero time derivatives
        return VortexState(ay=s, rate=torch.zeros_like(s), k=zero, phi=zero.clone(), y_prev=displacement(s, zero))

    def advance(self, p, state: VortexState, action: torch.Tensor, count: torch.Tensor, noise: Noise):
        k = 0.5 * K_MAX * (action[:, 0] + 1.0)
        phi = math.pi * action[:, 1]
        s, rate = self._substeps(SUBSTEPS, (state.ay, state.rate), k, phi, p.re)
        t = DT_ACT * (count + 1).to(self.dtype)
        y = displacement(s, t)
        # The published scores divide by the numerical step (0.1), not by the 0.5
        # between the two samples of y; kept for comparability.
        energy = 2.0 * OMEGA_S * GAMMA * ((y - state.y_prev) / DT) ** 2
        c, sn = torch.cos(OMEGA_STAR * t), torch.sin(OMEGA_STAR * t)
        ar, ai = s[:, 0], s[:, 1]
        lift = 2.0 * k * torch.cos(phi) * (ar * c - ai * sn) - 2.0 * k * torch.sin(phi) * (ai * c + ar * sn)
        reward = energy - p.w * 0.5 * lift**2
        return VortexState(ay=s, rate=rate, k=k, phi=phi, y_prev=y), reward

    def diagnose(self, p, state: VortexState) -> dict[str, torch.Tensor]:
        s = state.ay
        return {
            "flow_amplitude": torch.hypot(s[:, 0], s[:, 1]),
            "vibration_amplitude": torch.hypot(s[:, 2], s[:, 3]),
            "displacement": state.y_prev,
        }

    def observe(self, p, state: VortexState) -> torch.Tensor:
        # the published "time derivatives": the last LSRK4 stage's right-hand side
        return torch.cat((state.ay, state.rate), -1)


def frame(f: FrameInputs) -> np.ndarray:
    """The cylinder's transverse position over the episode and the feedback's gain and
    phase."""
    from beacon_torch.render import vortex_frame

    ay = torch.stack([s.ay for s in f.states]).double().numpy()
    last = f.states[-1]
    return vortex_frame(ay, float(last.k), float(last.phi), t=DT_ACT * f.step)


CARD = Card(
    family="ode",
    published_speed=6_560.0,
    speed_target=20.0,
    paper_ppo=38.0,
    gradcheck=GradCheck("re", 50.0, warmup=20, steps=20),
    frame=frame,
)
