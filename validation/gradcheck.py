"""Gradients of every continuous env on its published settings against central
differences, in float64 at a generic point.

    .venv/bin/python validation/gradcheck.py [--envs ENV ...]

Prints, per env, the derivative of the reward summed over a few actions with respect to
the actions (along a random direction) and to one physical parameter, by automatic
differentiation and by central differences, with their relative error. Each env
declares its check (``gradcheck`` on its class); the test suite runs the same checks on
the envs' cheaper test settings, and the table in docs/gradients.md comes from this
script.
"""

from __future__ import annotations

import argparse

from beacon_torch.gradcheck import check_env
from beacon_torch.registry import ENVS

CHECKED = [env_id for env_id, cls in ENVS.items() if cls.card.gradcheck is not None]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", nargs="*", default=CHECKED, choices=CHECKED)
    args = parser.parse_args(argv)
    print("| env | derivative | autograd | central differences | relative error | actions (warm-up + differentiated) |")
    print("|---|---|---|---|---|---|")
    for env_id in args.envs:
        case = ENVS[env_id].card.gradcheck
        result = check_env(env_id)
        for what, d in result.items():
            print(
                f"| {env_id} | {what} | {d.autograd:.10g} | {d.central:.10g} | {d.relative_error:.1e} | "
                f"{case.warmup} + {case.steps} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
