"""Two versions of the package side by side: the CPU time of one step, every env.

    .venv/bin/python benchmarks/revisions.py BEFORE AFTER [--envs ...] [--batches 1 16]
        [--modes eager compiled] [--rounds 3] [--seconds 1.0] [--blocks 3] [--interleaved] [--out DIR]

``BEFORE`` and ``AFTER`` are source trees of the package (two clones or worktrees of
two commits). Each round runs one process per tree on one thread; each process makes
every env at every batch size (seed 0, float32) and times ``step_members`` with random
actions (fixed seed), eagerly and, for the envs whose actions are cheap, compiled (what
the adapters and the recipes run), after warm-up steps (compilation included there), in
``--blocks`` blocks of the same number of steps. The time is the process's CPU time, so
that another process on the machine weighs less; run it on an idle machine all the same.

Sequentially (the default) the trees alternate in order from round to round. With
``--interleaved`` the two processes run side by side on one core (the next core in
the next round), and each case's blocks alternate between them, block by block: a
machine whose speed drifts over seconds (a shared host: this project's machines
change speed by up to two times between processes and within one) then slows the two
blocks of a pair alike, and the ratio of the trees is the median over every pair of
adjacent blocks, rounds pooled. The table gives, per case, the median block time of
each side and that ratio. Writes a new ``revisions-DATE-TIME.json`` (machine, trees and
their commits, every round's blocks) to ``--out``.
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


def worker(
    envs: list[str], batches: list[int], modes: list[str], seconds: float, blocks: int, interleaved: bool
) -> None:
    """Time the steps of every env in this process's tree; one JSON line per case.
    ``interleaved``: before timing a case, say so (with the steps a block would take),
    then time one block of the number of steps each line on stdin gives, until an
    empty line, so that the other tree's blocks run in between."""
    import torch

    import beacon_torch
    from beacon_torch import registry

    torch.set_num_threads(1)
    for env_id in envs:
        # the tree before may be one whose ids were classes with the card's fields on them
        spec = registry.env_spec(env_id) if hasattr(registry, "env_spec") else registry.env_class(env_id)
        costly = spec.card.costly if hasattr(spec, "card") else spec.costly
        for mode in [m for m in modes if m == "eager" or not costly]:
            for batch in batches:
                env = beacon_torch.make(env_id, batch, seed=0, compile=mode == "compiled")
                env.reset()
                gen = torch.Generator().manual_seed(2)
                # warm-up: compilation, caches; an action of seconds is timed once a block
                warm = timed(env, 1 if costly else 3, torch.Generator().manual_seed(1))
                n = 1 if costly else max(2, min(env.episode_length // 2, int(seconds / max(warm / 3, 1e-6))))
                if interleaved:
                    print(json.dumps(dict(ready=env_id, steps=n)), flush=True)
                    times = []
                    while line := sys.stdin.readline().strip():
                        n = int(line)
                        times.append(timed(env, n, gen) / n)
                        print(json.dumps(dict(block=times[-1])), flush=True)
                else:
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


def worker_command(tree: Path, args, interleaved: bool) -> tuple[list[str], dict]:
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    command = [sys.executable, str(HERE), "--worker", "--envs", *args.envs, "--batches", *map(str, args.batches)]
    command += ["--modes", *args.modes]
    command += ["--seconds", str(args.seconds), "--blocks", str(args.blocks)]
    command += ["--interleaved"] if interleaved else []
    return command, env


def run_tree(tree: Path, args) -> list[dict]:
    command, env = worker_command(tree, args, interleaved=False)
    out = subprocess.run(command, env=env, cwd=tree, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise SystemExit(f"{tree}: the worker failed:\n{out.stderr[-3000:]}")
    return [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]


def run_interleaved(trees: list[Path], core: int, args) -> list[list[dict]]:
    """Both trees' processes on one core, their blocks of each case alternating (which
    goes first alternates too), every block the same number of steps."""
    procs = []
    for tree in trees:
        command, env = worker_command(tree, args, interleaved=True)
        procs.append(
            subprocess.Popen(
                command,
                env=env,
                cwd=tree,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
                text=True,
                preexec_fn=lambda: os.sched_setaffinity(0, {core}),
            )
        )

    def record(proc) -> dict | None:
        """The next JSON line of a worker, None when it has ended."""
        for line in proc.stdout:
            if line.startswith("{"):
                return json.loads(line)
        return None

    def send(proc, text: str) -> None:
        proc.stdin.write(text + "\n")
        proc.stdin.flush()

    results: list[list[dict]] = [[] for _ in trees]
    while True:
        ready = [record(proc) for proc in procs]
        if all(r is None for r in ready):
            break
        if any(r is None for r in ready):
            raise SystemExit("a worker stopped before the other (run it sequentially to see why)")
        steps = str(ready[0]["steps"])  # the same blocks for both: BEFORE's choice
        for k in range(args.blocks):
            for proc in procs if k % 2 == 0 else procs[::-1]:
                send(proc, steps)
                record(proc)
        for k, proc in enumerate(procs):
            send(proc, "")
            results[k].append(record(proc))
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
    parser.add_argument("--interleaved", action="store_true", help="the two trees' blocks alternate (see above)")
    parser.add_argument("--out", type=Path, default=HERE.parent / "results" / "revisions")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.envs is None:
        from beacon_torch.registry import list_envs

        args.envs = list_envs()
    if args.worker:
        worker(args.envs, args.batches, args.modes, args.seconds, args.blocks, args.interleaved)
        return
    if len(args.trees) != 2 or not all((t / "beacon_torch").is_dir() for t in args.trees):
        parser.error("give two source trees of the package, BEFORE and AFTER")
    from beacon_torch.files import revision, save_rows

    rounds = {"before": [], "after": []}
    for r in range(args.rounds):
        if args.interleaved:
            cores = sorted(os.sched_getaffinity(0))
            before, after = run_interleaved(args.trees, cores[r % len(cores)], args)
            rounds["before"].append(before)
            rounds["after"].append(after)
            print(f"round {r + 1} done (interleaved)", file=sys.stderr, flush=True)
            continue
        order = [("before", args.trees[0]), ("after", args.trees[1])]
        for name, tree in order if r % 2 == 0 else order[::-1]:
            rounds[name].append(run_tree(tree, args))
            print(f"round {r + 1}: {name} done", file=sys.stderr, flush=True)
    rows = []
    for i, case in enumerate(rounds["before"][0]):
        key = (case["env"], case["mode"], case["batch"])
        per = {name: [rnd[i]["cpu_s"] for rnd in runs] for name, runs in rounds.items()}
        blocks = {name: [rnd[i]["blocks"] for rnd in runs] for name, runs in rounds.items()}
        if args.interleaved:  # adjacent blocks, rounds pooled
            pairs = zip(sum(blocks["before"], []), sum(blocks["after"], []), strict=True)
            before, after = (statistics.median(sum(blocks[k], [])) for k in ("before", "after"))
            ratio = statistics.median(a / b for b, a in pairs)
        else:
            before, after = statistics.median(per["before"]), statistics.median(per["after"])
            ratio = after / before
        rows.append(
            dict(
                env=key[0],
                mode=key[1],
                batch=key[2],
                before_ms=1e3 * before,
                after_ms=1e3 * after,
                ratio=ratio,
                rounds={k: [1e3 * v for v in vs] for k, vs in per.items()},
                blocks={k: [[1e3 * v for v in rnd] for rnd in runs] for k, runs in blocks.items()},
                interleaved=args.interleaved,
            )
        )
    print("| env | mode | batch | before (ms CPU/step) | after | after / before |")
    print("|---|---|---:|---:|---:|---:|")
    for row in rows:
        print(
            f"| {row['env']} | {row['mode']} | {row['batch']} | {row['before_ms']:.3f} | {row['after_ms']:.3f} "
            f"| {row['ratio']:.3f} |"
        )
    commits = [revision(t) for t in args.trees]
    for row in rows:
        row["trees"] = [str(t.resolve()) for t in args.trees]
        row["commits"] = commits
    path = save_rows(rows, args.out, "revisions")
    print(f"written to {path}", file=sys.stderr)


if __name__ == "__main__":
    main()
