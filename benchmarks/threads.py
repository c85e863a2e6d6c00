"""Which number of torch threads steps each env fastest, per batch size, on an idle machine.

    .venv/bin/python benchmarks/threads.py [--envs ...] [--num-envs 1 16 64] [--write] [--out DIR]

For every benchmark env (a variant steps its base env's physics) at each batch size,
the compiled float32 step (the recipes' path) is timed with each thread count from 1 to
the machine's cores, every configuration in a fresh process after its compilation
(``beacon_torch.bench``), the thread counts of one batch alternating. Prints a markdown
table, writes a new dated ``threads-DATE-TIME.json`` to ``--out`` and, with ``--write``
(or ``--from RECORD`` for a record taken before), the table of the fastest counts that
the library's default follows (``beacon_torch/data/threads.json``, read by
``beacon_torch.threads``): the fewest threads within 5 % of the fastest. Run it on an
otherwise idle machine: a core taken by another process changes the answer, which
``--busy 1`` measures (a process keeping one core busy meanwhile; see
docs/performance.md).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import torch

from beacon_torch import threads
from beacon_torch.bench import measure_in_fresh_process
from beacon_torch.files import machine, save_rows, write_text
from beacon_torch.registry import base_envs

OUT = Path(__file__).parent / "results" / "threads"


# counts within this fraction of the fastest count as fast: the fewest of them is the
# default (fewer threads also suffer less from a busy machine)
WITHIN = 0.05


def fastest_count(rates: dict[int, float]) -> int:
    """The fewest threads whose rate is within :data:`WITHIN` of the fastest."""
    top = max(rates.values())
    return min(n for n, rate in rates.items() if rate >= (1 - WITHIN) * top)


def table_of(rows: list[dict]) -> dict:
    """The fastest count of each env and batch of records' step rows, and of each env's
    training (its recipe's PPO at the defaults) of their training rows."""
    steps: dict = {}
    training: dict = {}
    for r in rows:
        if "training" in r:
            training.setdefault(r["env"], {})[r["threads"]] = r["transitions_per_s"]
        else:
            steps.setdefault(r["env"], {}).setdefault(str(r["batch"]), {})[r["threads"]] = r["transitions_per_s"]
    table = {env: {batch: fastest_count(by) for batch, by in batches.items()} for env, batches in steps.items()}
    return {"steps": table, "training": {env: fastest_count(by) for env, by in training.items()}}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", default=base_envs(), choices=base_envs())
    parser.add_argument("--num-envs", nargs="+", type=int, default=list(threads.BATCHES))
    parser.add_argument(
        "--repeats", type=int, default=None, help="measurements of each configuration (default 5 steps, 1 training)"
    )
    parser.add_argument("--write", action="store_true", help=f"write the library's table, {threads.TABLE}")
    parser.add_argument(
        "--busy",
        type=int,
        default=0,
        help="processes that each keep a core busy meanwhile (a shared machine); the record says so",
    )
    parser.add_argument(
        "--training", action="store_true", help="time PPO training at each env's recipe defaults instead of steps"
    )
    parser.add_argument(
        "--rounds",
        type=int,
        default=3,
        help="with --training: PPO rounds per measurement, the first (compiling) not timed",
    )
    parser.add_argument("--out", default=str(OUT))
    parser.add_argument(
        "--from",
        dest="records",
        nargs="+",
        help="write the library's table from these records (a later one's rows replace an earlier one's), "
        "measuring nothing",
    )
    args = parser.parse_args(argv)
    if args.records:
        records = [json.loads(Path(r).read_text()) for r in args.records]
        rows = {(r["env"], r.get("batch"), r["threads"]): r for record in records for r in record["rows"]}
        write_table([Path(r) for r in args.records], records[-1]["machine"], table_of(list(rows.values())))
        return
    args.repeats = args.repeats or (1 if args.training else 5)
    counts = list(range(1, (os.cpu_count() or 1) + 1))
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.busy)]
    try:
        (measure_training if args.training else measure_all)(args, counts)
    finally:
        for process in busy:
            process.kill()


