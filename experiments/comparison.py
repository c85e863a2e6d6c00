"""Model-free and gradient-based control side by side on every continuous env: the
recorded pairs' normalised training scores against transitions and against minutes
(PPO, TD3, SAC, the short-horizon actor-critic and its loop without a critic, grad,
from ``docs/results/``), gradient MPC's level (``experiments/results/mpc/``), and the
transitions and minutes each pair needed to reach the env's reference (normalised 1.0:
the paper's PPO score where there is one).

    .venv/bin/python experiments/comparison.py [--page docs/gradients.md]

A pair's curve is the mean over its seeds of the training episodes' scores, normalised
between no control and the env's reference like its results row; "reached" is the first
point where the mean of the last ``WINDOW`` curve points is at least 1. A summary
published before summaries kept their seeds' curves has its final point only: it
reached 1.0 within its budget if its final score is 1 or more, and the table says
"within" that budget, not when.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from beacon_torch.registry import continuous_envs

ROOT = Path(__file__).resolve().parents[1]
RECORDED = ROOT / "docs" / "results"
BEGIN, END = "<!-- comparison: experiments/comparison.py -->", "<!-- end of comparison -->"
ALGOS = ("ppo", "td3", "sac", "shac", "grad")
# PPO trains on the discrete twins of these: their rows are the targets' reference
PPO_OF = {"lorenz-continuous-v0": "lorenz-v0", "mixing-continuous-v0": "mixing-v0"}
# curve points over which "reached 1.0" is judged (training episodes are noisy)
WINDOW = 5
GRID = 100


def scored_envs() -> list[str]:
    """The continuous envs whose cards give a reference to normalise by (the paper's
    PPO score or another declared "= 1"): the comparison's scale (an env without one is
    compared on its own page)."""
    from beacon_torch.training import report

    return [env_id for env_id in continuous_envs() if report.normalisable(env_id)]


def pairs(env_id: str, recorded: Path = RECORDED) -> list[tuple[str, dict]]:
    """The recorded summaries that stand for ``env_id``, as (algorithm, summary)."""
    from beacon_torch.training import report

    found = []
    for algo in ALGOS:
        path = recorded / algo / f"{PPO_OF.get(env_id, env_id) if algo == 'ppo' else env_id}.json"
        if path.is_file():
            found.append((algo, report.read(path)))
    return found


def mean_curve(summary: dict) -> dict | None:
    """The seeds' mean normalised training score on a common grid of transitions, and
    the seeds' mean minutes of training at them (None where a seed logged no wall
    time); None for a summary that keeps no curves."""
    from beacon_torch.training import report

    curves = [seed.get("curve") for seed in summary["seeds"]]
    if not all(c and c["frames"] for c in curves):
        return None
    grid = np.linspace(max(c["frames"][0] for c in curves), min(c["frames"][-1] for c in curves), GRID)
    score = np.mean([np.interp(grid, c["frames"], c["score"]) for c in curves], axis=0)
    minutes = None
    if all(c["wall_s"] for c in curves):
        minutes = np.mean([np.interp(grid, c["frames"], c["wall_s"]) for c in curves], axis=0) / 60
    return {
        "frames": grid,
        "normalised": report.normalised(score, summary["uncontrolled"], summary["env"]),
        "minutes": minutes,
    }


def to_one(summary: dict) -> tuple[str, str]:
    """The transitions and minutes a pair needed to reach normalised 1.0, as the table
    writes them."""
    from beacon_torch.training import report

    curve = mean_curve(summary)
    final = report.row(summary, "own")["iqm"]
    if curve is None:
        if final >= 1.0:
            return f"within {summary['frames']:,} (final only)", f"within {summary['wall_s_per_seed'] / 60:.1f}"
        return "not reached (final only)", "-"
    smooth = np.convolve(curve["normalised"], np.ones(WINDOW) / WINDOW)[WINDOW - 1 : len(curve["frames"])]
    hit = np.flatnonzero(smooth >= 1.0)
    if not len(hit):
        return "not reached", "-"
    at = hit[0] + WINDOW - 1
    minutes = f"{curve['minutes'][at]:.1f}" if curve["minutes"] is not None else "-"
    return f"{curve['frames'][at]:,.0f}", minutes


def mpc_levels() -> dict[str, dict]:
    """Gradient MPC's evaluated record per env (the best normalised one). A record from
    starts where no control already scores above the paper's PPO (sloshing's developed
    test starts) has no meaningful normalised score and is no level."""
    from beacon_torch.arguments import load_script
    from beacon_torch.training.report import scaled

    module = load_script(ROOT / "experiments" / "mpc_table.py")
    best: dict[str, dict] = {}
    for record in module.records():
        if "normalised" not in record or not scaled(record["uncontrolled"], record["env"]):
            continue
        if record["normalised"] > best.get(record["env"], {}).get("normalised", -np.inf):
            best[record["env"]] = record
    return best


def _normalised(summary: dict, starts: str) -> str:
    """A pair's normalised IQM and interval from ``starts`` ("own" or "test"), or why
    there is none."""
    from beacon_torch.training import report

    if starts == "test" and not report.held_out(summary):
        return "- (b)"
    if starts == "test" and not report.test_scaled(summary):
        return "- (a)"
    row = report.row(summary, starts)
    return f"{row['iqm']:.2f} [{row['ci'][0]:.2f}, {row['ci'][1]:.2f}]"


def table(recorded: Path = RECORDED) -> str:
    """Each pair's normalised score from the env's own start and from the test set's
    starts, in a column each (the two are different episodes), with its budget and
    what it took to reach 1.0; gradient MPC's level in the column of the starts it
    planned from."""
    lines = [
        "| env | method | normalised, own start: IQM [95 % CI] | normalised, test set: IQM [95 % CI] | transitions "
        "| minutes per seed | transitions to 1.0 | minutes to 1.0 |",
        "|---|---|---|---|---|---|---|---|",
    ]
    levels = mpc_levels()
    for env_id in scored_envs():
        for algo, summary in pairs(env_id, recorded):
            name = algo if summary["env"] == env_id else f"{algo} ({summary['env']})"
            frames, minutes = to_one(summary)
            lines.append(
                f"| {env_id} | {name} | {_normalised(summary, 'own')} | {_normalised(summary, 'test')} "
                f"| {summary['frames']:,} | {summary['wall_s_per_seed'] / 60:.1f} | {frames} | {minutes} |"
            )
        if env_id in levels:
            r = levels[env_id]
            s = r["settings"]
            level = f"{r['normalised']:.2f}"
            own, test = (level, "-") if r["starts"] == "own" else ("-", level)
            lines.append(
                f"| {env_id} | gradient MPC ({s['horizon']} x {s['iterations']}) | {own} | {test} "
                f"| none (no learning) | {r['cpu_s_per_action']:.2g} CPU s per action | - | - |"
            )
    lines += [
        "",
        "(a): no control from the test set's developed starts already scores above the reference, so the scale "
        "from one to the other runs backwards and is not used. (b): published before its seeds were scored on "
        "the test set.",
    ]
    return "\n".join(lines)


def draw(path: Path, recorded: Path = RECORDED) -> None:
    """Per env, the normalised score against transitions (left) and minutes (right)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import NullFormatter

    from beacon_torch.files import save_figure
    from beacon_torch.training import report

    levels, envs = mpc_levels(), scored_envs()
    fig = Figure(figsize=(10, 2.6 * len(envs)), dpi=80)
    FigureCanvasAgg(fig)
    axes = fig.subplots(len(envs), 2, squeeze=False)
    for k, env_id in enumerate(envs):
        left, right = axes[k]
        for algo, summary in pairs(env_id, recorded):
            color, label = f"C{ALGOS.index(algo)}", algo if summary["env"] == env_id else f"{algo} ({summary['env']})"
            curve = mean_curve(summary)
            if curve is not None:
                left.plot(curve["frames"], curve["normalised"], color=color, label=label)
                if curve["minutes"] is not None:
                    right.plot(curve["minutes"], curve["normalised"], color=color, label=label)
            else:  # published before summaries kept curves: its final point
                final = report.row(summary, "own")["iqm"]
                left.plot([summary["frames"]], [final], "o", color=color, label=f"{label} (final)")
                right.plot([summary["wall_s_per_seed"] / 60], [final], "o", color=color, label=f"{label} (final)")
        for ax in (left, right):
            ax.axhline(1.0, color="k", ls=":", lw=1)
            ax.axhline(0.0, color="k", ls="--", lw=1)
            if env_id in levels:
                ax.axhline(levels[env_id]["normalised"], color=f"C{len(ALGOS)}", ls="-.", lw=1.2, label="gradient MPC")
            ax.grid(alpha=0.3)
            ax.set_ylabel("normalised score")
        left.set_xscale("log")
        low, high = left.get_xlim()
        left.set_xlim(low / 2, high * 2)  # a decade's tick always inside
        left.xaxis.set_minor_formatter(NullFormatter())  # the decades alone: minor labels overlap
        right.set_xlim(left=0)
        left.set_xlabel("transitions")
        right.set_xlabel("minutes of training per seed")
        left.set_title(env_id, fontsize=9, loc="left")
        if left.get_legend_handles_labels()[0]:  # an env without a recorded pair yet has none
            left.legend(fontsize=6, loc="lower right")
    fig.tight_layout()
    save_figure(fig, path, new=False)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--page", type=Path, default=ROOT / "docs" / "gradients.md")
    args = parser.parse_args()
    from beacon_torch.training.report import write_block

    draw(args.page.parent / "img" / "comparison.png")
    print(write_block(args.page, BEGIN, END, table()))


if __name__ == "__main__":
    main()
