"""Compile time: the first step of a new process after ``make(..., compile=True)``.

    .venv/bin/python benchmarks/compile_time.py [--envs ...] [--batch 1] [--out DIR]

For every env, two fresh processes share a new, empty torch compile cache
(``TORCHINDUCTOR_CACHE_DIR``): the first compiles cold, the second finds the cache warm.
Each times ``make``, ``reset`` and the first step (what a user waits for), then one
more step (which must not compile again), and counts the graphs torch found in its
cache, compiled anew, or could not cache. Prints a markdown table and writes
a new ``compile_time-DATE-TIME.json`` to ``--out``. The numbers in benchmarks/RESULTS.md come from this
script, run on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

from beacon_torch.files import machine, save_rows
from beacon_torch.registry import base_envs

ENVS = base_envs()

# run in the child: prints the seconds of the first step and of the second
_CHILD = """
import json, sys, time, torch
from torch._dynamo.utils import counters
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
second = time.perf_counter() - start
graphs = {k: counters["inductor"]["fxgraph_cache_" + k] for k in ("hit", "miss", "bypass")}
print(json.dumps({"first": first, "second": second, **graphs}))
"""


def first_steps(env_id: str, batch: int, cache: str) -> dict:
    """The child's seconds of the first and second steps, and its graph counts."""
    env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": cache}
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, env_id, str(batch)], env=env, capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", default=ENVS)
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--out", default="runs/compile_time")
    args = parser.parse_args()
    print(f"# {machine()}, batch {args.batch}, float32")
    print(
        "| env | first step, cold cache (s) | first step, warm cache (s) | second step (s) | warm: "
        "graphs from the cache / compiled / not cacheable |"
    )
    print("|---|---|---|---|---|")
    rows = []
    for env_id in args.envs:
        with tempfile.TemporaryDirectory(prefix="beacon-compile-") as cache:
            cold = first_steps(env_id, args.batch, cache)
            warm = first_steps(env_id, args.batch, cache)
        graphs = {f"warm_graphs_{k}": warm[k] for k in ("hit", "miss", "bypass")}
        rows.append(
            {
                "env": env_id,
                "batch": args.batch,
                "cold_s": cold["first"],
                "warm_s": warm["first"],
                "second_step_s": warm["second"],
                **graphs,
            }
        )
        print(
            f"| {env_id} | {cold['first']:.1f} | {warm['first']:.1f} | {warm['second']:.3f} | "
            f"{warm['hit']} / {warm['miss']} / {warm['bypass']} |",
            flush=True,
        )
    print("results:", save_rows(rows, args.out, "compile_time"))


if __name__ == "__main__":
    main()
