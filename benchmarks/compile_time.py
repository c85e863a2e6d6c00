"""Compile time: the first step of a new process after ``make(..., compile=True)``.

    .venv/bin/python benchmarks/compile_time.py [--envs ...] [--batch 1] [--out DIR]

For every env, two fresh processes share a new, empty torch compile cache
(``TORCHINDUCTOR_CACHE_DIR``): the first compiles cold, the second finds the cache warm.
Each times ``make``, ``reset`` and the first step (what a user waits for), then one
more step (which must not compile again). Prints a markdown table and writes
``compile_time.json`` to ``--out``. The numbers in benchmarks/RESULTS.md come from this
script, run on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile

from beacon_torch.bench import PUBLISHED, machine, save_rows

ENVS = list(PUBLISHED)

# run in the child: prints the seconds of the first step and of the second
_CHILD = """
import sys, time, torch
torch.set_num_threads(1)
import beacon_torch
start = time.perf_counter()
env = beacon_torch.make(sys.argv[1], int(sys.argv[2]), compile=True, seed=0)
env.reset_members()
g = torch.Generator().manual_seed(0)
env.step_members(env.random_action(g))
first = time.perf_counter() - start
start = time.perf_counter()
env.step_members(env.random_action(g))
print(first, time.perf_counter() - start)
"""


def first_steps(env_id: str, batch: int, cache: str) -> tuple[float, float]:
    env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": cache}
    out = subprocess.run([sys.executable, "-c", _CHILD, env_id, str(batch)], env=env, capture_output=True, text=True, check=True)
    first, second = out.stdout.split()[-2:]
    return float(first), float(second)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", default=ENVS)
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--out", default="runs/compile_time")
    args = parser.parse_args()
    print(f"# {machine()}, batch {args.batch}, float32")
    print("| env | first step, cold cache (s) | first step, warm cache (s) | second step (s) |")
    print("|---|---|---|---|")
    rows = []
    for env_id in args.envs:
        with tempfile.TemporaryDirectory(prefix="beacon-compile-") as cache:
            cold, _ = first_steps(env_id, args.batch, cache)
            warm, second = first_steps(env_id, args.batch, cache)
        rows.append({"env": env_id, "batch": args.batch, "cold_s": cold, "warm_s": warm, "second_step_s": second})
        print(f"| {env_id} | {cold:.1f} | {warm:.1f} | {second:.3f} |", flush=True)
    print("results:", save_rows(rows, args.out, "compile_time"))


if __name__ == "__main__":
    main()