def training_rate(env_id: str, count: int, rounds: int = 3) -> float:
    """Transitions per second of PPO training on ``env_id`` with the recipe's defaults
    and ``count`` threads, in a fresh process: ``rounds`` rounds of collection and
    updates, timed from the run's wall-time log after the first (which compiles)."""
    import tempfile

    from beacon_torch.training.config import PPOConfig, configure
    from beacon_torch.training.run import read_log

    batch = configure(PPOConfig, env_id).n_rollout
    with tempfile.TemporaryDirectory() as folder:
        script = Path(__file__).parents[1] / "recipes" / "ppo.py"
        argv = [sys.executable, str(script), "--env", env_id, "--frames", str(rounds * batch), "--out", folder]
        argv += ["--threads", str(count), "--no-progress", "--logger", "csv"]
        subprocess.run(argv, check=True, capture_output=True, text=True)
        rows = read_log(Path(folder) / "ppo" / "scalars" / "wall_time.csv")
    (first, t0), (last, t1) = rows[0], rows[-1]
    return (last - first) / (t1 - t0)


def measure_training(args, counts: list[int]) -> None:
    """The recipes' workload: PPO rounds at each env's defaults with each count."""
    where = machine() + (f", {args.busy} other process(es) each keeping a core busy" if args.busy else ", idle")
    print(f"{where}; thread counts {counts}; PPO training at the recipe's defaults", flush=True)
    print("| env | " + " | ".join(f"{n} thread{'s' * (n > 1)} (transitions/s)" for n in counts) + " | fastest |")
    print("|---|" + "---|" * (len(counts) + 1))
    for env_id in args.envs:
        rates = {n: 0.0 for n in counts}
        for _ in range(args.repeats):  # the counts alternate; the best of the repeats
            for n in counts:
                rates[n] = max(rates[n], training_rate(env_id, n, args.rounds))
        rows = [{"env": env_id, "training": "ppo", "threads": n, "transitions_per_s": r} for n, r in rates.items()]
        print(f"| {env_id} | " + " | ".join(f"{rates[n]:,.1f}" for n in counts) + f" | {fastest_count(rates)} |")
        # an env's record as soon as it is measured: the slow envs take minutes each
        record = save_rows([{**r, "busy_processes": args.busy} for r in rows], args.out, "threads-training")
        print(f"record: {record}", flush=True)


def measure_all(args, counts: list[int]) -> None:
    where = machine() + (f", {args.busy} other process(es) each keeping a core busy" if args.busy else ", idle")
    print(f"{where}; thread counts {counts}; compiled float32", flush=True)
    print(
        "| env | members | " + " | ".join(f"{n} thread{'s' * (n > 1)} (transitions/s)" for n in counts) + " | fastest |"
    )
    print("|---|---|" + "---|" * (len(counts) + 1))
    rows, fastest = [], {}
    for env_id in args.envs:
        for batch in args.num_envs:
            rates = {}
            for n in counts:
                torch.set_num_threads(n)  # the measuring process takes this process's count
                m = measure_in_fresh_process(env_id, batch, mode="compiled", repeats=args.repeats)
                rates[n] = m.transitions_per_s
                rows.append({"env": env_id, "batch": batch, "threads": n, "transitions_per_s": rates[n]})
            best = fastest_count(rates)
            fastest.setdefault(env_id, {})[str(batch)] = best
            cells = " | ".join(f"{rates[n]:,.1f}" for n in counts)
            print(f"| {env_id} | {batch} | {cells} | {best} |", flush=True)
    record = save_rows([{**r, "busy_processes": args.busy} for r in rows], args.out, "threads")
    print(f"record: {record}")
    if args.write and not args.busy:
        write_table([record], machine(), {"steps": fastest, "training": {}})


def write_table(records: list[Path], where: str, fastest: dict) -> None:
    names = [os.path.relpath(Path(r).resolve(), threads.TABLE.parents[2]) for r in records]
    table = {"machine": where, "records": names, **fastest}
    print(f"table: {write_text(threads.TABLE, json.dumps(table, indent=1) + chr(10))}")


if __name__ == "__main__":
    main()
