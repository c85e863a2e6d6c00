"""FluidGym's RBC2D results table rebuilt here: PPO and SAC, single- and multi-agent, on
each level, evaluated as FluidGym evaluates (the deterministic policy on held-out starts,
the Nusselt number averaged over each episode, the interquartile mean over the seeds and
episodes), beside no control from the same starts, FluidGym's own rows and the compute
of each.

    .venv/bin/python experiments/rbc2d_table.py [--runs runs/results] [--page docs/envs/rbc2d.md]

Reads the seeds that ``tools/reproduce.py train`` leaves in ``RUNS/ALGO/ENV/seedK`` for
``ENV`` among the six RBC2D ids, evaluates each seed's policy on the env's test set of
starts (eight developed states, one episode each; FluidGym's test set is ten), records
every episode's Nusselt number in a dated ``table-DATE.json`` in
``experiments/results/rbc2d/`` and writes the newest record's table on the page. The
improvement is the one FluidGym's table gives: the Nusselt number's fall against no
control, in per cent of no control's (ours: no control from the same starts). Compute:
FluidGym's A100-hours a run are its 50,000 environment steps at the seconds a step its
paper gives; ours are the CPU-hours of a seed's training (its wall time times its
threads), on the machine the record names.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "experiments" / "results" / "rbc2d"
BEGIN, END = "<!-- results: experiments/rbc2d_table.py -->", "<!-- end of the results -->"
LEVELS = ("easy", "medium", "hard")
# FluidGym's rows (paper/tables/RBC_results_table.tex, branch experiments): the IQM of
# the episodes' Nusselt number over its seeds and test episodes, and its improvement
FLUIDGYM = {
    ("easy", "PPO"): (4.008, 17.200),
    ("easy", "SAC"): (4.117, 14.952),
    ("easy", "MA-PPO"): (3.872, 20.015),
    ("easy", "MA-SAC"): (4.246, 12.285),
    ("medium", "PPO"): (6.291, 8.238),
    ("medium", "SAC"): (5.639, 17.746),
    ("medium", "MA-PPO"): (6.373, 7.041),
    ("medium", "MA-SAC"): (6.447, 5.960),
    ("hard", "PPO"): (7.547, 3.911),
    ("hard", "SAC"): (6.717, 14.467),
    ("hard", "MA-PPO"): (7.726, 1.622),
    ("hard", "MA-SAC"): (7.958, -1.327),
}
FLUIDGYM_SECONDS = {"easy": 1.27, "medium": 2.23, "hard": 2.26}  # an A100's seconds a step in training
FLUIDGYM_STEPS = 50_000  # environment steps a run


def cell(algo: str, env_id: str) -> tuple[str, str]:
    """``(level, FluidGym's algorithm name)`` of a run directory's pair."""
    level = env_id.split("-")[1]
    return level, ("MA-" if env_id.endswith("-ma-v0") else "") + algo.upper()


def pairs(runs: Path) -> list[tuple[str, str, Path]]:
    """The (algorithm, env, folder) of every RBC2D pair trained under ``runs``."""
    found = []
    for algo in ("ppo", "sac"):
        for level in LEVELS:
            for layout in ("", "-ma"):
                env_id = f"rbc2d-{level}{layout}-v0"
                folder = runs / algo / env_id
                if folder.is_dir():
                    found.append((algo, env_id, folder))
    return found


def evaluate(algo: str, env_id: str, folder: Path, free: dict) -> dict:
    """Each seed's test episodes under its policy, beside no control from the same
    starts (``free``: those of each env id and parameters, run once)."""
    import json

    from beacon_torch.starts import SETS
    from beacon_torch.training.evaluation import EVAL_SEED, episode_record, evaluate_run, uncontrolled_episodes
    from beacon_torch.training.run import load_checkpoint, seed_dirs

    seeds = []
    for run in seed_dirs(folder):
        state = load_checkpoint(run)
        params = state["config"].get("params", {})
        count = SETS["test"][1]
        key = (env_id, json.dumps(params, sort_keys=True))
        if key not in free:
            rollout, _ = uncontrolled_episodes(env_id, count, seed=EVAL_SEED, params=params, starts="test")
            free[key] = episode_record(rollout)
        result = evaluate_run(run, num_envs=count, starts="test", uncontrolled=sum(free[key]["score"]) / count)
        seeds.append(
            {
                "seed": run.name,
                "frames": state["frames"],
                "cpu_hours": state.get("elapsed", 0.0) * max(1, state["config"].get("threads", 1)) / 3600,
                "nusselt": result["episodes"]["nusselt"],
                "uncontrolled_nusselt": free[key]["nusselt"],
            }
        )
    level, name = cell(algo, env_id)
    return {"level": level, "algorithm": name, "env": env_id, "seeds": seeds}


def table(rows: list[dict]) -> str:
    from beacon_torch.training.report import iqm

    lines = [
        "| level | algorithm | FluidGym: Nu | improvement | A100-hours a run | here: Nu | improvement | "
        "no control here | seeds x episodes | transitions | CPU-hours a seed |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    done = {(r["level"], r["algorithm"]): r for r in rows}
    for level in LEVELS:
        hours = FLUIDGYM_STEPS * FLUIDGYM_SECONDS[level] / 3600
        for name in ("PPO", "SAC", "MA-PPO", "MA-SAC"):
            theirs, gain = FLUIDGYM[level, name]
            row = done.get((level, name))
            if row is None or not row["seeds"]:
                ours = "not run | | | | |"
            else:
                nu = iqm([x for s in row["seeds"] for x in s["nusselt"]])
                free = iqm([x for s in row["seeds"] for x in s["uncontrolled_nusselt"]])
                frames = ", ".join(f"{s['frames']:,}" for s in row["seeds"])
                cpu = sum(s["cpu_hours"] for s in row["seeds"]) / len(row["seeds"])
                episodes = len(row["seeds"][0]["nusselt"])
                ours = (
                    f"**{nu:.3f}** | {100 * (free - nu) / free:.1f} % | {free:.3f} | "
                    f"{len(row['seeds'])} x {episodes} | {frames} | {cpu:.2f}"
                )
            lines.append(f"| {level} | {name} | {theirs:.3f} | {gain:.1f} % | {hours:.1f} | {ours} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=Path, default=ROOT / "runs" / "results")
    parser.add_argument("--out", type=Path, default=RECORDS)
    parser.add_argument("--page", type=Path, default=ROOT / "docs" / "envs" / "rbc2d.md")
    parser.add_argument("--page-only", action="store_true", help="write the newest record's table, evaluate nothing")
    args = parser.parse_args()
    import torch

    from beacon_torch import received
    from beacon_torch.files import save_rows
    from beacon_torch.training.report import write_block

    torch.set_num_threads(1)
    if not args.page_only:
        free, rows = {}, []
        for algo, env_id, folder in pairs(args.runs):
            start = time.perf_counter()
            rows.append(evaluate(algo, env_id, folder, free))
            print(f"{algo}/{env_id}: {len(rows[-1]['seeds'])} seeds ({time.perf_counter() - start:.0f} s)", flush=True)
        if not rows:
            parser.exit(2, f"rbc2d_table: no RBC2D runs under {args.runs}\n")
        print("recorded:", save_rows(rows, args.out, "table"))
    records = sorted(args.out.glob("table-*.json"))
    if not records:
        parser.exit(2, f"rbc2d_table: no record in {args.out}\n")
    rows = received.json_file(records[-1], "an RBC2D results record")["rows"]
    print(table(rows))
    if args.page.exists():
        print(write_block(args.page, BEGIN, END, table(rows)))


if __name__ == "__main__":
    main()
