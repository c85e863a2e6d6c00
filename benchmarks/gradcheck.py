"""Gradients of every continuous env on its published settings against central
differences, in float64 at a generic point.

    .venv/bin/python benchmarks/gradcheck.py [--envs ENV ...]

Prints, per env, the derivative of the reward summed over a few actions with respect to
the actions (along a random direction) and to one physical parameter, by automatic
differentiation and by central differences, with their relative error. The test suite
checks the same on the published grids too, but for mixing-continuous-v0 (a smaller
cavity there); the table in docs/gradients.md comes from this script.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import beacon_torch
from beacon_torch.gradcheck import CASES, check


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", nargs="*", default=list(CASES), choices=list(CASES))
    args = parser.parse_args(argv)
    print("| env | derivative | autograd | central differences | relative error | actions (warm-up + differentiated) |")
    print("|---|---|---|---|---|---|")
    for env_id in args.envs:
        name, value, params, warmup, steps = CASES[env_id]

        def make(env_id=env_id, params=params, **kwargs):
            return beacon_torch.make(env_id, batch_size=1, dtype=torch.float64, seed=3, **params, **kwargs)

        result = check(make, name, value, warmup=warmup, steps=steps)
        for what, d in result.items():
            print(
                f"| {env_id} | {what} | {d.autograd:.10g} | {d.central:.10g} | {d.relative_error:.1e} | "
                f"{warmup} + {steps} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
