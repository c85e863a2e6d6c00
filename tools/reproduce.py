"""Reproduce the paper's training results: train, evaluate and plot each (algorithm,
env) over several seeds, then publish what was reached: the summary recorded in
``docs/results/``, the curve in ``docs/img/results/``, the best seed's policy shipped
with the package, and ``docs/results.md`` and the comparison of ``docs/gradients.md``
written from every recorded summary.

    python tools/reproduce.py train --algo ppo --envs lorenz-v0 vortex-v0 --seeds 3
    python tools/reproduce.py summarise runs/results/ppo/lorenz-v0   # evaluate again
    python tools/reproduce.py publish runs/results/ppo/lorenz-v0     # into the repository
    python tools/reproduce.py page        # docs/results.md from the recorded summaries

``train`` and ``summarise`` write inside ``--out`` only: a run goes to
``runs/results/ALGO/ENV/seedK`` (``beacon-torch eval/plot`` read it too), the
seeds' evaluation to ``summary.json`` and their curve to ``ENV.png`` beside
them. A stopped campaign is resumed by running the same command again (finished seeds
are skipped, unfinished ones resume from their checkpoint). Only ``publish`` writes
into the repository, and only a pair trained on at least the recorded budget (that of
the pair's recorded summary, else its settings' default), so that a short trial never
replaces a shipped policy or a recorded result. What it publishes (the pair, the
algorithm, the transitions, the scores) is read from the seeds' checkpoints and
evaluated again; a summary that says otherwise is refused.
"""

from __future__ import annotations

import argparse
import json
import math
import os
from pathlib import Path

from beacon_torch import files, pretrained, received, threads
from beacon_torch.arguments import find_user_modules, load_script, positive
from beacon_torch.registry import ENVS, env_spec
from beacon_torch.training import report
from beacon_torch.training.config import CONFIGS, configure, paper_frames, quiet_torchrl
from beacon_torch.training.evaluation import plot_runs, summarise, summary_of
from beacon_torch.training.run import CHECKPOINT, holds_run, load_checkpoint, seed_dirs

ROOT = Path(__file__).resolve().parents[1]
RECIPES = ROOT / "recipes"
IMAGES = ROOT / "docs" / "img" / "results"
SHIPPED = ROOT / "beacon_torch" / "pretrained"  # the checkout's, not an installed copy's
RECORDED = ROOT / "docs" / "results"  # the summaries the results page is written from
BEGIN, END = "<!-- results table: tools/reproduce.py page -->", "<!-- end of results table -->"


def load_recipe(algo: str):
    """The recipe script ``recipes/ALGO.py`` as a module of its own, loaded from its file:
    the driver is a script, and the repository's root is not on its import path."""
    return load_script(RECIPES / f"{algo}.py", f"recipe_{algo}")


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


# the settings train_pair gives each seed's run itself
DRIVER_SETTINGS = ("seed", "out", "resume", "progress")


def train_pair(
    algo: str, env_id: str, seeds: int, overrides: dict, *, out: Path, num_envs: int, progress: bool
) -> dict:
    """Train the missing seeds of one (algorithm, env) pair and summarise it, inside
    ``out``."""
    recipe = load_recipe(algo)
    root = out / algo / env_id
    for seed in range(seeds):
        run = root / f"seed{seed}"
        started = (run / CHECKPOINT).is_file()
        if not started and holds_run(run, algo):
            raise ValueError(f"{run}: a seed stopped before its first checkpoint; remove the folder to train it again")
        cfg = configure(CONFIGS[algo], env_id, **overrides, seed=seed, out=str(run), resume=started, progress=progress)
        if not (run / CHECKPOINT).is_file() or load_checkpoint(run)["frames"] < cfg.frames:
            recipe.main(cfg)
    return summarise(root, num_envs=num_envs)


def read_summary(file: Path) -> dict:
    """A summary written by ``summarise``, checked (``report.read``; an env without a
    reference on its card is recorded all the same) and of a known algorithm. Its
    paths are not used: files are found by the pair's name."""
    summary = report.read(file, scored=False)
    if summary["algo"] not in CONFIGS:
        raise ValueError(f"{file}: unknown algorithm {summary['algo']!r}; known: {', '.join(sorted(CONFIGS))}")
    return summary


def recorded_budget(algo: str, env_id: str, recorded: Path = RECORDED) -> int:
    """The transitions a pair must have been trained on to be published: those of its
    recorded summary, else its settings' default budget."""
    file = recorded / algo / f"{env_id}.json"
    if file.is_file():
        return int(read_summary(file)["frames"])
    return configure(CONFIGS[algo], env_id).frames


