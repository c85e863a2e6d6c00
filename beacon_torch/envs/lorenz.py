"""lorenz-v0: keep the Lorenz attractor in the x < 0 lobe (Beintema et al. 2020).

    dx/dt = sigma (y - x)
    dy/dt = x (rho - z) - y + u
    dz/dt = x y - beta z

One low-storage RK4 step of dt = 0.05 per action, 500 actions, start (10, 10, 10).
The observation is the state and, as published, the right-hand side of the last
LSRK4 stage (zeros at reset).
The forcing u is -1, 0 or +1 (discrete actions 0, 1, 2) in ``lorenz-v0`` and any value in
[-1, 1] in ``lorenz-continuous-v0``. Reward +1 for each step that ends with x < 0.

That indicator has no gradient; for gradient-based control ``reward_width`` > 0 replaces
it with the logistic step sigmoid(-x / reward_width), which tends to it as the width
goes to 0 (the published scores use the indicator, the default). With
``reward_value="indicator"`` the reward keeps the indicator's value and only its
gradient is the logistic step's (straight-through): a policy trained by gradient is then
scored, logged and evaluated on the published reward.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from beacon_torch.core.card import Card, FrameInputs, GradCheck
from beacon_torch.core.physics import Physics
from beacon_torch.core.state import Noise
from beacon_torch.numerics import lsrk4_step
from beacon_torch.params import param

DT = 0.05
EPISODE_LENGTH = 500
START = (10.0, 10.0, 10.0)


class LorenzState(NamedTuple):
    """One member per row."""

    xyz: torch.Tensor  # [batch, 3] the position (x, y, z)
    rate: torch.Tensor  # [batch, 3] the right-hand side of the last LSRK4 stage
    u: torch.Tensor  # [batch] the forcing of the last action


@dataclass(frozen=True)
class LorenzParams:
    sigma: float = param(10.0, low=0.0, high=1e3, low_open=True, doc="Prandtl-like ratio")
    rho: float = param(28.0, low=0.0, high=1e6, low_open=True, doc="Rayleigh-number ratio")
    beta: float = param(8.0 / 3.0, low=0.0, high=1e3, low_open=True, doc="geometric factor")
    reward_width: float = param(
        0.0, low=0.0, high=1e3, doc="width of a smooth step replacing the reward's indicator x < 0 (0: the indicator)"
    )
    reward_value: str = param(
        "smooth",
        kind="choice",
        choices=("smooth", "indicator"),
        doc="with reward_width > 0, the reward's value: the smooth step's, or the indicator's with its gradient",
    )


def lorenz_rhs(xyz: torch.Tensor, u: torch.Tensor, p: LorenzParams) -> torch.Tensor:
    """Time derivative of the forced Lorenz system; ``xyz`` is ``[B, 3]``, ``u`` ``[B]``."""
    x, y, z = xyz.unbind(-1)
    return torch.stack((p.sigma * (y - x), x * (p.rho - z) - y + u, x * y - p.beta * z), -1)


def lorenz_step(xyz: torch.Tensor, u: torch.Tensor, p: LorenzParams) -> tuple[torch.Tensor, torch.Tensor]:
    """One action: one LSRK4 step of dt = 0.05 with the forcing ``u`` ``[B]``; returns
    the new state and the right-hand side of the step's last stage."""
    return lsrk4_step(lambda s, t: lorenz_rhs(s, u, p), xyz, 0.0, DT)


class LorenzPhysics(Physics):
    """The forced Lorenz system with discrete forcing in {-1, 0, +1}."""

    Params = LorenzParams
    state_type = LorenzState
    episode_length = EPISODE_LENGTH
    discrete = True
    # a 3-variable ODE: differentiated, the calls around its integration cost most
    grad_whole_action = True
    diagnostics = {"x": "the state's x (the reward counts x < 0)", "y": "the state's y", "z": "the state's z"}

    @classmethod
    def sizes(cls, p) -> tuple[int, int]:
        return 6, 3  # push down, none, up

    def setup(self, p) -> None:
        self._lorenz = self.kernels(lorenz_step)

    def forcing(self, action: torch.Tensor) -> torch.Tensor:
        return (action - 1).to(self.dtype)

    def null_action(self) -> torch.Tensor:
        return torch.ones(self.batch_size, dtype=torch.int64, device=self.device)

    def initial_state(self, p, generator, mask=None) -> LorenzState:
        xyz = self.tensor(START).expand(self.num_envs, 3).clone()
        # the published reset observes zero time derivatives
        return LorenzState(xyz=xyz, rate=torch.zeros_like(xyz), u=torch.zeros_like(xyz[:, 0]))

    def advance(self, p, state: LorenzState, action: torch.Tensor, count: torch.Tensor, noise: Noise):
        u = self.forcing(action)
        xyz, rate = self._lorenz(state.xyz, u, p)
        reward = self.reward(p, xyz[:, 0])
        return LorenzState(xyz=xyz, rate=rate, u=u), reward

    def reward(self, p, x: torch.Tensor) -> torch.Tensor:
        width = p.reward_width
        step = (x < 0).to(self.dtype)
        smooth = torch.sigmoid(-x / width.clamp(min=1e-30))
        if p.reward_value == "indicator":
            # s - s is exactly 0 for a finite s: the indicator's value, the step's gradient
            smooth = step + (smooth - smooth.detach())
        # a width of 0 keeps the indicator
        return torch.where(width > 0, smooth, step)

    def diagnose(self, p, state: LorenzState) -> dict[str, torch.Tensor]:
        x, y, z = state.xyz.unbind(-1)
        return {"x": x, "y": y, "z": z}

    def observe(self, p, state: LorenzState) -> torch.Tensor:
        # the "time derivatives" are those of the published code: the right-hand side
        # of the last LSRK4 stage, not the one at the new state
        return torch.cat((state.xyz, state.rate), -1)


class LorenzContinuousPhysics(LorenzPhysics):
    """The same system with a forcing u = action in [-1, 1]."""

    discrete = False

    @classmethod
    def sizes(cls, p) -> tuple[int, int]:
        return 6, 1

    def forcing(self, action: torch.Tensor) -> torch.Tensor:
        return action[:, 0]

    # zero forcing (the discrete env's "no control" is its action 1)
    null_action = Physics.null_action


def frame(f: FrameInputs) -> np.ndarray:
    """The trajectory of a member's episode so far, and its forcing."""
    from beacon_torch.render import lorenz_frame

    xyz = torch.stack([s.xyz for s in f.states]).double().numpy()
    return lorenz_frame(xyz, float(f.states[-1].u), t=DT * f.step)


CARD = Card(family="ode", published_speed=62_300.0, speed_target=20.0, paper_ppo=400.0, frame=frame)
# the indicator reward has no gradient: its smooth version (docs/gradients.md)
CONTINUOUS_CARD = dataclasses.replace(
    CARD, gradcheck=GradCheck("rho", 28.0, warmup=10, steps=20, params={"reward_width": 1.0})
)
