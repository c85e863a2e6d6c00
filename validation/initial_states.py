"""Regenerate the initial states that ship with the package and check them.

    .venv/bin/python validation/initial_states.py [--write] [shkadov] [rayleigh]

shkadov: the film developed for 200 time units (default delta), about 50 s here;
rayleigh: the convection roll developed for 200 time units, about 20 s; cylinder and
cylinder-coarse: the wake shedding 8 time units after the inflow starts, at the default
40 cells per diameter (about 70 s) and at the tests' 10; rbc2d-easy, -medium, -hard:
the banks of ten initial domains, 283 time units each (compiled: 1 to 10 minutes a
bank), and their -validation and -test banks. Without --write,
compares the regenerated states with the shipped ones.
"""

from __future__ import annotations

import argparse
import time

import torch

from beacon_torch import cache
from beacon_torch.envs import cylinder, rayleigh, rbc2d, shkadov

STATES = {
    "shkadov": ("shkadov-film", shkadov.START_VERSION, dict(delta=0.1), lambda: shkadov.developed_film(0.1)),
    "rayleigh": (
        "rayleigh-convection",
        rayleigh.START_VERSION,
        dict(L=1.0, H=1.0, ra=1e4),
        lambda: rayleigh.developed_convection(rayleigh.RayleighParams()),
    ),
    **{
        name: (
            "cylinder-shedding",
            cylinder.START_VERSION,
            dict(cells=cells, nu=cylinder.NU, time=cylinder.DEVELOP_TIME),
            lambda cells=cells: cylinder.developed_shedding(cells)[0],
        )
        for name, cells in (("cylinder", 40), ("cylinder-coarse", 10))
    },
    **{
        f"rbc2d-{level}" + ("" if domains == "train" else f"-{domains}"): (
            "rbc2d-developed",
            rbc2d.START_VERSION,
            rbc2d.start_key(rbc2d.Rbc2dParams(**settings, domains=domains)),
            lambda settings=settings, domains=domains: rbc2d.developed_bank(
                rbc2d.Rbc2dParams(**settings, domains=domains), compile=True
            ),
        )
        for level, settings in rbc2d.LEVELS.items()
        for domains in rbc2d.BANK_SEEDS
    },
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--write", action="store_true", help="write the states into beacon_torch/data")
    parser.add_argument("names", nargs="*", default=sorted(STATES), choices=sorted(STATES))
    args = parser.parse_args()
    for name in args.names:
        file, version, key, generate = STATES[name]
        start = time.perf_counter()
        state = generate()
        print(f"{name}: generated in {time.perf_counter() - start:.1f} s")
        path = cache.PACKAGE_DATA / cache.file_name(file, version, key)
        if args.write:
            cache.save(state, path)
            print(f"  wrote {path}")
        elif path.is_file():
            shipped = torch.load(path, weights_only=True)
            diff = max((state[k] - shipped[k]).abs().max().item() for k in state)
            print(f"  max difference from the shipped state: {diff:.3e}")


if __name__ == "__main__":
    main()