# what publish compares between a summary and its re-evaluation: the pair, the seeds
# and their transitions exactly, scores and times to float rounding
EXACT = ("algo", "env", "frames")
CLOSE = ("eval_mean", "train_mean", "wall_s_per_seed", "uncontrolled", "test_mean", "test_uncontrolled")
PER_SEED_EXACT = ("seed", "frames", "curve")
PER_SEED_CLOSE = ("eval", "train_tail", "uncontrolled", "wall_s", "test", "test_uncontrolled")


def _same(a, b) -> bool:
    """Whether a summary's number ``a`` is the re-evaluated ``b`` (NaN only as NaN)."""
    if not isinstance(a, (int, float)) or isinstance(a, bool):
        return False
    if isinstance(b, float) and math.isnan(b):
        return isinstance(a, float) and math.isnan(a)
    return received.finite_number(a) and math.isclose(a, b, rel_tol=1e-6, abs_tol=1e-9)


def _exact(a, b) -> bool:
    return type(a) is type(b) and a == b


def mismatch(summary: dict, actual: dict) -> str:
    """The first field in which ``summary`` differs from ``actual`` (the re-evaluation
    of its seeds), as a phrase, or ""."""
    for key in EXACT:
        if not _exact(summary.get(key), actual[key]):
            return f"its {key} {summary.get(key)!r} is not its seeds' ({actual[key]!r})"
    seeds = summary.get("seeds")
    if not isinstance(seeds, list) or not all(isinstance(seed, dict) for seed in seeds):
        return "its seeds are not a list of records"
    given = {seed.get("seed"): seed for seed in seeds if isinstance(seed.get("seed"), str)}
    if sorted(given) != [seed["seed"] for seed in actual["seeds"]] or len(given) != len(seeds):
        names = ", ".join(seed["seed"] for seed in actual["seeds"])
        return f"its seeds {sorted(given)} are not the run's ({names})"
    for seed in actual["seeds"]:
        mine = given[seed["seed"]]
        for key in (*PER_SEED_EXACT, *PER_SEED_CLOSE):
            same = _exact(mine.get(key), seed[key]) if key in PER_SEED_EXACT else _same(mine.get(key), seed[key])
            if not same:
                return f"{seed['seed']}'s {key} {mine.get(key)!r} is not what its checkpoint gives ({seed[key]!r})"
    for key in CLOSE:
        if not _same(summary.get(key), actual[key]):
            return f"its {key} {summary.get(key)!r} is not what its seeds give ({actual[key]!r})"
    return ""


def publish(root: Path, recorded: Path = RECORDED, images: Path = IMAGES, shipped: Path = SHIPPED) -> Path:
    """Publish a summarised pair (``root``, holding ``summary.json`` and its seeds): its
    summary into ``recorded``, its curve into ``images``, its best seed's policy into
    ``shipped`` (the checkout's package). Nothing is taken from the summary on trust:
    the pair, the algorithm, the budget and the scores are those of the seeds'
    checkpoints, evaluated again, and a summary that says otherwise is refused; so is
    a pair below the recorded budget. Returns the recorded summary's file."""
    root = Path(root)
    file = root / "summary.json"
    summary = read_summary(file)
    actual = summary_of(root, num_envs=summary.get("num_envs", 8) if isinstance(summary.get("num_envs"), int) else 8)
    wrong = mismatch(summary, actual)
    if wrong:
        raise ValueError(f"{file}: {wrong}; summarise it again")
    algo, env_id = actual["algo"], actual["env"]
    if algo not in CONFIGS:
        raise ValueError(f"{file}: a pair of {algo!r}, which has no recipe to record")
    budget = recorded_budget(algo, env_id, recorded)
    if actual["frames"] < budget:
        raise ValueError(
            f"{root}: trained on {actual['frames']:,} transitions, below the recorded budget of "
            f"{algo} on {env_id} ({budget:,}); not published"
        )
    seeds = {run.name: run for run in seed_dirs(root)}
    (recorded / algo).mkdir(parents=True, exist_ok=True)
    (images / algo).mkdir(parents=True, exist_ok=True)
    # the curve drawn again from the seeds' logs, not copied from the pair's folder
    copy = plot_runs([root], images / algo / f"{env_id}.png")
    actual["png"] = (
        os.path.relpath(copy.resolve(), ROOT) if copy.resolve().is_relative_to(ROOT) else str(copy.resolve())
    )
    best = max(actual["seeds"], key=lambda s: s["eval"])
    policy = shipped / algo / f"{env_id}.pt"
    policy.parent.mkdir(parents=True, exist_ok=True)
    pretrained.export(
        seeds[best["seed"]],
        policy,
        seed=best["seed"],
        score=best["eval"],
        uncontrolled=best["uncontrolled"],
    )
    return files.write_text(recorded / algo / f"{env_id}.json", json.dumps(actual, indent=1))


