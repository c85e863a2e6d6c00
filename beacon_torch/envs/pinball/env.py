"""pinball-v0 as an env: its parameters, its state, the rotations' action and the
reward (the case: :mod:`beacon_torch.envs.pinball`)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from beacon_torch.cache import cached
from beacon_torch.core.card import PUBLISHED_RESULT, Card, FrameInputs, GradCheck, Reference
from beacon_torch.core.physics import Physics
from beacon_torch.core.state import Noise, map_state
from beacon_torch.envs.pinball.flow import (
    CYLINDERS,
    DIAMETER,
    DT,
    EPISODE_LENGTH,
    N_PROBES,
    SUBSTEPS,
    U_INF,
    Box,
    Flow,
    coefficient,
    developed,
    resolution_error,
    rest,
    run,
    step,
)
from beacon_torch.numerics.bodies import DIFFUSION_LIMIT, stable
from beacon_torch.params import number, param

# the developed starts' generation: a new one whenever the scheme changes the flow
START_VERSION = 1
# time units from the free stream to the developed flow, and the front cylinder's
# kick in the first of them that breaks the mirror symmetry
DEVELOP_TIME = 400.0
KICK = 0.5
# the largest rotation rate, in U / D (HydroGym's pinball bound, pi / 2)
MAX_ROTATION = 0.5 * math.pi


def developed_start(cells: int, re: float, device: str | torch.device = "cpu", dtype=torch.float64) -> Flow:
    """The levels' start at ``re`` on a grid of ``cells`` per diameter: the developed
    uncontrolled flow (without batch dimension; float64 on the CPU unless told),
    shipped, cached or computed once."""
    key = dict(cells=cells, re=re, time=DEVELOP_TIME, kick=KICK)
    like = map_state(lambda v: v[0], rest(1, Box(cells, dtype=torch.float64, device="cpu"), torch.float64, "cpu"))
    compute = lambda: developed(cells, 1.0 / re, time=DEVELOP_TIME, kick=KICK)[0]
    # what out_of_bounds ends an episode beyond
    bounds = {"u": (-10.0 * U_INF, 10.0 * U_INF)}
    return cached("pinball-developed", START_VERSION, key, compute, like, bounds, device=device, dtype=dtype)


class PinballState(NamedTuple):
    """The flow and the cylinders' loads averaged over the last action."""

    u: torch.Tensor  # [batch, nx + 1, ny]
    v: torch.Tensor  # [batch, nx, ny + 1]
    p: torch.Tensor  # [batch, nx, ny]
    hu: torch.Tensor  # [batch, nx, ny]
    hv: torch.Tensor  # [batch, nx, ny - 1]
    omega: torch.Tensor  # [batch, 3] the cylinders' angular velocities
    drag: torch.Tensor  # [batch, 3] the mean drag force of each cylinder over the last action
    lift: torch.Tensor  # [batch, 3]
    torque: torch.Tensor  # [batch, 3] the fluid's torque on each cylinder


def re_param(default: float):
    doc = (
        "Reynolds number U D / nu (Deng et al.: steady below about 18, then shedding, asymmetric beyond about 68, "
        "quasi-periodic beyond 104, chaotic beyond 115)"
    )
    return param(default, low=10.0, high=200.0, per_member=False, differentiable=True, doc=doc)


@dataclass(frozen=True)
class PinballParams:
    re: float = re_param(30.0)
    cells_per_diameter: int = param(
        20,
        low=10,
        high=40,
        kind="int",
        per_member=False,
        doc="grid cells across a cylinder's diameter, even (finer grids need a higher Re at the env's time step)",
    )
    max_rotation: float = param(
        MAX_ROTATION, low=0.0, high=20.0, per_member=False, doc="the largest angular velocity, in U / D"
    )
    power_weight: float = param(
        1.0,
        low=0.0,
        high=100.0,
        doc="weight of the rotations' power in the reward (1: the net drag power, 0: the drag alone)",
    )

    def __post_init__(self):
        cells, re = int(self.cells_per_diameter), number(self.re)
        error = resolution_error(cells)
        if error:
            raise ValueError(error)
        h = DIAMETER / cells
        if not stable(h, 1.0 / re, DT):
            raise ValueError(
                f"parameters 're' = {re:g} and 'cells_per_diameter' = {cells}: the explicit diffusion is unstable "
                f"at dt = {DT:g} (8 nu dt / h^2 = {8 * DT / (re * h * h):.2f} must stay below {DIFFUSION_LIMIT}); "
                "take fewer cells or a higher Re"
            )


