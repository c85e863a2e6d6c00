"""The ``beacon-torch`` command.

    beacon-torch list                 the environment ids and their parameters
    beacon-torch run ENV [options]    an uncontrolled and a random-policy episode:
                                      scores, a plot, optionally an animation
    beacon-torch bench [options]      transitions per second against the published
                                      code: a table, CSV, JSON and a plot
    beacon-torch eval DIR             a trained policy's score against the
                                      uncontrolled one, and an animation
    beacon-torch plot DIR... --out P  learning curves, mean and std over seeds
    beacon-torch report DIR...        the benchmark protocol: normalised scores, their
                                      interquartile mean over seeds and its bootstrap
                                      interval, a table and a figure

An env registered by a module of your own (``beacon_torch.register``) is named
``module:env-id``, or its module imported first with ``beacon-torch --import module``;
modules are found from the working directory, as ``python -m`` finds them.

Training is the recipes' (``recipes/ppo.py``, ``td3.py``, ``sac.py``, ``dqn.py``, ``grad.py``, ``shac.py`` in the
repository); ``eval`` and ``plot`` read the run directories they write.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from beacon_torch.arguments import find_user_modules, plain, positive
from beacon_torch.files import create_file, outputs, save_figure

if TYPE_CHECKING:
    import torch

# Nothing here imports torch at the top: `--help` and `list` answer at once, and each
# command imports what it uses.

# the output of `list` for the package's own envs, written by docs/make_env_tables.py
# (the suite checks it is current)
LISTING = Path(__file__).parent / "data" / "envs.txt"


class CliError(Exception):
    """An error of the user's arguments: reported as one line, no traceback."""


def _parse_params(items: Sequence[str]) -> dict[str, Any]:
    from beacon_torch.params import parse_assignments

    try:
        return parse_assignments(items)
    except ValueError as err:
        raise CliError(str(err)) from None


def listing() -> str:
    """What `list` prints: every registered env, its action and observation sizes and
    episode length, and its parameters with their defaults, ranges and meanings."""
    from beacon_torch.params import describe
    from beacon_torch.registry import ENVS, list_envs

    lines = []
    for env_id in list_envs():
        spec = ENVS[env_id]
        physics = spec.physics
        # what the defaults resolve to (start: the published state), a variant's own included
        defaults = dataclasses.replace(physics.Params(), **spec.physical_defaults())
        n_obs, n_actions = physics.sizes(defaults)
        kind = f"{n_actions} discrete actions" if physics.discrete else f"{n_actions}-D continuous action"
        lines.append(f"{env_id}: {kind}, {n_obs} observations, {physics.episode_length} steps")
        for row in describe(physics.Params):
            lines.append(f"    {row['name']} = {getattr(defaults, row['name'])!r}  {row['range']}  {row['doc']}")
    return "\n".join(lines) + "\n"


def cmd_list(args: argparse.Namespace) -> int:
    # the package's envs alone: their listing is stored; envs of the user's own modules
    # are listed from their classes
    print(listing() if args.imports else LISTING.read_text(), end="")
    return 0


def _cumulative(rollout) -> torch.Tensor:
    """``[batch, steps]`` cumulative rewards of each member's episode, flat after its
    end (a member that blew up stops adding)."""
    import torch

    from beacon_torch import episodes

    rewards = episodes.step_rewards(rollout).cpu()
    done = rollout["next", "done"][..., 0].cpu().to(torch.int64)
    before = done.cumsum(-1) - done  # ends before each step
    return (rewards * (before == 0)).cumsum(-1)