def results_block(recorded: Path, page: Path, images: Path) -> str:
    """The results page's generated part: the protocol's figure and table over every
    recorded summary its envs' cards can normalise, the others' own scores, the PPO
    floors, and the curves."""
    rel = lambda path: os.path.relpath(Path(path).resolve(), page.resolve().parent)
    files = sorted(recorded.glob("*/*.json"))
    everyone = [read_summary(f) for f in files]
    scored = [report.normalisable(s["env"]) for s in everyone]
    summaries = [s for s, ok in zip(everyone, scored, strict=True) if ok]
    names = [images / f"report.{suffix}" for suffix in ("md", "json", "png")]
    protocol = []
    if summaries:
        # every pair on the paper's episodes, where all are recorded and comparable
        rows = report.report([f for f, ok in zip(files, scored, strict=True) if ok], *names, starts="own", replace=True)
        protocol = [f"![normalised scores]({rel(rows['png'])})", rows["table"]]
    held = [report.row(s, "test") for s in summaries if report.test_scaled(s)]
    test_table = (
        "On the held-out test set's 8 developed starts (one episode each; 0 = no control from "
        "the same states, 1 = the env's reference, the same score as on its own start or, for a share of no "
        "control, the same share), the pairs recorded with them:\n\n" + report.table(held)
        if held
        else "No recorded pair has test-set scores yet."
    )
    unscaled = [s for s in summaries if report.held_out(s) and not report.test_scaled(s)]
    if unscaled:
        test_table += (
            "\n\nNot normalised on the test set, where no control from the developed starts already scores "
            "above the reference (the scale would run backwards): "
            + "; ".join(
                f"{s['algo']}/{s['env']} {report.iqm([seed['test'] for seed in s['seeds']]):.4g} "
                f"against {s['test_uncontrolled']:.4g} uncontrolled (reference "
                f"{report.reference(s['env'], s['test_uncontrolled']):g})"
                for s in unscaled
            )
            + "."
        )
    floors = [
        "| env | PPO floor | training episodes from the own start, last tenth (mean over seeds) | best seed's "
        "deterministic policy, own start | transitions (of the paper's budget) | floor met |",
        "|---|---|---|---|---|---|",
    ]
    for s in summaries:
        if (
            s["algo"] == "ppo"
            and env_spec(s["env"]).base_id() == s["env"]
            and env_spec(s["env"]).card.paper_ppo is not None
        ):
            floor, best = env_spec(s["env"]).card.paper_ppo, max(seed["eval"] for seed in s["seeds"])
            met = "met" if s["train_mean"] >= floor and best >= floor else "**missed**"
            floors.append(
                f"| {s['env']} | {floor:g} | {s['train_mean']:.4g} | {best:.4g} | {s['frames']:,} "
                f"of {paper_frames(s['env']):,} | {met} |"
            )
    curves = ", ".join(f"[{s['algo']}/{s['env']}]({rel(images / s['algo'] / (s['env'] + '.png'))})" for s in everyone)
    return "\n\n".join(
        [
            *protocol,
            test_table,
            *unnormalised([s for s, ok in zip(everyone, scored, strict=True) if not ok]),
            "\n".join(floors),
            f"Curves: {curves}.",
        ]
    )


