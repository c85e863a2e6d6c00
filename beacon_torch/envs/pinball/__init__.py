"""pinball-v0: the fluidic pinball, three cylinders whose rotations control the wake
(Deng, Noack, Morzynski & Pastur, J. Fluid Mech. 884, A37, 2020; Raibaudo et al.,
Phys. Fluids 32, 2020; Cornejo Maceda et al., J. Fluid Mech. 917, A42, 2021).

Incompressible flow past three cylinders of diameter D = 1 on an equilateral triangle of
side 1.5 D pointing upstream: the front one at (-3 sqrt(3) / 4, 0), the rear ones at
(0, 3/4) and (0, -3/4), in the box [-6, 20] x [-6, 6]:

    div u = 0
    u_t + (u.grad) u = -grad p + (1 / Re) lap u

with the uniform inflow U = 1 on the left, slip walls below and above (v = 0, no
shear), an open outlet (p = 0, the velocity carried out at U), and no-slip cylinders
turning at the angular velocities the actions ask for. Re = U D / nu is a parameter:
steady below about 18, periodic shedding beyond, an asymmetric (pitchfork) state beyond
about 68, quasi-periodic beyond about 104 and chaotic beyond about 115 (Deng et al.).

The numerics are the cylinder's (:mod:`beacon_torch.numerics.bodies`): the stretched
staggered grid (square cells of D / ``cells_per_diameter`` around the cylinders and
their near wake, growing by 5 % a cell outside up to 8 of them), the direct forcing of
each body with its wall's velocity (here the rotation's, tangential), Adams-Bashforth 2
and the incremental projection; dt = 5e-3, 100 steps per action (0.5 convective time
units), 100 actions per episode. Each cylinder's drag, lift and torque are what the
forcing takes from the flow around it.

Action: the three angular velocities in units of ``max_rotation`` (each step they move a
tenth of the way to the action). Observation: u and v at 35 probes in the wake.
Reward per action: minus the net drag power, the three drag coefficients' sum plus the
rotations' power coefficient (weighted by ``power_weight``).

The package: the flow (:mod:`~beacon_torch.envs.pinball.flow`: the grid, the bodies,
one time step, the developed start) and its physics and card, with the levels' parameters
(:mod:`~beacon_torch.envs.pinball.env`).
"""

from beacon_torch.envs.pinball.env import (
    CARD,
    CHAOTIC,
    CHAOTIC_CARD,
    MAX_ROTATION,
    PERIODIC,
    PERIODIC_CARD,
    PinballParams,
    PinballPhysics,
    PinballState,
)
from beacon_torch.envs.pinball.flow import (
    CYLINDERS,
    DIAMETER,
    DT,
    EPISODE_LENGTH,
    NAMES,
    PROBES,
    SUBSTEPS,
    Box,
    Flow,
    coefficient,
    developed,
    rest,
    run,
    step,
)

__all__ = [
    "CYLINDERS",
    "NAMES",
    "DIAMETER",
    "DT",
    "SUBSTEPS",
    "EPISODE_LENGTH",
    "PROBES",
    "MAX_ROTATION",
    "Box",
    "Flow",
    "rest",
    "run",
    "step",
    "coefficient",
    "developed",
    "PinballParams",
    "PinballState",
    "PinballPhysics",
    "CARD",
    "PERIODIC",
    "PERIODIC_CARD",
    "CHAOTIC",
    "CHAOTIC_CARD",
]
