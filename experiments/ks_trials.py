"""ks-v0's first training trials as a table of its page: one row per recorded run in
``experiments/results/ks/trials/RUN/`` (a recipe's ``episode_score.csv`` and
``wall_time.csv`` copied from its run directory, with ``settings.json``: the recipe and
what it was given).

    .venv/bin/python experiments/ks_trials.py [--page docs/envs/ks.md]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TRIALS = ROOT / "experiments" / "results" / "ks" / "trials"
BEGIN, END = "<!-- trials: experiments/ks_trials.py -->", "<!-- end of the trials -->"


def table(folder: Path = TRIALS) -> str:
    from beacon_torch.training.run import read_log

    lines = [
        "| run | recipe and settings | transitions | minutes | first episodes' score | last episodes' score | "
        "last mean distance per action |",
        "|---|---|---|---|---|---|---|",
    ]
    for run in sorted(p for p in folder.iterdir() if p.is_dir()):
        settings = json.loads((run / "settings.json").read_text())
        scores = read_log(run / "episode_score.csv")
        frames, seconds = read_log(run / "wall_time.csv")[-1]
        given = ", ".join(f"{k}={v}" for k, v in settings["given"].items()) or "defaults"
        last = scores[-1][1]
        lines.append(
            f"| {run.name} | {settings['recipe']} ({given}) | {int(frames):,} | {seconds / 60:.1f} "
            f"| {scores[0][1]:,.0f} | {last:,.0f} | {-last / 3000:.2f} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--page", type=Path, default=ROOT / "docs" / "envs" / "ks.md")
    args = parser.parse_args()
    from beacon_torch.training.report import write_block

    print(table())
    print(write_block(args.page, BEGIN, END, table()))


if __name__ == "__main__":
    main()
