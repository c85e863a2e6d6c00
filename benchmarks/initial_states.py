"""Regenerate the initial states that ship with the package and check them.

    .venv/bin/python benchmarks/initial_states.py [--write]

shkadov: the film developed for 200 time units (default delta); sloshing: the excited
tank. Without --write, compares the regenerated states with the shipped/cached ones.
"""

from __future__ import annotations

import argparse
import time

import torch

from beacon_torch import cache
from beacon_torch.envs import shkadov


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--write", action="store_true", help="write the states into beacon_torch/data")
    args = parser.parse_args()

    key = dict(version=1, delta=0.1)
    start = time.perf_counter()
    film = shkadov.developed_film(0.1)
    print(f"shkadov film: {time.perf_counter() - start:.1f} s, h in [{film['h'].min():.4f}, {film['h'].max():.4f}]")
    path = cache.PACKAGE_DATA / cache.file_name("shkadov-film", key)
    if args.write:
        cache.save(film, path)
        print(f"wrote {path}")
    elif path.is_file():
        shipped = torch.load(path, weights_only=True)
        diff = max((film[k] - shipped[k]).abs().max().item() for k in film)
        print(f"max difference from the shipped film: {diff:.3e}")


if __name__ == "__main__":
    main()
