"""ks-v0's training as two tables of its page: its first trials, one row per recorded
run in ``experiments/results/ks/trials/RUN/`` (a recipe's ``episode_score.csv`` and
``wall_time.csv`` copied from its run directory, with ``settings.json``: the recipe and
what it was given); and the three-seed results published by ``tools/reproduce.py``
(``docs/results/ALGO/ks-v0.json``), as distances to the target.

    .venv/bin/python experiments/ks_trials.py [--page docs/envs/ks.md]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TRIALS = ROOT / "experiments" / "results" / "ks" / "trials"
RECORDED = ROOT / "docs" / "results"
BEGIN, END = "<!-- trials: experiments/ks_trials.py -->", "<!-- end of the trials -->"
RESULTS = "<!-- results: experiments/ks_trials.py -->", "<!-- end of the results -->"
ENV = "ks-v0"


def table(folder: Path = TRIALS) -> str:
    from beacon_torch.training.run import read_log

    actions = episode_actions()

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
            f"| {scores[0][1]:,.0f} | {last:,.0f} | {-last / actions:.2f} |"
        )
    return "\n".join(lines)


def episode_actions() -> int:
    """An episode's actions: a score over them is minus the summed distance."""
    from beacon_torch.registry import env_spec

    return env_spec(ENV).physics.episode_length


def results(recorded: Path = RECORDED) -> str:
    """The published pairs on ks-v0, on the test set's starts: the normalised score
    (0 no control, 1 the target held from the first action) and the mean distance to
    the target per action of each seed's deterministic policy."""
    from beacon_torch.training import report

    actions = episode_actions()
    lines = [
        "| recipe | seeds | transitions | minutes per seed | normalised score, IQM [95 % CI] | "
        "mean distance per action, per seed | no control's |",
        "|---|---|---|---|---|---|---|",
    ]
    for file in sorted(recorded.glob(f"*/{ENV}.json")):
        row = report.row(report.read(file))
        per_seed = ", ".join(f"{-score / actions:.2f}" for score in row["scores"])
        lines.append(
            f"| {row['algo']} | {row['seeds']} | {row['frames']:,} | {row['wall_s_per_seed'] / 60:.1f} "
            f"| **{row['iqm']:.2f}** [{row['ci'][0]:.2f}, {row['ci'][1]:.2f}] | {per_seed} "
            f"| {-row['uncontrolled'] / actions:.2f} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--page", type=Path, default=ROOT / "docs" / "envs" / "ks.md")
    args = parser.parse_args()
    from beacon_torch.training.report import write_block

    for begin_end, block in (((BEGIN, END), table()), (RESULTS, results())):
        print(block)
        print(write_block(args.page, *begin_end, block))


if __name__ == "__main__":
    main()