def _plot_run(path: Path, env_id: str, null: torch.Tensor, rand: torch.Tensor) -> None:
    """The cumulative rewards of the uncontrolled member and of the random-policy batch
    (each over the steps its rollout took), into the new file ``path``."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 4), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.plot(range(1, null.shape[-1] + 1), null[0].numpy(), "k--", label="uncontrolled")
    mean, std = rand.mean(0).numpy(), rand.std(0, unbiased=False).numpy()
    steps = range(1, rand.shape[-1] + 1)
    ax.plot(steps, mean, color="C0", label=f"random policy (mean of {rand.shape[0]})")
    ax.fill_between(steps, mean - std, mean + std, color="C0", alpha=0.3, lw=0)
    ax.set_xlabel("actions")
    ax.set_ylabel("cumulative reward")
    ax.set_title(env_id)
    ax.grid(alpha=0.4)
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path, new=True)


def cmd_run(args: argparse.Namespace) -> int:
    from beacon_torch import episodes
    from beacon_torch.base import make
    from beacon_torch.registry import env_spec, resolve_id

    args.env = resolve_id(args.env)  # "module:env-id" registers it
    env_spec(args.env)  # an unknown id fails here, before anything is built
    if args.num_envs < 1:
        raise CliError(f"--num-envs must be a positive integer, got {args.num_envs}")
    if args.gif_every < 0:
        raise CliError(f"--gif-every must be a positive integer (0: about 100 frames), got {args.gif_every}")
    if args.gif is not None and Path(args.gif).suffix.lower() != ".gif":
        raise CliError(f"--gif {args.gif}: an animation is a GIF file, named *.gif")
    params = _parse_params(args.param)
    _threads(args, args.env, args.num_envs)
    kwargs = dict(device=args.device, dtype=args.dtype, seed=args.seed, params=params)
    plot, scores_file = outputs(args.out, f"runs/{args.env}", "run.png", "scores.json")
    gif = outputs(args.gif, None, option="--gif")[0] if args.gif else None
    plot.parent.mkdir(parents=True, exist_ok=True)
    from beacon_torch.files import Lock

    lock = Lock(plot.parent)  # a second run writing into the same folder is refused now, not at its end

    results = {}
    rewards = {}
    for name, batch in (("uncontrolled", 1), ("random", args.num_envs)):
        env = make(args.env, batch, **kwargs)
        policy = episodes.null_policy(env) if name == "uncontrolled" else episodes.random_policy(env, args.seed)
        start = time.perf_counter()
        rollout = episodes.episode(env, policy, progress=f"{args.env} {name}")
        elapsed = time.perf_counter() - start
        score = episodes.scores(rollout)
        rewards[name] = _cumulative(rollout)
        results[name] = dict(
            num_envs=batch,
            mean=score.mean().item(),
            std=score.std(unbiased=False).item(),
            min=score.min().item(),
            max=score.max().item(),
            transitions_per_s=batch * rollout.shape[-1] / elapsed,
        )
        r = results[name]
        spread = f" +- {r['std']:.4g} (min {r['min']:.4g}, max {r['max']:.4g})" if batch > 1 else ""
        print(
            f"{args.env} {name:>12}: score {r['mean']:.6g}{spread}"
            f"  [{batch} x {rollout.shape[-1]} steps in {args.dtype}, {r['transitions_per_s']:.0f} transitions/s]"
        )

    text = json.dumps({"env": args.env, "params": {k: str(v) for k, v in params.items()}, **results}, indent=2)
    create_file(scores_file, lambda tmp: tmp.write_text(text))
    _plot_run(plot, args.env, rewards["uncontrolled"], rewards["random"])
    print(f"plot: {plot}\nscores: {scores_file}")

    if gif is not None:
        from beacon_torch.render import save_animation

        env = make(args.env, 1, record_history=True, **kwargs)
        every = args.gif_every or max(1, env.episode_length // 100)
        frames = []
        env.reset()
        frames.append(env.render())

        def grab(step: int) -> None:
            if step % every == 0 and step < env.episode_length:
                frames.append(env.render())

        episodes.episode(env, episodes.null_policy(env), frame_hook=grab, progress=f"{args.env} animation")
        frames.append(env.render())  # the end of the episode, whatever the stride
        gif = save_animation(frames, gif)
        print(f"animation ({len(frames)} frames of the uncontrolled episode): {gif}")
    lock.release()
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from beacon_torch import bench
    from beacon_torch.core.checks import as_device
    from beacon_torch.registry import base_envs, env_spec, resolve_id

    envs = [resolve_id(env_id) for env_id in args.envs or base_envs()]
    for env_id in envs:
        env_spec(env_id)
    for b in args.num_envs or ():
        if b < 1:
            raise CliError(f"--num-envs must be positive integers, got {b}")
    for name in ("steps", "repeats"):
        if getattr(args, name) is not None and getattr(args, name) < 1:
            raise CliError(f"--{name} must be a positive integer, got {getattr(args, name)}")
    as_device(args.device)  # before any measuring process is started
    if args.threads:  # the measuring processes take this one's count
        _threads(args, None, 1)
    from beacon_torch.files import dated_name

    out = Path(args.out or Path("runs/bench") / dated_name("bench"))
    bench.check_out(out)
    results = bench.run(
        envs,
        num_envs=args.num_envs,
        dtypes=args.dtype,
        modes=args.mode,
        device=args.device,
        steps=args.steps,
        repeats=args.repeats,
    )
    paths = bench.write(results, out)
    print()
    print(bench.markdown(results))
    print(f"\nresults: {paths['csv']}, {paths['json']}\nplot: {paths['png']}")
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from beacon_torch.core.checks import as_device
    from beacon_torch.training.evaluation import evaluate_policy, evaluate_run
    from beacon_torch.training.run import load_checkpoint, seed_dirs

    if args.num_envs < 1:
        raise CliError(f"--num-envs must be a positive integer, got {args.num_envs}")
    as_device(args.device)  # before a policy is moved there
    if (args.run is None) == (args.pretrained is None):
        raise CliError("eval takes a run directory or --pretrained ALGO/ENV, one of the two")
    starts = None if args.starts == "own" else args.starts
    if args.pretrained is not None:
        from beacon_torch import pretrained

        try:
            algo, env_id = pretrained.split_name(args.pretrained)
        except ValueError as err:
            raise CliError(f"--pretrained: {err}") from None
        _threads(args, env_id, args.num_envs)
        policy = pretrained.load(args.pretrained, device=args.device)
        views = _views(args, args.out, ".", f"{algo}/{env_id}", "-")
        record = pretrained.info(args.pretrained)
        params = record.get("params", {})  # the physics it was trained on
        r = evaluate_policy(
            env_id,
            policy,
            num_envs=args.num_envs,
            device=args.device,
            params=params,
            starts=starts,
            progress=True,
            **views,
        )
        trained = f"trained on {record['frames']} transitions"
        runs = [(f"pretrained {algo}", r, trained)]
    else:
        runs = []
        _threads(args, load_checkpoint(seed_dirs(args.run)[0])["env"], args.num_envs)
        for run in seed_dirs(args.run):
            views = _views(args, None, run, "", "")
            r = evaluate_run(run, num_envs=args.num_envs, device=args.device, starts=starts, progress=True, **views)
            runs.append((str(run), r, f"trained on {r['frames']} transitions"))
    for name, r, trained in runs:
        written = [f"{what} {r[key]}" for key, what in VIEWS.items() if key in r]
        print(
            f"{r['env']} {name}: score {r['score_mean']:.6g} {_spread(r['score_std'], args.num_envs)} "
            f"(uncontrolled {r['uncontrolled']:.6g}; {trained}"
            + (f"; the {r['starts']} set's starts" if r["starts"] else "; the env's own start")
            + ")"
            + "".join(f"; {w}" for w in written)
        )
    return 0


# what eval writes, by evaluate_policy's keyword: how it says so, and its file's name
VIEWS = {"gif": "animation", "side_by_side": "beside no control", "figure": "diagnostics"}
NAMES = {"gif": ("controlled", ".gif"), "side_by_side": ("side-by-side", ".gif"), "figure": ("diagnostics", ".png")}


def _views(args: argparse.Namespace, given, default, stem: str, sep: str) -> dict:
    """The new files eval writes for one policy (the animations unless ``--no-gif``),
    named ``stem`` + ``sep`` + the view's name (``stem`` alone for the controlled
    animation of a pretrained policy), chosen before any work."""
    keys = [k for k in NAMES if k == "figure" or not args.no_gif]
    names = []
    for key in keys:
        name, suffix = NAMES[key]
        names.append(f"{stem}{suffix}" if stem and key == "gif" else f"{stem}{sep}{name}{suffix}")
    paths = outputs(given, default, *names)
    paths[0].parent.mkdir(parents=True, exist_ok=True)
    return dict(zip(keys, paths, strict=True))


def _threads(args: argparse.Namespace, env_id: str | None, batch: int) -> None:
    """Torch's threads for a command's episodes: ``--threads``, else the measured
    default for the env and batch (``beacon_torch.threads``)."""
    from beacon_torch import threads

    threads.use(args.threads, env_id, batch)


def _spread(std: float, episodes: int) -> str:
    """How the scores of ``episodes`` episodes spread, in words a reader takes in."""
    if episodes == 1:
        return "over 1 episode"
    if std == 0:  # deterministic physics and policy from one start: one episode, repeated
        return f"(the same in all {episodes} episodes)"
    return f"+- {std:.3g} over {episodes} episodes"


def cmd_plot(args: argparse.Namespace) -> int:
    from beacon_torch.training.evaluation import plot_runs

    path = plot_runs(args.runs, outputs(args.out, "learning_curve.png")[0], name=args.scalar, new=True)
    print(f"plot: {path}")
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from beacon_torch.training.report import report

    md, numbers, png = outputs(args.out, "runs/report", "report.md", "report.json", "report.png")
    _threads(args, None, 8)  # the evaluations of runs without a summary
    result = report(args.runs, md, numbers, png, starts=args.starts, progress=True)
    print(result["table"])
    print(f"\ntable: {md}, numbers: {numbers}\nfigure: {png}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from beacon_torch import __version__

    parser = argparse.ArgumentParser(
        prog="beacon-torch",
        description=plain(__doc__.split("\n\n")[0]),
        epilog="Each command's options: beacon-torch COMMAND --help.",
    )
    parser.add_argument("--version", action="version", version=f"beacon-torch {__version__}")
    parser.add_argument(
        "--threads",
        type=positive,
        metavar="N",
        help="torch threads (default: $BEACON_TORCH_THREADS, else the count measured fastest for the env "
        "and batch on an idle machine; on a shared machine give 1)",
    )
    parser.add_argument(
        "--import",
        dest="imports",
        action="append",
        default=[],
        metavar="MODULE",
        help="import a module that registers envs (beacon_torch.register) first (repeatable)",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("list", help="list the environments and their parameters").set_defaults(func=cmd_list)

    run = sub.add_parser("run", help="uncontrolled and random-policy episodes of an env")
    run.add_argument("env", help="environment id (see 'beacon-torch list')")
    run.add_argument("--num-envs", type=int, default=16, help="members of the random-policy batch")
    run.add_argument("--seed", type=int, default=0)
    run.add_argument("--device", default="cpu")
    run.add_argument(
        "--dtype",
        default="float64",
        choices=["float32", "float64"],
        help="default float64, as the published scores (the recipes train in float32: chaotic lorenz-v0 "
        "scores 238 there, 207 here)",
    )
    run.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", help="an env parameter (repeatable)")
    run.add_argument("--out", help="output directory (default runs/ENV, under new names if run.png is taken)")
    run.add_argument("--gif", metavar="PATH", help="write an animation of the uncontrolled episode (a new file)")
    run.add_argument("--gif-every", type=int, default=0, help="render every N-th step (default: about 100 frames)")
    run.set_defaults(func=cmd_run)

    bench = sub.add_parser("bench", help="transitions per second against the published code")
    bench.add_argument("--envs", nargs="+", metavar="ENV", help="env ids (default: the seven benchmark envs)")
    bench.add_argument(
        "--num-envs", nargs="+", type=int, metavar="N", help="default 1 16 64 256 1024 (1 16 32 64 for the cavities)"
    )
    bench.add_argument("--dtype", nargs="+", default=["float32"], choices=["float32", "float64"])
    bench.add_argument("--mode", nargs="+", default=["eager", "compiled"], choices=["eager", "compiled"])
    bench.add_argument("--device", default="cpu")
    bench.add_argument("--steps", type=int, help="timed steps per repeat (default 20; 2 for the cavities)")
    bench.add_argument("--repeats", type=int, default=5, help="timed repeats; the median is reported")
    bench.add_argument(
        "--out", help="output directory, without earlier results (default: a new runs/bench/bench-DATE-TIME)"
    )
    bench.set_defaults(func=cmd_bench)

    ev = sub.add_parser("eval", help="score a trained policy against the uncontrolled env")
    ev.add_argument("run", nargs="?", help="a run directory of a recipe (one seed, or seedK folders)")
    ev.add_argument(
        "--pretrained", metavar="ALGO/ENV", help="a shipped policy instead (beacon_torch.pretrained.available())"
    )
    ev.add_argument(
        "--out", help="where --pretrained writes ALGO/ENV.gif (default: here, under a new name if it is taken)"
    )
    ev.add_argument("--num-envs", type=int, default=8, help="evaluation episodes (one batch)")
    ev.add_argument(
        "--starts",
        choices=("test", "validation", "train", "own"),
        default="test",
        help="the episodes: from a set of developed states (beacon_torch.starts), one per episode, or 'own': "
        "the env's own start, the paper's episodes (default: test, states no training started from)",
    )
    ev.add_argument("--device", default="cpu")
    ev.add_argument("--no-gif", action="store_true", help="no animation of the controlled episode")
    ev.set_defaults(func=cmd_eval)

    pl = sub.add_parser("plot", help="learning curves of run directories, paper style")
    pl.add_argument("runs", nargs="+", help="run directories")
    pl.add_argument("--out", help="the PNG to write, a new file (default learning_curve.png, or a free name)")
    pl.add_argument("--scalar", default="episode_score", help="the logged value to draw")
    pl.set_defaults(func=cmd_plot)

    rp = sub.add_parser(
        "report", help="the benchmark protocol over trained runs: normalised scores, IQM and bootstrap intervals"
    )
    rp.add_argument(
        "runs", nargs="+", help="run directories (seedK folders of one env and algorithm) or their summary.json files"
    )
    rp.add_argument(
        "--out", help="where report.md, report.json and report.png go, new files (default runs/report, free names)"
    )
    rp.add_argument(
        "--starts",
        choices=("test", "own"),
        default="test",
        help="score the seeds on the test set's developed starts or on the env's own start (default: test; "
        "summaries recorded without test-set scores give their own start's, marked)",
    )
    rp.set_defaults(func=cmd_report)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    find_user_modules()
    try:
        return _run(args)
    except BrokenPipeError:
        # the reader stopped reading (``beacon-torch list | head``): nothing more to say
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        except (OSError, ValueError):
            pass
        return 0


def _run(args: argparse.Namespace) -> int:
    try:
        for module in args.imports:
            try:
                importlib.import_module(module)
            except ImportError as err:
                raise CliError(f"--import {module}: {err}") from None
        return args.func(args)
    except BrokenPipeError:
        raise
    except (
        CliError,
        ValueError,
        TypeError,
        OSError,
    ) as err:  # OSError: a path that cannot be read or written, named in the message
        print(f"beacon-torch: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
