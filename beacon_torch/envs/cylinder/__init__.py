"""cylinder-v0: reduce the drag of a cylinder in a channel with two synthetic jets
(Rabault, Kuchta, Jensen, Reglade & Cerardi, J. Fluid Mech. 865, 2019), on the
geometry of the Schaefer & Turek (1996) benchmark 2D-2.

Incompressible flow past a cylinder of diameter D = 0.1 centred at (0.2, 0.2) in the
channel [0, 2.2] x [0, 0.41]:

    div u = 0
    u_t + (u.grad) u = -grad p + nu lap u + f

with nu = 1e-3 (Re = U D / nu = 100 on the mean inflow U = 1), the parabolic inflow
u(0, y) = 4 Um y (H - y) / H^2 (Um = 1.5), no-slip walls, an open outlet (p = 0, the
velocity carried out at U).

The grid is the cavities' staggered grid, stretched: square cells of D /
``cells_per_diameter`` in a box around the cylinder and its near wake, growing by 5 %
a cell outside it. The cylinder is immersed by direct forcing (:class:`ImmersedBoundary`):
after the explicit predictor, the faces inside the circle take the body's velocity and
the first fluid faces around it the value of a quadratic in the wall distance through
the wall's velocity and the flow one and two cells further out along the normal, a
boundary of second order in the cell size. The projection that follows is the
rectangle's own, so a direct Poisson solve still applies (tensor products of the 1-D
operators' eigenvectors across the channel, tridiagonal solves along it); mass is
conserved in every cell whose centre lies in the fluid, and in the body's cells
together (:meth:`Channel.continuity`). The force on the cylinder is the momentum the
forcing removes, plus the rate of change of the momentum the body's faces hold (the
jets' stream through it): the method's equivalent of the stress integrated on the
surface.

Time stepping: Adams-Bashforth 2 for advection and diffusion (the forward Euler of
the cavities is unstable at this cell Reynolds number), the incremental projection of
the cavities, dt = 5e-4 (stable up to 40 cells across the diameter: :func:`stable`),
50 steps per action, 80 actions per episode.

Control: two jets at 90 and 270 degrees, 10 degrees wide, with opposite mass flow
rates. The two actions in [-1, 1] are flow rates of at most 1e-2; as published, the
jets' rates relax each step by a tenth of the way to the action and their mean is
removed, which leaves the top jet's rate Q relaxing to (a_0 - a_1) / 2 * 1e-2 and the
bottom's at -Q. The jets' velocity on the wall is the published cosine across each jet
(:func:`wall_velocity`); inside the body their fluid crosses it as a vertical stream,
face-averaged and scaled so that the grid's faces carry exactly Q.

Observation: the pressure at the published 151 probes (bilinear in the cells).
Reward per action: -(mean drag force - 0.159) - 0.2 |mean lift force| over the action's
steps (0.159: the uncontrolled mean drag force of the published mesh). Every episode
starts from the developed uncontrolled shedding (:func:`developed_shedding`).

The package: the flow (:mod:`~beacon_torch.envs.cylinder.channel`: the grid, the body,
one time step, the developed start), its physics and env
(:mod:`~beacon_torch.envs.cylinder.env`), the benchmark's figures
(:mod:`~beacon_torch.envs.cylinder.validation`) and the validation runs:
``python -m beacon_torch.envs.cylinder.schaefer_turek`` (the benchmark 2D-2) and
``python -m beacon_torch.envs.cylinder.base_flow`` (the steady base flow). Their
names are given here too.
"""

from beacon_torch.envs.cylinder.channel import (
    CENTRE,
    DEVELOP_TIME,
    DIAMETER,
    DRAG_OFFSET,
    DT,
    EPISODE_LENGTH,
    FINE_X,
    FINE_Y,
    GROWTH,
    HEIGHT,
    JET_WIDTH,
    LENGTH,
    LIFT_PENALTY,
    N_PROBES,
    NU,
    PROBES,
    PUBLISHED_REDUCTION,
    Q_MAX,
    RADIUS,
    SMOOTHING,
    START_VERSION,
    SUBSTEPS,
    U_MAX,
    U_MEAN,
    WIDEST,
    Channel,
    Flow,
    coefficient,
    developed_shedding,
    inside,
    jet_profile,
    rest,
    run,
    step,
    wall_velocity,
)
from beacon_torch.envs.cylinder.env import CARD, CylinderParams, CylinderPhysics, CylinderState, jet_target
from beacon_torch.envs.cylinder.validation import SCHAEFER_TUREK, shedding_figures
from beacon_torch.numerics.bodies import DIFFUSION_LIMIT, ImmersedBoundary, probe_stencil, stable
from beacon_torch.numerics.staggered import Axis

__all__ = [
    "LENGTH",
    "HEIGHT",
    "CENTRE",
    "DIAMETER",
    "RADIUS",
    "NU",
    "U_MAX",
    "U_MEAN",
    "DT",
    "SUBSTEPS",
    "EPISODE_LENGTH",
    "Q_MAX",
    "SMOOTHING",
    "JET_WIDTH",
    "DRAG_OFFSET",
    "PUBLISHED_REDUCTION",
    "LIFT_PENALTY",
    "DEVELOP_TIME",
    "START_VERSION",
    "FINE_X",
    "FINE_Y",
    "GROWTH",
    "WIDEST",
    "PROBES",
    "N_PROBES",
    "Flow",
    "CylinderState",
    "CylinderParams",
    "DIFFUSION_LIMIT",
    "stable",
    "Axis",
    "Channel",
    "inside",
    "jet_profile",
    "wall_velocity",
    "ImmersedBoundary",
    "probe_stencil",
    "step",
    "rest",
    "run",
    "coefficient",
    "SCHAEFER_TUREK",
    "shedding_figures",
    "developed_shedding",
    "jet_target",
    "CylinderPhysics",
    "CARD",
]