class PinballPhysics(Physics):
    """The flow past three rotating cylinders (3 continuous actions: their angular
    velocities)."""

    members_innermost = True

    Params = PinballParams
    state_type = PinballState
    episode_length = EPISODE_LENGTH
    substeps = SUBSTEPS
    # a completed action's reward is above minus the drag and power coefficients of any
    # flow the scheme keeps stable; a blow-up ends below them all
    blowup_reward = -100.0
    diagnostics = {
        "drag": "sum of the three cylinders' drag coefficients, averaged over the action",
        "lift": "sum of the three cylinders' lift coefficients",
        "power": "the rotations' power coefficient, 2 P / (rho U^3 D) (positive: spent on the flow)",
        "drag_front": "the front cylinder's drag coefficient",
        "drag_top": "the top cylinder's drag coefficient",
        "drag_bottom": "the bottom cylinder's drag coefficient",
        "omega_front": "the front cylinder's angular velocity at the action's end, in U / D (anticlockwise positive)",
        "omega_top": "the top cylinder's angular velocity at the action's end, in U / D",
        "omega_bottom": "the bottom cylinder's angular velocity at the action's end, in U / D",
    }

    @classmethod
    def sizes(cls, p) -> tuple[int, int]:
        return 2 * N_PROBES, 3

    def member_floats(self) -> int:
        # u, v, p, the two tendencies, and the step's work on as many again
        return 10 * (self.box.nx + 1) * (self.box.ny + 1)

    def setup(self, p) -> None:
        self.box = Box(int(p.cells_per_diameter), dtype=self.dtype, device=self.device)
        # what the speed benchmark of the 2-D envs reads
        self.nx, self.ny, self.solver = self.box.nx, self.box.ny, self.box
        self._steps = self.kernels.loop(step)

    def _start(self, p) -> Flow:
        # loaded at the first reset: an env started by set_state never develops its flow.
        # One start per thousandth of Re: a derivative's neighbouring Re (a relative
        # step of 1e-6) starts from the same developed flow rather than computing two
        cells, re = int(p.cells_per_diameter), round(number(p.re), 3)
        return developed_start(cells, re, self.device, self.dtype)

    def _start_loads(self, p) -> torch.Tensor:
        """The cylinders' loads in the start's flow, over one time step of it without
        rotation (``[1, 3, 3]``: drag, lift, torque of each cylinder; what the
        diagnostics report before the first action, the flow itself starting
        unchanged)."""
        cells, re = int(p.cells_per_diameter), round(number(p.re), 3)

        def loads():
            flow = Flow(*(f[None] for f in self._start(p)))
            with torch.no_grad():
                return run(flow, 1, flow.omega.new_zeros(1, 3), self.box, 1.0 / re, DT)[1]

        return self.remembered(("start loads", cells, re), loads)

    def state_like(self, p) -> PinballState:
        flow = rest(self.num_envs, self.box, self.dtype, self.device)
        return PinballState(*flow, drag=flow.omega, lift=flow.omega, torque=flow.omega)

    def initial_state(self, p, generator, mask=None) -> PinballState:
        flow = Flow(*(f.expand(self.num_envs, *f.shape).clone() for f in self._start(p)))
        drag, lift, torque = (f.expand(self.num_envs, 3).clone() for f in self._start_loads(p).unbind(1))
        return PinballState(*flow, drag=drag, lift=lift, torque=torque)

    def advance(self, p, state: PinballState, action: torch.Tensor, count: torch.Tensor, noise: Noise):
        flow = Flow(*state[: len(Flow._fields)])
        target = p.max_rotation * action
        # nu [B]: the batch is the steps' last axis
        flow, loads = run(flow, SUBSTEPS, target, self.box, 1.0 / p.re, DT, self._steps)
        drag, lift, torque = loads.unbind(1)  # each [B, 3]
        next_state = PinballState(*flow, drag=drag, lift=lift, torque=torque)
        reward = -(coefficient(drag).sum(-1) + p.power_weight * self.power(next_state))
        return next_state, reward

    @staticmethod
    def power(state: PinballState) -> torch.Tensor:
        """The rotations' power coefficient ``[B]``: the power the cylinders spend
        turning against the fluid's torque, 2 P / (rho U^3 D)."""
        return 2.0 * (-state.torque * state.omega).sum(-1) / (U_INF**3 * DIAMETER)

    def diagnose(self, p, state: PinballState) -> dict[str, torch.Tensor]:
        drag = coefficient(state.drag)
        return {
            "drag": drag.sum(-1),
            "lift": coefficient(state.lift).sum(-1),
            "power": self.power(state),
            "drag_front": drag[:, 0],
            "drag_top": drag[:, 1],
            "drag_bottom": drag[:, 2],
            "omega_front": state.omega[:, 0],
            "omega_top": state.omega[:, 1],
            "omega_bottom": state.omega[:, 2],
        }

    def observe(self, p, state: PinballState) -> torch.Tensor:
        return self.box.velocity_probes(state.u, state.v)

    def out_of_bounds(self, p, state: PinballState) -> torch.Tensor:
        # a flow faster than ten times the free stream has left the scheme's stable range
        return state.u.abs().flatten(1).amax(1) > 10.0 * U_INF