def unnormalised(summaries: list[dict]) -> list[str]:
    """The recorded pairs of envs without a reference on their card: their own
    scores beside no control, for the env's page to set against its reference."""
    if not summaries:
        return []
    lines = [
        "Recorded, not normalised: their envs have no reference on the card (each env's page sets the "
        "scores beside its own reference):",
        "",
        "| env | algorithm | episodes | seeds | score, IQM (per seed) | uncontrolled | transitions "
        "| wall time per seed |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for s in sorted(summaries, key=lambda s: (s["algo"], s["env"])):
        scores = [seed["eval"] for seed in s["seeds"]]
        lines.append(
            f"| {s['env']} | {s['algo']} | {report.EPISODES['own']} | {len(scores)} | {report.iqm(scores):.4g} "
            f"({', '.join(f'{x:.4g}' for x in scores)}) | {s['uncontrolled']:.4g} | {s['frames']:,} "
            f"| {s['wall_s_per_seed'] / 60:.1f} min |"
        )
    return ["\n".join(lines)]


def write_results_page(recorded: Path, page: Path, images: Path) -> Path:
    """Write the generated part between the markers of the results page (appended when
    they are missing)."""
    return report.write_block(page, BEGIN, END, results_block(recorded, page, images))


def write_comparison() -> Path:
    """Redraw the model-free against gradient-based comparison of docs/gradients.md,
    which reads the same recorded summaries as the results page."""
    comparison = load_script(ROOT / "experiments" / "comparison.py", "experiments_comparison")
    page = ROOT / "docs" / "gradients.md"
    comparison.draw(page.parent / "img" / "comparison.png")
    return report.write_block(page, comparison.BEGIN, comparison.END, comparison.table())


def evaluation_threads(given: int | None, root: str | Path, batch: int) -> None:
    """Torch's threads for evaluating the pair ``root``: ``given``, else the count
    measured fastest for its env at the evaluation's batch."""
    threads.use(given, load_checkpoint(seed_dirs(root)[0])["env"], batch)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    tr = sub.add_parser("train", help="train, evaluate and plot (algorithm, env) pairs, inside --out")
    tr.add_argument("--algo", default="ppo", choices=sorted(CONFIGS), help="the recipe (default: ppo)")
    tr.add_argument("--envs", nargs="+", required=True, choices=sorted(ENVS), metavar="ENV", help="env ids")
    tr.add_argument("--seeds", type=positive, default=3, help="seeds per env, 0 to N-1 (default: 3)")
    tr.add_argument(
        "--set",
        type=setting,
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a recipe setting for every env (e.g. frames=100000)",
    )
    tr.add_argument(
        "--eval-episodes", type=positive, default=8, help="evaluation episodes per seed, one batch (default: 8)"
    )
    tr.add_argument(
        "--threads", type=positive, help="torch threads of every run (default: each recipe's, see beacon_torch.threads)"
    )
    tr.add_argument("--no-progress", action="store_true", help="no progress bars (campaigns in the background)")
    tr.add_argument("--out", default="runs/results", help="where the runs go (default: runs/results)")
    su = sub.add_parser("summarise", help="evaluate and plot trained pairs again (e.g. after a stopped campaign)")
    su.add_argument("pairs", nargs="+", help="run directories, e.g. runs/results/ppo/burgers-v0")
    su.add_argument(
        "--eval-episodes", type=positive, default=8, help="evaluation episodes per seed, one batch (default: 8)"
    )
    pu = sub.add_parser(
        "publish", help="record summarised pairs in docs/results/, ship their best policies and write docs/results.md"
    )
    pu.add_argument("pairs", nargs="+", help="summarised run directories, e.g. runs/results/ppo/burgers-v0")
    pu.add_argument("--doc", default=str(ROOT / "docs" / "results.md"), help="the results page to write")
    for evaluating in (su, pu):
        evaluating.add_argument(
            "--threads", type=positive, help="torch threads of the evaluations (default: the env's measured fastest)"
        )
    page = sub.add_parser("page", help="write docs/results.md from the recorded summaries (docs/results/)")
    page.add_argument("--doc", default=str(ROOT / "docs" / "results.md"), help="the results page to write")
    args = parser.parse_args(argv)
    find_user_modules()
    quiet_torchrl()
    try:
        if args.command == "summarise":
            for root in args.pairs:
                evaluation_threads(args.threads, root, args.eval_episodes)
                summarise(root, num_envs=args.eval_episodes)
            return
        if args.command == "train":
            overrides = {name: text_value(value) for name, value in args.set}
            if args.threads:  # each seed's run sets it again from its settings
                overrides["threads"] = args.threads
            taken = sorted(set(overrides) & set(DRIVER_SETTINGS))
            if taken:
                parser.error(f"--set {taken[0]}: the driver sets it for each seed ({', '.join(DRIVER_SETTINGS)})")
            for env_id in args.envs:
                train_pair(
                    args.algo,
                    env_id,
                    args.seeds,
                    overrides,
                    out=Path(args.out),
                    num_envs=args.eval_episodes,
                    progress=not args.no_progress,
                )
            return
        if args.command == "publish":
            for root in args.pairs:
                evaluation_threads(args.threads, root, 8)
                print(f"published {root}: {publish(Path(root))}")
        print(write_results_page(RECORDED, Path(args.doc), IMAGES))
        if Path(args.doc).resolve() == (ROOT / "docs" / "results.md").resolve():
            print(write_comparison())
    except (ValueError, OSError) as err:
        parser.exit(2, f"reproduce: error: {err}\n")


if __name__ == "__main__":
    main()
