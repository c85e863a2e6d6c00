"""FluidGym's RBC2D results table rebuilt here: PPO and SAC, single- and multi-agent, on
each level, evaluated as FluidGym evaluates (the deterministic policy on held-out starts,
the Nusselt number averaged over each episode, the interquartile mean over the seeds and
episodes), beside no control from the same starts, FluidGym's own rows and the compute
of each.

    .venv/bin/python experiments/rbc2d_table.py [--results docs/results] [--page docs/envs/rbc2d.md]

Reads the pairs that ``tools/reproduce.py publish`` recorded in ``RESULTS/ALGO/ENV.json``
for the six RBC2D ids: each seed's episodes from the env's test set of starts (eight
developed states, one episode each; FluidGym's test set is ten) with their Nusselt
numbers, and no control's from the same starts; and writes the table on the page. The
improvement is the one FluidGym's table gives: the Nusselt number's fall against no
control, in per cent of no control's (ours: no control from the same starts). Compute:
FluidGym's A100-hours a run are its 50,000 environment steps at the seconds a step its
paper gives; ours are the CPU-hours of a seed's training (its wall time times its
threads, on the machine of the campaign); the agent, whose actor, critic and update
a PPO pair trained with (FluidGym's runs: Stable-Baselines3's).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from beacon_torch.envs.rbc2d import LEVELS

ROOT = Path(__file__).resolve().parents[1]
BEGIN, END = "<!-- results: experiments/rbc2d_table.py -->", "<!-- end of the results -->"
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


def agent(algo: str, summary: dict) -> str:
    """Whose PPO a pair trained: its actor, critic and update as its run recorded them
    (runs made before a setting existed trained the paper's); SAC's is of one kind, its
    gradient steps said where they are fewer than FluidGym's (one an agent transition:
    a flow step's twelve in the multi-agent layout)."""
    config = summary["config"]
    if algo != "ppo":
        agents = 12 if config.get("env", "").endswith("-ma-v0") else 1
        per_step = config.get("updates_per_batch", 1) / config.get("frames_per_batch", 1)
        if per_step >= agents:
            return "SAC's"
        return (
            f"SAC's, {per_step:g} gradient step{'s' * (per_step != 1)} a flow step "
            f"(FluidGym's: {agents}, one an agent transition)"
        )
    parts = (config.get("actor", "paper"), config.get("critic", "paper"), config.get("update", "paper"))
    if parts == ("free-spread", "sb3", "sb3"):
        return "Stable-Baselines3's"
    return "Stable-Baselines3's actor" if parts[0] == "free-spread" else "the paper's"


def recorded(results: Path, received) -> list[dict]:
    """The table's rows from the recorded summaries of the RBC2D pairs in ``results``."""
    rows = []
    for algo in ("ppo", "sac"):
        for level in LEVELS:
            for layout in ("", "-ma"):
                env_id = f"rbc2d-{level}{layout}-v0"
                file = results / algo / f"{env_id}.json"
                if not file.is_file():
                    continue
                summary = received.json_file(file, "a recorded summary")
                threads = max(1, int(summary["config"].get("threads") or 1))
                seeds = [
                    {
                        "seed": s["seed"],
                        "frames": s["frames"],
                        "cpu_hours": s["wall_s"] * threads / 3600,
                        "nusselt": s["test_episodes"]["nusselt"],
                        "uncontrolled_nusselt": s["test_uncontrolled_episodes"]["nusselt"],
                    }
                    for s in summary["seeds"]
                ]
                level_name, name = cell(algo, env_id)
                rows.append(
                    {
                        "level": level_name,
                        "algorithm": name,
                        "env": env_id,
                        "agent": agent(algo, summary),
                        "seeds": seeds,
                    }
                )
    return rows


def table(rows: list[dict]) -> str:
    from beacon_torch.training.report import iqm

    lines = [
        "| level | algorithm | FluidGym: Nu | improvement | A100-hours a run | here: Nu | improvement | "
        "no control here | seeds x episodes | transitions | CPU-hours a seed | agent |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    done = {(r["level"], r["algorithm"]): r for r in rows}
    for level in LEVELS:
        hours = FLUIDGYM_STEPS * FLUIDGYM_SECONDS[level] / 3600
        for name in ("PPO", "SAC", "MA-PPO", "MA-SAC"):
            theirs, gain = FLUIDGYM[level, name]
            row = done.get((level, name))
            if row is None or not row["seeds"]:
                ours = "not run | | | | | |"
            else:
                nu = iqm([x for s in row["seeds"] for x in s["nusselt"]])
                free = iqm([x for s in row["seeds"] for x in s["uncontrolled_nusselt"]])
                frames = ", ".join(f"{s['frames']:,}" for s in row["seeds"])
                cpu = sum(s["cpu_hours"] for s in row["seeds"]) / len(row["seeds"])
                episodes = len(row["seeds"][0]["nusselt"])
                ours = (
                    f"**{nu:.3f}** | {100 * (free - nu) / free:.1f} % | {free:.3f} | "
                    f"{len(row['seeds'])} x {episodes} | {frames} | {cpu:.2f} | {row['agent']}"
                )
            lines.append(f"| {level} | {name} | {theirs:.3f} | {gain:.1f} % | {hours:.1f} | {ours} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--results", type=Path, default=ROOT / "docs" / "results")
    parser.add_argument("--page", type=Path, default=ROOT / "docs" / "envs" / "rbc2d.md")
    args = parser.parse_args()
    from beacon_torch import received
    from beacon_torch.training.report import write_block

    rows = recorded(args.results, received)
    print(table(rows))
    if args.page.exists():
        print(write_block(args.page, BEGIN, END, table(rows)))


if __name__ == "__main__":
    main()
