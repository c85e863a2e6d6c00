"""Speed of the 2-D envs: one full uncontrolled episode of a batch of cavities (or of
cylinder wakes).

    .venv/bin/python benchmarks/cavity_speed.py [--batch 16] [--dtype float32] [--compile] [--envs ...] [--out FILE]

Prints transitions per second per env (and the factor over the published code's
single-environment speed on this kind of machine: rayleigh 13.8/s, mixing 3.7/s; none
for the cylinder, whose published solver is not run here), and a breakdown of one
substep: the direct Poisson solve against the rest of the scheme. ``--envs`` takes ids
as ``make`` does (``beacon_torch.envs.cylinder:cylinder-v0``).
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import torch

import beacon_torch
from beacon_torch import episodes
from beacon_torch.files import create_file, refuse_existing
from beacon_torch.registry import ENVS, base_envs

CAVITIES = [env_id for env_id in base_envs() if ENVS[env_id].card.family == "2-D"]


def substep_breakdown(env, repeats: int = 50) -> dict:
    """Milliseconds per batched substep: the Poisson solve alone, and the whole substep."""
    rhs = torch.randn((env.nx, env.ny, env.num_envs), dtype=env.dtype, device=env.device)  # batch last
    env.physics.solver.solve(rhs)
    start = time.perf_counter()
    for _ in range(repeats):
        env.physics.solver.solve(rhs)
    poisson = (time.perf_counter() - start) / repeats
    return {"poisson_ms": 1e3 * poisson}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--dtype", default="float32")
    parser.add_argument(
        "--compile", action="store_true", help="the compiled path (make(..., compile=True)); compilation is timed apart"
    )
    parser.add_argument("--envs", nargs="+", default=CAVITIES)
    parser.add_argument("--out", help="write the results as JSON")
    args = parser.parse_args()
    if args.out:
        refuse_existing([args.out], "give another --out")  # before the measurement, not after
    results = {
        "machine": f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} "
        f"threads, torch {torch.__version__}"
    }
    for env_id in args.envs:
        env = beacon_torch.make(env_id, args.batch, dtype=args.dtype, compile=args.compile)
        substeps, published = env.physics.substeps, env.card.published_speed
        compile_s = 0.0
        if args.compile:  # compile on a throw-away step, outside the timed episode
            start = time.perf_counter()
            env.reset()
            env.step(env.reset().set("action", env.null_action()))
            compile_s = time.perf_counter() - start
        start = time.perf_counter()
        rollout = episodes.episode(env, episodes.null_policy(env))
        elapsed = time.perf_counter() - start
        rate = rollout.numel() / elapsed
        row = {
            "batch": args.batch,
            "dtype": args.dtype,
            "compiled": args.compile,
            "compile_s": compile_s,
            "episode_s": elapsed,
            "transitions_per_s": rate,
            "vs_published": rate / published if published is not None else None,
            "substep_ms": 1e3 * elapsed / (env.episode_length * substeps),
            **substep_breakdown(env),
        }
        results[env_id] = row
        against = f"{row['vs_published']:.1f}x the published {published}/s" if row["vs_published"] else "no published"
        print(
            f"{env_id} ({'compiled' if args.compile else 'eager'}): {rate:.1f} transitions/s ({against}), "
            f"episode {elapsed:.1f} s after {compile_s:.1f} s compiling, "
            f"{row['substep_ms']:.2f} ms per batched substep of which Poisson {row['poisson_ms']:.2f} ms"
        )
    if args.out:
        text = json.dumps(results, indent=2)
        create_file(args.out, lambda tmp: tmp.write_text(text), "give another --out")


if __name__ == "__main__":
    main()
