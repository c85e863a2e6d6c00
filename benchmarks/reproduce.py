"""Reproduce the paper's training results: train, evaluate and plot each (algorithm,
env) over several seeds, then write ``docs/results.md`` from what was recorded.

    python benchmarks/reproduce.py train --algo ppo --envs lorenz-v0 vortex-v0 --seeds 3
    python benchmarks/reproduce.py summarise runs/results/ppo-lorenz-v0   # evaluate again
    python benchmarks/reproduce.py report          # docs/results.md and its curves

A run goes to ``runs/results/<algo>-<env>/seedK`` (the CLI's layout, so that
``beacon-torch eval/plot`` read it too); a stopped campaign is resumed by running the
same command again (finished seeds are skipped, unfinished ones resume from their
checkpoint). After the seeds of a pair, their deterministic-policy evaluation goes to
``runs/results/<algo>-<env>/summary.json`` and the curve to ``docs/img/results/``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from beacon_torch.cli import _parse_params  # noqa: E402
from beacon_torch.recipes import dqn, gradient_control, ppo, td3  # noqa: E402
from beacon_torch.recipes.common import load_checkpoint  # noqa: E402
from beacon_torch.recipes.config import grad_config, off_policy_config, ppo_config  # noqa: E402
from beacon_torch.recipes.runs import summarise, write_results_table  # noqa: E402

RECIPES = {"ppo": (ppo_config, ppo.train), "td3": (off_policy_config, td3.train), "dqn": (off_policy_config, dqn.train), "grad": (grad_config, gradient_control.train)}
IMAGES = ROOT / "docs" / "img" / "results"


def train_pair(algo: str, env_id: str, args) -> dict:
    configure, recipe = RECIPES[algo]
    cfg = configure(env_id, **_parse_params(args.set))
    root = Path(args.out) / f"{algo}-{env_id}"
    for seed in range(args.seeds):
        run = root / f"seed{seed}"
        done = (run / "checkpoint.pt").is_file() and load_checkpoint(run)["frames"] >= cfg.frames
        if not done:
            recipe(env_id, cfg, run, seed=seed, resume=(run / "checkpoint.pt").is_file(), progress=not args.no_progress)
    return summarise(root, members=args.members, images=args.images)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    tr = sub.add_parser("train", help="train, evaluate and plot (algorithm, env) pairs")
    tr.add_argument("--algo", default="ppo", choices=sorted(RECIPES))
    tr.add_argument("--envs", nargs="+", required=True)
    tr.add_argument("--seeds", type=int, default=3)
    tr.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="a recipe setting for every env (e.g. frames=100000)")
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
    args = parser.parse_args()
    if args.command == "report":
        print(write_results_table(Path(args.out), Path(args.doc)))
        return
    if args.command == "summarise":
        for root in args.pairs:
            summarise(root, members=args.members, images=args.images)
        return
    if args.threads:
        torch.set_num_threads(args.threads)
    for env_id in args.envs:
        train_pair(args.algo, env_id, args)


if __name__ == "__main__":
    main()
