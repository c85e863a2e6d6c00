"""The first PPO trials on Vignon et al.'s channel as a table of rayleigh-separable-v0's
page: one row per recorded run in ``experiments/results/rayleigh-separable/trials/RUN/``
(a recipe's ``episode_score.csv`` and ``wall_time.csv`` copied from its run directory,
with ``settings.json``: the recipe, the env and what it was given).

    .venv/bin/python experiments/rayleigh_separable_trials.py [--page docs/envs/rayleigh-separable.md]

Both layouts' scores are turned into a Nusselt number per action: the multi-agent
env's reward is minus the (mixed) Nusselt number; rayleigh-v0's is minus the bottom
wall's temperature gradient in units of dT over a unit length, so on the channel (H = 2)
its Nusselt number is minus H times the reward.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TRIALS = ROOT / "experiments" / "results" / "rayleigh-separable" / "trials"
BEGIN, END = "<!-- trials: experiments/rayleigh_separable_trials.py -->", "<!-- end of the trials -->"
# per env: actions an episode, and the factor from a reward to a Nusselt number
SCALE = {"rayleigh-separable-v0": (200, -1.0), "rayleigh-v0": (100, -2.0)}


def table(folder: Path = TRIALS) -> str:
    from beacon_torch.training.run import read_log

    lines = [
        "| run | recipe and settings | transitions | minutes | episodes' Nusselt: first | last | best |",
        "|---|---|---|---|---|---|---|",
    ]
    for run in sorted(p for p in folder.iterdir() if p.is_dir()):
        settings = json.loads((run / "settings.json").read_text())
        length, factor = SCALE[settings["env"]]
        nusselt = [factor * score / length for _, score in read_log(run / "episode_score.csv")]
        frames, seconds = read_log(run / "wall_time.csv")[-1]
        given = ", ".join(f"{k}={v}" for k, v in settings["given"].items()) or "defaults"
        lines.append(
            f"| {run.name} | {settings['recipe']} on {settings['env']} ({given}) | {int(frames):,} "
            f"| {seconds / 60:.1f} | {nusselt[0]:.3f} | {nusselt[-1]:.3f} | {min(nusselt):.3f} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--page", type=Path, default=ROOT / "docs" / "envs" / "rayleigh-separable.md")
    args = parser.parse_args()
    from beacon_torch.training.report import write_block

    print(table())
    print(write_block(args.page, BEGIN, END, table()))


if __name__ == "__main__":
    main()