def frame(f: FrameInputs) -> np.ndarray:
    """The vorticity around the cylinders, their rotations and the drag."""
    from matplotlib.patches import Circle, FancyArrowPatch

    from beacon_torch.render import action_bars, new_figure, to_rgb

    last, b = f.states[-1], f.physics.box
    x, y, vorticity = b.vorticity(last.u, last.v)
    fig = new_figure(size=(8.6, 3.2))
    ax = fig.add_axes((0.05, 0.14, 0.62, 0.74))
    field = ax.pcolormesh(x, y, vorticity.T, cmap="RdBu_r", vmin=-3, vmax=3, shading="nearest")
    omega = last.omega.double().numpy()
    for c, w in zip(CYLINDERS, omega, strict=True):
        ax.add_patch(Circle((c.x, c.y), c.radius, color="0.3"))
        if abs(w) > 1e-3:
            # an arc around the cylinder, its arrow in the sense of rotation
            start, end = (c.x + 0.62, c.y), (c.x, c.y + 0.62 * np.sign(w))
            arc = f"arc3,rad={0.4 * np.sign(w)}"
            style = dict(arrowstyle="-|>", mutation_scale=9, lw=1.6, color="gold")
            ax.add_patch(FancyArrowPatch(start, end, connectionstyle=arc, **style))
    ax.set_xlim(-3.0, 9.0)
    ax.set_ylim(-3.0, 3.0)
    ax.set_aspect("equal")
    ax.tick_params(labelsize=7)
    fig.colorbar(field, cax=fig.add_axes((0.685, 0.2, 0.012, 0.62)), label="vorticity")
    t = DT * SUBSTEPS * f.step
    drag = float(coefficient(last.drag).sum())
    re = float(f.params.re)
    ax.set_title(f"fluidic pinball   Re = {re:g}   t = {t:.1f}   sum C_D = {drag:.3f}", fontsize=9)
    bars = fig.add_axes((0.79, 0.2, 0.19, 0.6))
    bound = float(f.params.max_rotation) or 1.0
    action_bars(bars, list(omega / bound), ["front", "top", "bottom"], [(-1.0, 1.0)] * 3)
    bars.set_title("rotation / bound", fontsize=8)
    return to_rgb(fig)


CARD = Card(
    family="2-D",
    costly=True,  # an action is 100 substeps of the 2-D flow
    gradcheck=GradCheck("re", 30.0, warmup=1, steps=1),
    test_settings={"cells_per_diameter": 10},
    frame=frame,
)

# pinball-periodic-v0: Re 100, periodic shedding past the pitchfork (asymmetric)
PERIODIC = {"re": 100.0}
PERIODIC_CARD = dataclasses.replace(
    CARD,
    # the reward is minus the net drag power's coefficients, so their saving is the score's
    reference=Reference(
        PUBLISHED_RESULT,
        "Li et al., J. Fluid Mech. 932 (2022), Re 100: the net drag power 29 % below no control",
        ratio=0.71,
    ),
    gradcheck=GradCheck("re", 100.0, warmup=1, steps=1),
)
# pinball-chaotic-v0: Re 130, chaotic (HydroGym's chaotic pinball)
CHAOTIC = {"re": 130.0}
CHAOTIC_CARD = dataclasses.replace(CARD, gradcheck=GradCheck("re", 130.0, warmup=1, steps=1))
