"""Reproduce the paper's training results: train, evaluate and plot each (algorithm,
env) over several seeds, then write ``docs/results.md`` from what was recorded.

    python recipes/reproduce.py train --algo ppo --envs lorenz-v0 vortex-v0 --seeds 3
    python recipes/reproduce.py summarise runs/results/ppo-lorenz-v0   # evaluate again
    python recipes/reproduce.py report          # docs/results.md and its curves

A run goes to ``runs/results/<algo>-<env>/seedK`` (``beacon-torch eval/plot`` read it
too); a stopped campaign is resumed by running the same command again (finished seeds
are skipped, unfinished ones resume from their checkpoint). After the seeds of a pair,
their deterministic-policy evaluation goes to ``runs/results/<algo>-<env>/summary.json``
and the curve to ``docs/img/results/``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
from pathlib import Path

import torch

from beacon_torch.training.evaluation import summarise
from beacon_torch.training.run import CHECKPOINT, load_checkpoint

from config import CONFIGS, PPO_TARGETS, configure, paper_frames

ROOT = Path(__file__).resolve().parents[1]
IMAGES = ROOT / "docs" / "img" / "results"
BEGIN, END = "<!-- results table: recipes/reproduce.py report -->", "<!-- end of results table -->"


def setting(item: str) -> tuple[str, str]:
    name, sep, value = item.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"--set expects NAME=VALUE, got {item!r}")
    return name.strip(), value.strip()


def text_value(text: str):
    """A setting's value as a number where it reads as one (``configure`` types it)."""
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


def train_pair(algo: str, env_id: str, seeds: int, overrides: dict, *, out: Path, members: int, images: Path, progress: bool) -> dict:
    """Train the missing seeds of one (algorithm, env) pair, then summarise it."""
    recipe = importlib.import_module(algo)
    root = out / f"{algo}-{env_id}"
    for seed in range(seeds):
        run = root / f"seed{seed}"
        started = (run / CHECKPOINT).is_file()
        cfg = configure(CONFIGS[algo], env_id, **overrides, seed=seed, out=str(run), resume=started, progress=progress)
        if not started or load_checkpoint(run)["frames"] < cfg.frames:
            recipe.main(cfg)
    return summarise(root, members=members, images=images)


def write_results_table(out: str | Path, path: str | Path) -> Path:
    """The table of every ``out/*/summary.json`` with the PPO targets, written between
    the table markers of the markdown file ``path`` (appended if they are missing).
    Rows already in the table for (env, algorithm) pairs that have no summary in
    ``out`` are kept: a campaign adds to the recorded results without their runs."""
    out, path = Path(out), Path(path)
    text = path.read_text() if path.exists() else ""
    rows = {}
    if BEGIN in text:
        for line in text[text.index(BEGIN) : text.index(END)].splitlines():
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if line.startswith("|") and len(cells) > 2 and cells[0] not in ("env", "---"):
                rows[(cells[1].split()[0], cells[0])] = line
    for file in sorted(out.glob("*/summary.json")):
        s = json.loads(file.read_text())
        target = PPO_TARGETS.get(s["env"]) if s["algo"] == "ppo" else None
        met = "" if target is None else ("met" if s["eval_mean"] >= target else "**missed**")
        spread = (lambda key, s=s: f" +- {s[key]:.2g}") if len(s["seeds"]) > 1 else (lambda key: "")
        # runs from before the normalisation statistics became a setting used 16 steps
        algo = s["algo"] + (" (16-step norm.)" if s["config"].get("norm_steps", 16) != 64 else "")
        rows[(s["algo"], s["env"])] = (
            f"| {s['env']} | {algo} | {s['eval_mean']:.4g}{spread('eval_std')} | {s['train_mean']:.4g}{spread('train_std')} | "
            f"{s['uncontrolled']:.4g} | {'' if target is None else f'>= {target:g} ({met})'} | {len(s['seeds'])} | {s['frames']:,} of {paper_frames(s['env']):,} | "
            f"{s['wall_s_per_seed'] / 60:.1f} min | [curve]({os.path.relpath(s['png'], path.resolve().parent)}) |"
        )
    table = "\n".join(
        [
            "| env | algorithm | deterministic policy | training episodes, last 10 % | uncontrolled (same env) | PPO target | seeds "
            "| transitions (of the paper's budget) | wall time per seed | curve |",
            "|---|---|---|---|---|---|---|---|---|---|",
            *(rows[key] for key in sorted(rows)),
        ]
    )
    block = f"{BEGIN}\n{table}\n{END}"
    if BEGIN in text:
        text = text[: text.index(BEGIN)] + block + text[text.index(END) + len(END) :]
    else:
        text = text + "\n" + block + "\n"
    path.write_text(text)
    return path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    tr = sub.add_parser("train", help="train, evaluate and plot (algorithm, env) pairs")
    tr.add_argument("--algo", default="ppo", choices=sorted(CONFIGS))
    tr.add_argument("--envs", nargs="+", required=True)
    tr.add_argument("--seeds", type=int, default=3)
    tr.add_argument("--set", type=setting, action="append", default=[], metavar="NAME=VALUE", help="a recipe setting for every env (e.g. frames=100000)")
    tr.add_argument("--members", type=int, default=8, help="evaluation episodes per seed")
    tr.add_argument("--threads", type=int, help="torch threads (default: torch's)")
    tr.add_argument("--no-progress", action="store_true")
    tr.add_argument("--out", default="runs/results")
    tr.add_argument("--images", default=str(IMAGES), help="where the curves go (default docs/img/results)")
    su = sub.add_parser("summarise", help="evaluate and plot trained pairs again (e.g. after a stopped campaign)")
    su.add_argument("pairs", nargs="+", help="run directories, e.g. runs/results/ppo-burgers-v0")
    su.add_argument("--members", type=int, default=8)
    su.add_argument("--images", default=str(IMAGES))
    rep = sub.add_parser("report", help="write the results table into docs/results.md")
    rep.add_argument("--out", default="runs/results")
    rep.add_argument("--doc", default=str(ROOT / "docs" / "results.md"))
    args = parser.parse_args(argv)
    if args.command == "report":
        print(write_results_table(Path(args.out), Path(args.doc)))
    elif args.command == "summarise":
        for root in args.pairs:
            summarise(root, members=args.members, images=args.images)
    else:
        if args.threads:
            torch.set_num_threads(args.threads)
        overrides = {name: text_value(value) for name, value in args.set}
        for env_id in args.envs:
            train_pair(args.algo, env_id, args.seeds, overrides, out=Path(args.out), members=args.members, images=Path(args.images), progress=not args.no_progress)


if __name__ == "__main__":
    main()
