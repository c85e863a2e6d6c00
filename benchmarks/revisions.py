"""Two versions of the package side by side: the CPU time of one step, every env.

    .venv/bin/python benchmarks/revisions.py BEFORE AFTER [--envs ...] [--batches 1 16]
        [--modes eager compiled] [--rounds 3] [--seconds 1.0] [--blocks 3] [--paired] [--out DIR]

``BEFORE`` and ``AFTER`` are source trees of the package (two clones or worktrees of
two commits). Each round runs one process per tree on one thread; each process makes
every env at every batch size (seed 0, float32) and times ``step_members`` with random
actions (fixed seed), eagerly and, for the envs whose actions are cheap, compiled (what
the adapters and the recipes run), after warm-up steps (compilation included there), in
``--blocks`` blocks of the same number of steps. The time is the process's CPU time, so
that another process on the machine weighs less; run it on an idle machine all the same.

Sequentially (the default) the trees alternate in order from round to round. With
``--paired`` (a machine of two cores or more) the two processes run at once, each
pinned to a core of its own (swapped from round to round), and wait for each other
before every case, so that both time the case in the same seconds: a machine whose
speed drifts (a shared host) then slows both sides alike, and each round's ratio is
taken between simultaneous measurements. The table gives, per case, the median over the
rounds of the block medians of each side and the median of the rounds' ratios. Writes a
new ``revisions-DATE-TIME.json`` (machine, trees, every round's blocks) to ``--out``.
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


def worker(envs: list[str], batches: list[int], modes: list[str], seconds: float, blocks: int, paired: bool) -> None:
    """Time the steps of every env in this process's tree; one JSON line per case.
    ``paired``: before timing a case, say so and wait for the number of steps a block
    takes (one line on stdin), so that the other tree times it at the same time."""
    import torch

    import beacon_torch
    from beacon_torch.registry import env_class

    torch.set_num_threads(1)
    for env_id in envs:
        costly = env_class(env_id).costly
        for mode in [m for m in modes if m == "eager" or not costly]:
            for batch in batches:
                env = beacon_torch.make(env_id, batch, seed=0, compile=mode == "compiled")
                env.reset()
                gen = torch.Generator().manual_seed(2)
                # warm-up: compilation, caches; an action of seconds is timed once a block
                warm = timed(env, 1 if costly else 3, torch.Generator().manual_seed(1))
                n = 1 if costly else max(2, min(env.episode_length // 2, int(seconds / max(warm / 3, 1e-6))))
                if paired:
                    print(json.dumps(dict(ready=env_id, steps=n)), flush=True)
                    n = int(sys.stdin.readline())
                times = [timed(env, n, gen) / n for _ in range(blocks)]
                case = dict(env=env_id, mode=mode, batch=batch, steps=n, cpu_s=statistics.median(times), blocks=times)
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


def worker_command(tree: Path, args, paired: bool) -> tuple[list[str], dict]:
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    command = [sys.executable, str(HERE), "--worker", "--envs", *args.envs, "--batches", *map(str, args.batches)]
    command += ["--modes", *args.modes]
    command += ["--seconds", str(args.seconds), "--blocks", str(args.blocks)] + (["--paired"] if paired else [])
    return command, env


def run_tree(tree: Path, args) -> list[dict]:
    command, env = worker_command(tree, args, paired=False)
    out = subprocess.run(command, env=env, cwd=tree, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise SystemExit(f"{tree}: the worker failed:\n{out.stderr[-3000:]}")
    return [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]


def run_paired(trees: list[Path], cores: list[int], args) -> list[list[dict]]:
    """Both trees at once, tree k pinned to ``cores[k]``, each case started together."""
    procs = []
    for tree, core in zip(trees, cores, strict=True):
        command, env = worker_command(tree, args, paired=True)
        procs.append(
            subprocess.Popen(
                command,
                env=env,
                cwd=tree,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
                text=True,
                preexec_fn=lambda core=core: os.sched_setaffinity(0, {core}),
            )
        )

    def next_record(proc, tree) -> dict:
        for line in proc.stdout:
            if line.startswith("{"):
                return json.loads(line)
        raise SystemExit(f"{tree}: the worker stopped (exit {proc.wait()})")

    results: list[list[dict]] = [[] for _ in trees]
    while True:
        ready = []
        for proc in procs:
            line = ""
            while not line.startswith("{"):
                line = proc.stdout.readline()
                if not line:
                    break
            ready.append(json.loads(line) if line else None)
        if all(r is None for r in ready):
            break
        if any(r is None for r in ready):
            raise SystemExit("a worker stopped before the other")
        steps = ready[0]["steps"]  # the same block for both: BEFORE's choice
        for proc in procs:
            proc.stdin.write(f"{steps}\n")
            proc.stdin.flush()
        for k, (proc, tree) in enumerate(zip(procs, trees, strict=True)):
            results[k].append(next_record(proc, tree))
    for proc in procs:
        proc.wait()
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("trees", nargs="*", type=Path, help="BEFORE and AFTER: two source trees of the package")
    parser.add_argument("--envs", nargs="+", default=None, help="env ids (default: every registered one)")
    parser.add_argument("--batches", nargs="+", type=int, default=[1, 16])
    parser.add_argument(
        "--modes", nargs="+", choices=["eager", "compiled"], default=["eager", "compiled"], help="compiled: cheap envs"
    )
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=1.0, help="CPU seconds per timed block")
    parser.add_argument("--blocks", type=int, default=3, help="timed blocks per case and round")
    parser.add_argument("--paired", action="store_true", help="both trees at once, on a core each (see above)")
    parser.add_argument("--out", type=Path, default=HERE.parent / "results" / "revisions")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.envs is None:
        from beacon_torch.registry import list_envs

        args.envs = list_envs()
    if args.worker:
        worker(args.envs, args.batches, args.modes, args.seconds, args.blocks, args.paired)
        return
    if len(args.trees) != 2 or not all((t / "beacon_torch").is_dir() for t in args.trees):
        parser.error("give two source trees of the package, BEFORE and AFTER")
    if args.paired and len(os.sched_getaffinity(0)) < 2:
        parser.error("--paired needs two cores")
    from beacon_torch.files import save_rows

    rounds = {"before": [], "after": []}
    for r in range(args.rounds):
        if args.paired:
            cores = sorted(os.sched_getaffinity(0))[:2]
            before, after = run_paired(args.trees, cores if r % 2 == 0 else cores[::-1], args)
            rounds["before"].append(before)
            rounds["after"].append(after)
            print(f"round {r + 1} done (paired)", file=sys.stderr, flush=True)
            continue
        order = [("before", args.trees[0]), ("after", args.trees[1])]
        for name, tree in order if r % 2 == 0 else order[::-1]:
            rounds[name].append(run_tree(tree, args))
            print(f"round {r + 1}: {name} done", file=sys.stderr, flush=True)
    rows = []
    for i, case in enumerate(rounds["before"][0]):
        key = (case["env"], case["mode"], case["batch"])
        per = {name: [rnd[i]["cpu_s"] for rnd in runs] for name, runs in rounds.items()}
        before, after = statistics.median(per["before"]), statistics.median(per["after"])
        # paired: each round's ratio is of simultaneous measurements
        ratios = [a / b for a, b in zip(per["after"], per["before"], strict=True)]
        rows.append(
            dict(
                env=key[0],
                mode=key[1],
                batch=key[2],
                before_ms=1e3 * before,
                after_ms=1e3 * after,
                ratio=statistics.median(ratios) if args.paired else after / before,
                round_ratios=ratios,
                rounds={k: [1e3 * v for v in vs] for k, vs in per.items()},
                blocks={k: [[1e3 * v for v in rnd[i]["blocks"]] for rnd in runs] for k, runs in rounds.items()},
                paired=args.paired,
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
