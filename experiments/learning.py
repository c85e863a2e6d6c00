"""PPO against gradient-based control on one env (cylinder-v0, pinball-periodic-v0):
how many transitions and minutes each takes to learn.

    .venv/bin/python experiments/learning.py RUN_DIR [RUN_DIR ...] --figure FIGURE.png [--out DIR]

RUN_DIR: a folder of seeds of one algorithm (``runs/results/ppo/cylinder-v0``,
``runs/results/grad/cylinder-v0``), or one seed's folder, all trained on the same env
and parameters. For each, the training episodes' scores of its seeds (the deterministic
policy's for gradient-based control, the sampled one's for PPO) are averaged over
windows of transitions, and the transitions and wall-clock
minutes at which the seeds' mean first reaches a half and nine tenths of the way from
no control to the first run's final score are printed beside each other. Draws both
curves against transitions and against minutes into a new figure and writes a new dated
``ENV_learning-DATE-TIME.json`` (the env's name without its version:
``cylinder_learning-...``). ``--carry RECORD`` puts an earlier record's curves ahead
of the runs' (an algorithm added to a comparison whose other runs' folders are on
another machine; the levels are then set by the record's first curve). The minutes are
the runs' own logged wall time: compare them only between runs that shared the machine
alike.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

WINDOWS = 40  # points of each curve


def curve(run: Path) -> dict:
    """The mean over the seeds of the episode scores and of the wall time, on a common
    grid of transitions (the range every seed covers)."""
    import numpy as np

    from beacon_torch.training.evaluation import read_scalar
    from beacon_torch.training.run import load_checkpoint, seed_dirs

    seeds = seed_dirs(run)
    scores = [read_scalar(s, "episode_score") for s in seeds]
    clocks = [read_scalar(s, "wall_time") for s in seeds]
    end = min(int(steps[-1]) for steps, _ in scores)
    start = max(int(steps[0]) for steps, _ in scores)
    grid = np.linspace(start, end, WINDOWS)
    # a window's mean, not the noisy last episode: each seed's scores binned on the grid
    edges = np.concatenate(([0.0], 0.5 * (grid[1:] + grid[:-1]), [np.inf]))
    binned = []
    for steps, values in scores:
        which = np.digitize(steps, edges) - 1
        means = np.array([values[which == k].mean() if (which == k).any() else np.nan for k in range(len(grid))])
        good = ~np.isnan(means)
        binned.append(np.interp(grid, grid[good], means[good]))
    minutes = np.mean([np.interp(grid, steps, values) for steps, values in clocks], 0) / 60.0
    state = load_checkpoint(seeds[0])
    return {
        "run": str(run),
        "algo": state["algo"],
        "env": state["env"],
        "params": state["config"].get("params", {}),
        "seeds": len(seeds),
        "transitions": grid.tolist(),
        "minutes": minutes.tolist(),
        "score": np.mean(binned, 0).tolist(),
        "spread": np.std(binned, 0).tolist(),
    }


# what a curve of a record holds: its numbers per point, and the rest
CURVE_SERIES = ("transitions", "minutes", "score", "spread")


def carried(path: str) -> list[dict]:
    """The curves of an earlier record of this script (read as received data), each
    with its series of equal length and finite numbers; a one-line error for any other
    file."""
    from beacon_torch import received

    record = received.json_file(path, "learning record")
    rows = record.get("rows") if isinstance(record, dict) else None
    if not isinstance(rows, list) or len(rows) < 2:
        raise ValueError(f"{path}: not a record of experiments/learning.py (no curves)")
    for k, c in enumerate(rows[1:]):
        where = f"{path}: curve {k}"
        if not isinstance(c, dict) or not all(isinstance(c.get(key), str) for key in ("algo", "env")):
            raise ValueError(f"{where} names no algorithm and env")
        if not isinstance(c.get("params"), dict) or not isinstance(c.get("seeds"), int):
            raise ValueError(f"{where}: its parameters or seeds are not a record's")
        series = [c.get(key) for key in CURVE_SERIES]
        if not all(isinstance(v, list) and v and len(v) == len(series[0]) for v in series) or not all(
            received.finite_number(x) for v in series for x in v
        ):
            raise ValueError(f"{where}: its {', '.join(CURVE_SERIES)} are not series of finite numbers of one length")
        c.setdefault("record", Path(path).name)
    return rows[1:]


def first_reaching(c: dict, level: float) -> tuple[float, float]:
    """Transitions and minutes at which the curve first reaches ``level`` (NaN if never)."""
    for n, m, s in zip(c["transitions"], c["minutes"], c["score"], strict=True):
        if s >= level:
            return n, m
    return float("nan"), float("nan")


def main() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import beacon_torch
    from beacon_torch import episodes
    from beacon_torch.files import create_file, refuse_existing, save_rows

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", help="folders of seeds, the first one setting the levels")
    parser.add_argument("--carry", metavar="RECORD", help="an earlier record whose curves go ahead of the runs'")
    parser.add_argument("--figure", required=True, help="a new PNG file")
    parser.add_argument("--out", default="runs/learning")
    args = parser.parse_args()
    refuse_existing([args.figure], "give another --figure")
    try:
        curves = (carried(args.carry) if args.carry else []) + [curve(Path(run)) for run in args.runs]
    except (ValueError, FileNotFoundError) as err:
        parser.error(str(err))
    trained = {(c["env"], json.dumps(c["params"], sort_keys=True)) for c in curves}
    if len(trained) > 1:
        raise SystemExit(f"the runs were trained on different envs or parameters: {sorted(trained)}")
    env_id, params = curves[0]["env"], curves[0]["params"]
    # float32 and from the developed start, as the runs trained
    env = beacon_torch.make(env_id, 1, params=params or None)
    free = float(episodes.scores(episodes.episode(env, episodes.null_policy(env)))[0])
    final = curves[0]["score"][-1]
    rows = []
    print(f"no control {free:.3f}; {curves[0]['algo']}'s final score {final:.3f}")
    for fraction in (0.5, 0.9):
        level = free + fraction * (final - free)
        for c in curves:
            n, m = first_reaching(c, level)
            rows.append({"algo": c["algo"], "fraction": fraction, "level": level, "transitions": n, "minutes": m})
            print(f"{c['algo']}: {fraction:.0%} of the way ({level:.3f}) at {n:,.0f} transitions, {m:.1f} minutes")
    fig, (by_data, by_time) = plt.subplots(1, 2, figsize=(10.0, 3.8), sharey=True)
    for k, c in enumerate(curves):
        label = f"{c['algo']} ({c['seeds']} seed{'s' if c['seeds'] > 1 else ''})"
        low = [s - d for s, d in zip(c["score"], c["spread"], strict=True)]
        high = [s + d for s, d in zip(c["score"], c["spread"], strict=True)]
        for ax, x in ((by_data, c["transitions"]), (by_time, c["minutes"])):
            ax.plot(x, c["score"], color=f"C{k}", label=label)
            ax.fill_between(x, low, high, color=f"C{k}", alpha=0.2, lw=0)
    for ax, name in ((by_data, "transitions"), (by_time, "wall-clock minutes (as logged)")):
        ax.axhline(free, color="k", ls="--", lw=1, label="no control")
        ax.set_xlabel(name)
        ax.grid(alpha=0.3)
    by_data.set_ylabel("episode score")
    by_data.legend(fontsize=8)
    fig.tight_layout()
    print("figure:", create_file(args.figure, lambda tmp: fig.savefig(tmp, dpi=110, format="png")))
    record = [{"uncontrolled": free, "levels": rows}, *curves]
    print("results:", save_rows(record, args.out, f"{env_id.removesuffix('-v0')}_learning"))


if __name__ == "__main__":
    main()
