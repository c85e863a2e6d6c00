"""heat-v0: hold a heated rod at a target temperature profile (a worked example env).

    T_t = kappa T_xx + P a(t) g(x)

on [0, 1] with T = 0 at both ends, a heater of Gaussian shape g around x = 0.3 and
power P a with a in [-1, 1] (cooling allowed), from a rod at rest at T = 0 with a
random hot spot. Explicit centred differences on 32 cells, 20 substeps of
dt = 0.4 dx^2 / kappa per action, 100 actions. The agent sees 4 thermometers and is
rewarded by minus the mean squared distance of the rod to T = 1 - 4 (x - 1/2)^2.

Written as a user of beacon-torch would write a new case (docs/adding-an-env.md): one
module of its state, its parameters, its physics and, as plain values, its card and its
frame, registered with ``beacon_torch.register`` and checked by the conformance kit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

import beacon_torch
from beacon_torch.core.card import Card, FrameInputs, GradCheck
from beacon_torch.core.physics import Physics
from beacon_torch.core.state import Noise
from beacon_torch.params import param

N_CELLS = 32
DX = 1.0 / N_CELLS
SUBSTEPS = 20
EPISODE_LENGTH = 100
PROBES = (4, 12, 20, 28)  # the cells the thermometers sit in


class HeatState(NamedTuple):
    """One member per row."""

    T: torch.Tensor  # [batch, N_CELLS + 2] the temperature, the two wall cells included


@dataclass(frozen=True)
class HeatParams:
    kappa: float = param(0.05, low=0.0, high=1.0, low_open=True, per_member=False, doc="diffusivity")
    power: float = param(20.0, low=0.0, high=1e8, doc="heater power at a = 1")
    # read by the start only, which is not differentiated
    spot: float = param(1.0, low=0.0, high=10.0, differentiable=False, doc="height of the random hot spot at the start")


def heat_substep(i, T: torch.Tensor, heating: torch.Tensor, kappa: float, dt: float) -> torch.Tensor:
    """Substep ``i`` of an action: one explicit Euler step of the rod ``T`` (``[B, n]``,
    the two wall cells included) under ``heating`` (``[B, n - 2]``)."""
    interior = T[:, 1:-1] + dt * (heating + kappa * (T[:, 2:] - 2.0 * T[:, 1:-1] + T[:, :-2]) / DX**2)
    return torch.nn.functional.pad(interior, (1, 1))


class HeatPhysics(Physics):
    """The heated rod: every hook takes the parameters first."""

    Params = HeatParams
    state_type = HeatState
    episode_length = EPISODE_LENGTH
    deterministic = False  # the hot spot of a start is drawn from the generator
    # a rod that overheats: every reward is at least -(T - target)^2 with T <= 1e3
    blowup_reward = -1e6

    @classmethod
    def sizes(cls, p) -> tuple[int, int]:
        return len(PROBES), 1

    def setup(self, p) -> None:
        x = (torch.arange(N_CELLS + 2, dtype=self.dtype, device=self.device) - 0.5) * DX
        self.x = x
        self.target = 1.0 - 4.0 * (x - 0.5) ** 2
        self._heater = torch.exp(-(((x[1:-1] - 0.3) / 0.05) ** 2))
        # kappa is one number for the batch (per_member=False): it fixes the time step
        self._kappa = float(p.kappa)
        self._dt = 0.4 * DX**2 / self._kappa  # within the explicit scheme's limit, 0.5
        self._substeps = self.kernels.loop(heat_substep)

    def initial_state(self, p, generator, mask=None) -> HeatState:
        where = torch.rand((self.num_envs, 1), generator=generator, dtype=self.dtype, device=self.device)
        bump = self.member(p.spot) * torch.exp(-(((self.x - where) / 0.1) ** 2))
        return HeatState(T=torch.nn.functional.pad(bump[:, 1:-1], (1, 1)))

    def advance(self, p, state: HeatState, action: torch.Tensor, count: torch.Tensor, noise: Noise):
        heating = self.member(p.power) * action * self._heater
        T = self._substeps(SUBSTEPS, state.T, heating, self._kappa, self._dt)
        reward = -((T - self.target) ** 2).mean(-1)
        return HeatState(T=T), reward

    def observe(self, p, state: HeatState) -> torch.Tensor:
        return state.T[:, list(PROBES)]

    def out_of_bounds(self, p, state: HeatState) -> torch.Tensor:
        return state.T.abs().amax(-1) > 1e3


def frame(f: FrameInputs) -> np.ndarray:
    """The rod's temperature against the target profile."""
    from beacon_torch.render import new_figure, to_rgb

    x, target = f.physics.x.cpu().numpy(), f.physics.target.cpu().numpy()
    fig = new_figure()
    ax = fig.add_axes((0.1, 0.14, 0.85, 0.74))
    ax.plot(x, target, color="#555555", lw=0.6, ls="--")
    ax.plot(x, f.states[-1].T.double().numpy(), color="#d62728")
    ax.set_ylim(-0.5, 2.0)
    ax.set_xlabel("x")
    ax.set_ylabel("T")
    ax.set_title(f"heat   action {f.step}", fontsize=10)
    return to_rgb(fig)


CARD = Card(family="1-D", gradcheck=GradCheck("power", 20.0, warmup=5, steps=3), frame=frame)

beacon_torch.register("heat-v0", HeatPhysics, CARD)
