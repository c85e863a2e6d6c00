"""Two versions of the package side by side: the CPU time of one step, every env.

    .venv/bin/python benchmarks/revisions.py BEFORE AFTER [--envs ...] [--batches 1 16]
        [--rounds 3] [--seconds 1.0] [--out DIR]

``BEFORE`` and ``AFTER`` are source trees of the package (two clones or worktrees of
two commits). Each round runs one process per tree, the trees alternating in order
from round to round, on one thread; each process makes every env at every batch size
(seed 0, float32) and times ``step_members`` with random actions (fixed seed), eagerly
and, for the envs whose actions are cheap, compiled (what the adapters and the recipes
run), after warm-up steps (compilation included there). The time is the process's CPU
time, so that another process on the machine weighs less; run it on an idle machine
all the same. A step's time is the median over the rounds; the table gives both and
their ratio. Writes a new ``revisions-DATE-TIME.json`` (machine, trees, every round's
numbers) to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve()


def worker(envs: list[str], batches: list[int], seconds: float) -> None:
    """Time the steps of every env in this process's tree; one JSON line per case."""
    import torch

    import beacon_torch
    from beacon_torch.registry import env_class

    torch.set_num_threads(1)
    for env_id in envs:
        costly = env_class(env_id).costly
        for mode in ["eager"] if costly else ["eager", "compiled"]:
            for batch in batches:
                env = beacon_torch.make(env_id, batch, seed=0, compile=mode == "compiled")
                env.reset()
                gen = torch.Generator().manual_seed(2)
                # warm-up: compilation, caches; an action of seconds is timed twice a block
                warm = timed(env, 1 if costly else 3, torch.Generator().manual_seed(1))
                n = 2 if costly else max(2, min(env.episode_length // 2, int(seconds / max(warm / 3, 1e-6))))
                times = [timed(env, n, gen) / n for _ in range(3)]
                case = dict(env=env_id, mode=mode, batch=batch, steps=3 * n, cpu_s=statistics.median(times))
                print(json.dumps(case), flush=True)


def timed(env, n: int, gen) -> float:
    """The CPU time of ``n`` steps of random actions (a continuous action at half
    amplitude), in one episode (reset before, untimed, where it would end)."""
    if int(env.step_count.max()) + n > env.episode_length:
        env.reset()
    actions = [env.random_action(gen) if env.discrete else 0.5 * env.random_action(gen) for _ in range(n)]
    start = time.process_time()
    for action in actions:
        env.step_members(action)
    return time.process_time() - start


def run_tree(tree: Path, args) -> list[dict]:
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    command = [sys.executable, str(HERE), "--worker", "--envs", *args.envs, "--batches", *map(str, args.batches)]
    command += ["--seconds", str(args.seconds)]
    out = subprocess.run(command, env=env, cwd=tree, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise SystemExit(f"{tree}: the worker failed:\n{out.stderr[-3000:]}")
    return [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("trees", nargs="*", type=Path, help="BEFORE and AFTER: two source trees of the package")
    parser.add_argument("--envs", nargs="+", default=None, help="env ids (default: every registered one)")
    parser.add_argument("--batches", nargs="+", type=int, default=[1, 16])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=1.0, help="CPU seconds per timed block")
    parser.add_argument("--out", type=Path, default=HERE.parent / "results" / "revisions")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.envs is None:
        from beacon_torch.registry import list_envs

        args.envs = list_envs()
    if args.worker:
        worker(args.envs, args.batches, args.seconds)
        return
    if len(args.trees) != 2 or not all((t / "beacon_torch").is_dir() for t in args.trees):
        parser.error("give two source trees of the package, BEFORE and AFTER")
    from beacon_torch.files import save_rows

    rounds = {"before": [], "after": []}
    for r in range(args.rounds):
        order = [("before", args.trees[0]), ("after", args.trees[1])]
        for name, tree in order if r % 2 == 0 else order[::-1]:
            rounds[name].append(run_tree(tree, args))
            print(f"round {r + 1}: {name} done", file=sys.stderr, flush=True)
    rows = []
    for case in rounds["before"][0]:
        key = (case["env"], case["mode"], case["batch"])
        per = {
            name: [c["cpu_s"] for rnd in runs for c in rnd if (c["env"], c["mode"], c["batch"]) == key]
            for name, runs in rounds.items()
        }
        before, after = statistics.median(per["before"]), statistics.median(per["after"])
        rows.append(
            dict(
                env=key[0],
                mode=key[1],
                batch=key[2],
                before_ms=1e3 * before,
                after_ms=1e3 * after,
                ratio=after / before,
                rounds={k: [1e3 * v for v in vs] for k, vs in per.items()},
            )
        )
    print("| env | mode | batch | before (ms CPU/step) | after | after / before |")
    print("|---|---|---:|---:|---:|---:|")
    for row in rows:
        print(
            f"| {row['env']} | {row['mode']} | {row['batch']} | {row['before_ms']:.3f} | {row['after_ms']:.3f} "
            f"| {row['ratio']:.3f} |"
        )
    for row in rows:
        row["trees"] = [str(t.resolve()) for t in args.trees]
    path = save_rows(rows, args.out, "revisions")
    print(f"written to {path}", file=sys.stderr)


if __name__ == "__main__":
    main()
