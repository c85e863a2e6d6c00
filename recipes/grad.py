"""Gradient-based control: a deterministic policy trained by backpropagating the rewards
through the physics (short-horizon analytic policy gradients), the critic-less setting of
the short-horizon actor-critic (``recipes/shac.py``, whose loop this is).

The batched env runs with ``differentiable=True``. Each update steps the policy through
``horizon`` actions of every member, sums the discounted rewards (a member's sum
restarting with its next episode), and follows their exact gradient with respect to the
policy's weights (through the observation normalisation, the actions and every substep
of the solver); the graph is then cut at the current state and the episodes go on. No
critic, no sampling noise: what a simulator that is torch buys.

    python recipes/grad.py --env burgers-v0
    python recipes/grad.py --env vortex-v0 --horizon 100 --lr 3e-4

Its settings are the actor-critic's, env by env, without the critic and with the
squash's margin (``GradConfig``).
"""

from __future__ import annotations

from pathlib import Path

from beacon_torch.arguments import load_script
from beacon_torch.training.config import GradConfig, script

# the loop is the short-horizon actor-critic's, read from its script beside this one
# (the recipes are scripts, not a package)
main = load_script(Path(__file__).with_name("shac.py"), "recipe_shac").main

if __name__ == "__main__":
    script(main, GradConfig)
