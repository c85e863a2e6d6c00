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
import shutil
from pathlib import Path

import torch

from beacon_torch import pretrained
from beacon_torch.training import report
from beacon_torch.training.evaluation import summarise
from beacon_torch.training.report import PAPER_PPO
from beacon_torch.training.run import CHECKPOINT, load_checkpoint

from config import CONFIGS, configure, paper_frames

ROOT = Path(__file__).resolve().parents[1]
IMAGES = ROOT / "docs" / "img" / "results"
RECORDED = ROOT / "docs" / "results"  # the summaries the results page is written from
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
    """Train the missing seeds of one (algorithm, env) pair, summarise it and ship its
    best seed's policy."""
    recipe = importlib.import_module(algo)
    root = out / f"{algo}-{env_id}"
    for seed in range(seeds):
        run = root / f"seed{seed}"
        started = (run / CHECKPOINT).is_file()
        cfg = configure(CONFIGS[algo], env_id, **overrides, seed=seed, out=str(run), resume=started, progress=progress)
        if not started or load_checkpoint(run)["frames"] < cfg.frames:
            recipe.main(cfg)
    summary = summarise(root, members=members, images=images)
    ship(root)
    return summary


def record(out: Path, recorded: Path = RECORDED, images: Path = IMAGES) -> list[Path]:
    """Copy every ``out/*/summary.json`` into the repository's record of summaries
    (``docs/results/ALGO-ENV.json``) and its curve into ``images``, so that the results
    page can be written again without the runs."""
    recorded.mkdir(parents=True, exist_ok=True)
    images.mkdir(parents=True, exist_ok=True)
    written = []
    for file in sorted(Path(out).glob("*/summary.json")):
        summary = json.loads(file.read_text())
        png = Path(summary["png"])
        if png.resolve() != (images / png.name).resolve():
            shutil.copyfile(png, images / png.name)
        copy = (images / png.name).resolve()
        summary["png"] = str(copy.relative_to(ROOT) if copy.is_relative_to(ROOT) else copy)
        target = recorded / f"{summary['algo']}-{summary['env']}.json"
        target.write_text(json.dumps(summary, indent=1))
        written.append(target)
    return written


def ship(root: Path) -> Path:
    """The best seed's policy of a trained pair (by its deterministic evaluation) as the
    package's pretrained policy of that pair."""
    summary = json.loads((root / "summary.json").read_text())
    best = max(summary["seeds"], key=lambda s: s["eval"])
    path = pretrained.path_of(summary["algo"], summary["env"])
    return pretrained.export(root / best["seed"], path, seed=best["seed"], score=best["eval"], uncontrolled=best["uncontrolled"])


def results_block(recorded: Path, page: Path, images: Path) -> str:
    """The results page's generated part: the protocol's figure and table over every
    recorded summary, the PPO floors, and the curves."""
    summaries = [json.loads(f.read_text()) for f in sorted(recorded.glob("*.json"))]
    rows = report.report(sorted(recorded.glob("*.json")), images)
    rel = lambda path: os.path.relpath(ROOT / path, page.resolve().parent)  # recorded paths are the repository's
    floors = ["| env | PPO floor | training episodes, last tenth (mean over seeds) | best seed's deterministic policy | transitions (of the paper's budget) | floor met |", "|---|---|---|---|---|---|"]
    for s in summaries:
        if s["algo"] == "ppo" and s["env"] in PAPER_PPO:
            floor, best = PAPER_PPO[s["env"]], max(seed["eval"] for seed in s["seeds"])
            met = "met" if s["train_mean"] >= floor and best >= floor else "**missed**"
            floors.append(f"| {s['env']} | {floor:g} | {s['train_mean']:.4g} | {best:.4g} | {s['frames']:,} of {paper_frames(s['env']):,} | {met} |")
    curves = ", ".join(f"[{s['algo']} {s['env']}]({rel(s['png'])})" for s in summaries)
    return "\n\n".join([f"![normalised scores]({rel(rows['png'])})", rows["table"], "\n".join(floors), f"Curves: {curves}."])


def write_results_page(recorded: Path, page: Path, images: Path) -> Path:
    """Write the generated part between the markers of the results page (appended when
    they are missing)."""
    return report.write_block(page, BEGIN, END, results_block(recorded, page, images))


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
    rep = sub.add_parser("report", help="record the summaries of --out in docs/results/ and write docs/results.md from every recorded one")
    rep.add_argument("--out", default="runs/results")
    rep.add_argument("--doc", default=str(ROOT / "docs" / "results.md"))
    rep.add_argument("--images", default=str(IMAGES))
    args = parser.parse_args(argv)
    if args.command == "report":
        record(Path(args.out))
        print(write_results_page(RECORDED, Path(args.doc), Path(args.images)))
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
