"""The gradient model-predictive control's recorded results as the table of
docs/gradients.md: one row per record of ``recipes/mpc.py`` in
``experiments/results/mpc/ENV/mpc.json`` (an evaluation, or the cost of a few planned
actions where an episode does not fit in an hour).

    .venv/bin/python experiments/mpc_table.py [--page docs/gradients.md]
"""

from __future__ import annotations

import argparse
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "experiments" / "results" / "mpc"
BEGIN, END = "<!-- gradient mpc: experiments/mpc_table.py -->", "<!-- end of gradient mpc -->"


def records(folder: Path = RECORDS) -> list[dict]:
    from beacon_torch import received

    return [received.json_file(path, "an mpc record") for path in sorted(folder.glob("*/mpc.json"))]


def table(rows: list[dict]) -> str:
    """The records as a markdown table. A planned action costs ``horizon x iterations``
    differentiated steps: the cost at FluidGym's 20 x 10 is the recorded one scaled."""
    from beacon_torch.registry import env_spec
    from beacon_torch.training.report import normalisable, normalised, scaled

    lines = [
        "| env | starts (episodes) | horizon x iterations | planner's model | score (std over episodes) "
        "| uncontrolled | normalised | CPU s per action | at 20 x 10 | an episode at 20 x 10 |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        s = r["settings"]
        model = ", ".join(f"{k}={v}" for k, v in r["plan_params"].items()) or "the env's"
        per_action = r["cpu_s_per_action"]
        default = per_action * (20 * 10) / (s["horizon"] * s["iterations"])
        hours = default * env_spec(r["env"]).physics.episode_length / 3600
        episode = f"{hours:.1f} h" if hours >= 1 else f"{60 * hours:.0f} min"
        if "score_mean" in r:
            # a record written before its env's card had a reference is scored by it now
            share = r.get("normalised")
            if share is None and normalisable(r["env"]):
                share = float(normalised(r["score_mean"], r["uncontrolled"], r["env"]))
            if share is None:
                cell = "- (b)"
            # no control above the paper's score from these starts: the scale runs backwards
            elif scaled(r["uncontrolled"], r["env"]):
                cell = f"**{share:.2f}**"
            else:
                cell = "- (a)"
            scores = f"{r['score_mean']:.4g} ({r['score_std']:.2g}) | {r['uncontrolled']:.4g} | {cell}"
        else:
            scores = f"not run ({r['planned_actions']} actions planned for their cost) | | "
        lines.append(
            f"| {r['env']} | {r['starts']} ({s['num_envs']}) | {s['horizon']} x {s['iterations']}"
            f"{', compiled' if s['compile'] else ''}{', checkpointed' if s['grad_checkpoint'] else ''} | {model} "
            f"| {scores} | {per_action:.3g} | {default:.3g} | {episode} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--page", type=Path, default=ROOT / "docs" / "gradients.md")
    args = parser.parse_args()
    from beacon_torch.training.report import write_block

    print(write_block(args.page, BEGIN, END, table(records())))


if __name__ == "__main__":
    main()
