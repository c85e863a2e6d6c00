"""Trained runs: the deterministic policy's score against no control, learning curves
over seeds, and a run directory's summary.

A run directory is one seed's folder (``run.Run``) or a folder of ``seedK`` folders.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

import beacon_torch
from beacon_torch import episodes, received
from beacon_torch.core.checks import as_device
from beacon_torch.files import save_figure, write_text
from beacon_torch.registry import compiles_by_default
from beacon_torch.starts import SETS
from beacon_torch.training import networks
from beacon_torch.training.env import make_env
from beacon_torch.training.run import CHECKPOINT, BadRun, load_checkpoint, read_log, seed_dirs

# the seed of the evaluation episodes: every evaluation of an env sees the same episodes
EVAL_SEED = 12345
# the start set a summary and the commands judge a policy on by default: developed
# states the policy never started from in training (beacon_torch.starts)
HELD_OUT = "test"


def _episode(env, policy, *, frames: bool, title: str | None):
    """One episode of every member of ``env`` (a TorchRL env, transformed or not) and,
    with ``frames``, about 100 frames of its render member, the last one at the end."""
    base = getattr(env, "base_env", env)
    shots = []
    every = max(1, base.episode_length // 100)

    def grab(step: int) -> None:
        if step % every == 0:
            shots.append(base.render())

    rollout = episodes.episode(env, policy, frame_hook=grab if frames else None, progress=title)
    if frames:
        shots.append(base.render())
    return rollout, shots


def episode_record(rollout) -> dict[str, list[float]]:
    """Each episode's score and the mean of each of the env's diagnostics over it (the
    Nusselt number of a convection episode, a wake's drag), member by member."""
    record = {"score": episodes.scores(rollout).tolist()}
    if "diagnostics" in rollout["next"].keys():
        for name, values in rollout["next", "diagnostics"].items():
            record[name] = episodes.episode_means(values, rollout).tolist()
    return record


def evaluation_compiles(env_id: str) -> bool:
    """Whether an evaluation compiles its envs when not told: the 2-D flows, whose action
    is a hundred or more substeps, where the recipes compile by default
    (:func:`~beacon_torch.registry.compiles_by_default`); the cheaper envs' episodes take
    less than their compilation."""
    return compiles_by_default() and beacon_torch.registry.env_spec(env_id).card.costly


def evaluate_policy(
    env_id: str,
    policy,
    *,
    norm: dict | None = None,
    num_envs: int = 8,
    device="cpu",
    gif: str | Path | None = None,
    side_by_side: str | Path | None = None,
    figure: str | Path | None = None,
    seed: int = EVAL_SEED,
    params: dict | None = None,
    starts: str | None = None,
    progress: bool = False,
    uncontrolled: float | None = None,
    compile: bool | None = None,
) -> dict:
    """``policy``, deterministic, on ``num_envs`` episodes of ``env_id`` with the physical
    ``params`` (seeded by ``seed``) whose observations are normalised by ``norm`` (an
    ``ObservationNorm`` state; None: raw), next to the uncontrolled episodes from the
    same starts: the env's own, or those of the start set ``starts`` ("train",
    "validation", "test": :mod:`beacon_torch.starts`). ``gif``: an animation of member
    0's episode; ``side_by_side``: member 0's controlled and uncontrolled episodes side
    by side; ``figure``: the env's diagnostics and the reward per action over the
    episodes, controlled beside uncontrolled (new files, each); ``progress``: progress
    bars of the two episodes on stderr; ``uncontrolled``: the uncontrolled score of
    these episodes where it is already known (the same env, parameters, seed, members
    and starts: they are the same episodes), which are then not run again (with no
    side-by-side animation nor figure, which draw them); ``compile``: the envs'
    compiled physics (None: :func:`evaluation_compiles`). Returns the scores' mean and
    spread, no control's mean score and each episode's record (:func:`episode_record`),
    and no control's where they were run."""
    if uncontrolled is not None and (side_by_side is not None or figure is not None):
        raise ValueError(
            "a known uncontrolled score draws no side-by-side animation nor figure: they need its episodes"
        )
    params = params or {}
    if compile is None:
        compile = evaluation_compiles(env_id)
    animate = gif is not None or side_by_side is not None
    sets = {} if starts is None else {"starts": starts}
    env = make_env(
        env_id,
        num_envs,
        device=device,
        seed=seed,
        norm=norm,
        norm_steps=0,
        record_history=animate,
        params=params,
        **sets,
        compile=compile,
    )
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        rollout, frames = _episode(env, policy, frames=animate, title=f"{env_id} controlled" if progress else None)
    controlled = episodes.scores(rollout)
    free = None
    if uncontrolled is None:
        free, free_frames = uncontrolled_episodes(
            env_id, num_envs, device=device, seed=seed, params=params, starts=starts,
            frames=side_by_side is not None, progress=progress, compile=compile,
        )  # fmt: skip
        uncontrolled = episodes.scores(free).mean().item()
    out = {
        "env": env_id,
        "starts": starts,
        "score_mean": controlled.mean().item(),
        "score_std": controlled.std(unbiased=False).item(),
        "uncontrolled": uncontrolled,
        "episodes": episode_record(rollout),
    }
    if free is not None:
        out["uncontrolled_episodes"] = episode_record(free)
    from beacon_torch.render import save_animation, side_by_side_frames

    if gif is not None:
        out["gif"] = str(save_animation(frames, gif))
    if side_by_side is not None:
        out["side_by_side"] = str(save_animation(side_by_side_frames(frames, free_frames), side_by_side))
    if figure is not None:
        out["figure"] = str(diagnostics_figure(env_id, rollout, free, figure))
    return out


def uncontrolled_episodes(
    env_id: str,
    num_envs: int,
    *,
    device="cpu",
    seed: int = EVAL_SEED,
    params: dict | None = None,
    starts: str | None = None,
    frames: bool = False,
    progress: bool = False,
    compile: bool | None = None,
):
    """The evaluation episodes of :func:`evaluate_policy` without control (the same
    seed gives the same starts and noise as the controlled ones): their rollout and,
    with ``frames``, member 0's frames; ``compile`` as there."""
    sets = {} if starts is None else {"starts": starts}
    compile = evaluation_compiles(env_id) if compile is None else compile
    ref = beacon_torch.make(
        env_id, num_envs, device=device, seed=seed, params=params or {}, record_history=frames, compile=compile, **sets
    )
    title = f"{env_id} uncontrolled" if progress else None
    return _episode(ref, episodes.null_policy(ref), frames=frames, title=title)


def diagnostics_figure(env_id: str, controlled, uncontrolled, path: str | Path) -> Path:
    """The env's diagnostics and the reward per action (one panel each) over two
    rollouts of the same starts, a new file: the mean over the members of the
    controlled episodes with their range, and of the uncontrolled ones dashed. A
    member's values stop where its episode ended."""
    panels = [*beacon_torch.registry.ENVS[env_id].physics.diagnostics, "reward"]
    series = [
        (label, {name: _per_action(rollout, name) for name in panels})
        for label, rollout in (("controlled", controlled), ("uncontrolled", uncontrolled))
    ]
    return draw_diagnostics(series, path, title=f"{env_id}: controlled against uncontrolled, from the same starts")


def draw_diagnostics(
    series: list[tuple[str, dict[str, np.ndarray]]],
    path: str | Path,
    *,
    title: str,
    times: np.ndarray | None = None,
    xlabel: str = "actions",
    lines: dict[str, tuple[float, str]] | None = None,
) -> Path:
    """Quantities over time, one panel each, as a new figure: ``series`` holds
    ``(label, {name: [members, actions] values})``, NaN where a member's episode has
    ended; each series is drawn as the mean over its members (with their range where
    there are several), the one labelled "uncontrolled" or "no control" dashed in
    black. ``times``: the horizontal axis (the action counts by default); ``lines``:
    ``{name: (value, label)}``, a reference value drawn across a panel."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    panels = list(series[0][1])
    fig = Figure(figsize=(7, 1.9 * len(panels) + 0.6), dpi=100)
    FigureCanvasAgg(fig)
    for k, name in enumerate(panels):
        ax = fig.add_subplot(len(panels), 1, k + 1)
        colors = iter(f"C{i}" for i in range(10))
        for label, values in series:
            values = np.atleast_2d(np.asarray(values[name], dtype=np.float64))
            steps = np.arange(1, values.shape[1] + 1) if times is None else np.asarray(times)
            free = label in ("uncontrolled", "no control")
            color, style = ("k", "--") if free else (next(colors), "-")
            many = values.shape[0] > 1
            with np.errstate(all="ignore"):
                mean = np.nanmean(values, 0)
                ax.plot(
                    steps,
                    mean,
                    style,
                    color=color,
                    lw=1.2 if many else 0.9,
                    label=label + (f" (mean of {values.shape[0]})" if many else ""),
                )
                if many and not free:
                    ax.fill_between(steps, np.nanmin(values, 0), np.nanmax(values, 0), color=color, alpha=0.2, lw=0)
        if lines and name in lines:
            value, label = lines[name]
            ax.axhline(value, color="0.5", ls=":", lw=1, label=label)
        ax.set_ylabel(name.replace("_", " "), fontsize=9)
        ax.grid(alpha=0.3)
        if k == 0:
            ax.set_title(title, fontsize=10)
        if k == 0 or (lines and name in lines):
            ax.legend(fontsize=7)
    ax.set_xlabel(xlabel)
    fig.tight_layout()
    save_figure(fig, path, new=True)
    return Path(path)


def _per_action(rollout, name: str) -> np.ndarray:
    """``[members, actions]`` float64 values of a diagnostic (or the team's reward) after
    each action, NaN after each member's first end."""
    if name == "reward":
        values = episodes.step_rewards(rollout)
    else:
        values = rollout["next", "diagnostics", name].to(torch.float64)
    values = values.detach().cpu().numpy().copy()
    done = rollout["next", "done"][..., 0].cpu().numpy()
    after = np.cumsum(done, -1) - done > 0  # steps after a member's first end
    values[after] = np.nan
    return values


def evaluate_run(
    run: str | Path,
    *,
    num_envs: int = 8,
    device="cpu",
    gif: str | Path | None = None,
    side_by_side: str | Path | None = None,
    figure: str | Path | None = None,
    seed: int = EVAL_SEED,
    starts: str | None = None,
    progress: bool = False,
    uncontrolled: float | None = None,
) -> dict:
    """The deterministic policy of one seed's checkpoint (:func:`evaluate_policy`)."""
    device = as_device(device)  # before the policy is moved there
    state = load_checkpoint(run)
    params = state["config"].get("params", {})  # the physics it was trained on
    env = make_env(state["env"], 1, norm=state["obs_norm"], params=params)
    actor = networks.policy(env, state["policy"]["network"], state["policy"]["hidden"])
    network = f"a {state['policy']['network']} of width {state['policy']['hidden']} on {state['env']}"
    try:
        received.load_into(actor, state["modules"]["actor"], f"{Path(run) / CHECKPOINT}: the actor's weights", network)
    except ValueError as err:
        raise BadRun(str(err)) from None
    actor = actor.to(device)
    result = evaluate_policy(
        state["env"],
        actor,
        norm=state["obs_norm"],
        num_envs=num_envs,
        device=device,
        gif=gif,
        side_by_side=side_by_side,
        figure=figure,
        seed=seed,
        params=params,
        starts=starts,
        progress=progress,
        uncontrolled=uncontrolled,
    )
    return {**result, "frames": state["frames"]}


def read_scalar(run: str | Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    """``(steps, values)`` of one logged scalar of one seed folder."""
    files = sorted(Path(run).glob(f"*/scalars/{name}.csv"))
    if not files:
        return np.zeros(0), np.zeros(0)
    rows = sorted(read_log(files[0]))
    return np.array([r[0] for r in rows]), np.array([r[1] for r in rows])


def plot_runs(
    runs: list[str | Path], path: str | Path, *, name: str = "episode_score", new: bool = False, progress: bool = True
) -> Path:
    """The paper-style figure, one panel per env: per run directory, the mean and
    standard deviation over its seeds of ``name`` against transitions (each seed
    interpolated on a common grid), with the env's uncontrolled score dashed. A series
    of one logged point is drawn as a point with its spread. ``new``: ``path`` must not
    exist when it is written (else it is replaced); ``progress``: a bar for the
    uncontrolled episode."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    by_env: dict[str, list] = {}
    for run in runs:
        seeds = seed_dirs(run)
        state = load_checkpoint(seeds[0])
        curves = [c for c in (read_scalar(s, name) for s in seeds) if len(c[0])]
        if not curves:
            raise ValueError(f"{run}: no '{name}' logged yet (no episode has ended)")
        by_env.setdefault(state["env"], []).append((run, state["algo"], curves))
    fig = Figure(figsize=(7, 4 * len(by_env)), dpi=100)
    FigureCanvasAgg(fig)
    k = 0
    for panel, (env_id, env_runs) in enumerate(by_env.items()):
        ax = fig.add_subplot(len(by_env), 1, panel + 1)
        for run, algo, curves in env_runs:
            grid = np.linspace(max(c[0][0] for c in curves), min(c[0][-1] for c in curves), 100)
            values = np.stack([np.interp(grid, s, v) for s, v in curves])
            mean, std = values.mean(0), values.std(0)
            label = f"{algo} {Path(run).name} ({len(curves)} seed{'s' if len(curves) > 1 else ''})"
            if grid[0] == grid[-1]:  # one point: a line of no length would not show
                ax.errorbar(grid[:1], mean[:1], yerr=std[:1], fmt="o", color=f"C{k}", capsize=3, label=label)
            else:
                ax.plot(grid, mean, color=f"C{k}", label=label)
                ax.fill_between(grid, mean - std, mean + std, color=f"C{k}", alpha=0.25, lw=0)
            k += 1
        ax.axhline(_uncontrolled(env_id, progress), color="k", ls="--", lw=1, label=f"{env_id} uncontrolled (float32)")
        ax.set_xlabel("transitions")
        ax.set_ylabel(name.replace("_", " "))
        ax.set_title(env_id)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, new=new)
    return Path(path)


def _uncontrolled(env_id: str, progress: bool = True) -> float:
    """The uncontrolled score drawn beside curves: in the recipes' float32 (chaotic
    lorenz-v0 scores 238 there, 207 in float64); one episode where the physics is
    deterministic, else the mean of 16."""
    num_envs = 1 if beacon_torch.registry.ENVS[env_id].physics.deterministic else 16
    ref = beacon_torch.make(env_id, num_envs, seed=0, compile=evaluation_compiles(env_id))
    title = f"{env_id} uncontrolled" if progress else None
    rollout = episodes.episode(ref, episodes.null_policy(ref), progress=title)
    return episodes.scores(rollout).mean().item()


# the points of a seed's training curve a summary keeps: enough to draw it, small
# beside the summary's size limit
CURVE_POINTS = 200


def curve_of(run: str | Path) -> dict:
    """A seed's training curve as its summary keeps it: the training episodes' scores
    (``score``) against the transitions (``frames``) and the wall time of training at
    them (``wall_s``, interpolated between the logged batches; empty where no wall time
    was logged), at most ``CURVE_POINTS`` points evenly spread over the logged ones."""
    steps, scores = read_scalar(run, "episode_score")
    if len(steps) > CURVE_POINTS:
        keep = np.unique(np.linspace(0, len(steps) - 1, CURVE_POINTS).round().astype(int))
        steps, scores = steps[keep], scores[keep]
    logged, wall = read_scalar(run, "wall_time")
    return {
        "frames": [int(s) for s in steps],
        "score": [float(v) for v in scores],
        "wall_s": [float(w) for w in np.interp(steps, logged, wall)] if len(logged) else [],
    }


def summary_of(root: str | Path, *, num_envs: int = 8, progress: bool = False) -> dict:
    """A run directory's results, from its checkpoints and logs alone: per seed, the
    deterministic policy's score on ``num_envs`` episodes from the env's own start (the
    paper's episodes, ``eval``), on the held-out test set's developed starts (``test``,
    one episode per state) and the mean score of the training episodes that ended in
    the last tenth of the transitions, each beside no control on the same episodes (the
    test episodes' records too: each one's score and diagnostics, :func:`episode_record`);
    their mean and spread over the seeds; transitions and wall time (what the
    checkpoints record); each seed's training curve (:func:`curve_of`). Every seed
    must be a run of the same algorithm on the same env."""
    root = Path(root)
    seeds = seed_dirs(root)
    per_seed, pairs = [], set()
    # the uncontrolled episodes of a seed's evaluation are every seed's that trained on
    # the same physics: run once per parameters
    known: dict[tuple[str, str], tuple[float, float]] = {}
    free_test: dict[tuple[str, str], dict] = {}  # no control's test episodes, by physics
    for run in seeds:
        state = load_checkpoint(run)
        pairs.add((state["algo"], state["env"]))
        physics = (state["env"], json.dumps(state["config"].get("params", {}), sort_keys=True, default=repr))
        own, test = known.get(physics, (None, None))
        ev = evaluate_run(run, num_envs=num_envs, gif=None, progress=progress, uncontrolled=own)
        held = evaluate_run(run, num_envs=SETS[HELD_OUT][1], starts=HELD_OUT, progress=progress, uncontrolled=test)
        known[physics] = (ev["uncontrolled"], held["uncontrolled"])
        free_test.setdefault(physics, held.get("uncontrolled_episodes"))
        steps, values = read_scalar(run, "episode_score")
        tail = values[steps >= 0.9 * steps[-1]] if len(steps) else values
        per_seed.append(
            {
                "seed": run.name,
                "frames": state["frames"],
                "wall_s": state.get("elapsed", 0.0),
                "eval": ev["score_mean"],
                "train_tail": float(tail.mean()) if len(tail) else float("nan"),
                "uncontrolled": ev["uncontrolled"],
                "test": held["score_mean"],
                "test_uncontrolled": held["uncontrolled"],
                "test_episodes": held["episodes"],
                "test_uncontrolled_episodes": free_test[physics],
                "curve": curve_of(run),
            }
        )
    if len(pairs) > 1:
        raise ValueError(f"{root}: its seeds are runs of several pairs ({', '.join(sorted(map('/'.join, pairs)))})")
    evals = np.array([s["eval"] for s in per_seed])
    tails = np.array([s["train_tail"] for s in per_seed])
    tests = np.array([s["test"] for s in per_seed])
    return {
        "algo": state["algo"],
        "env": state["env"],
        "config": state["config"],
        "seeds": per_seed,
        "eval_mean": float(evals.mean()),
        "eval_std": float(evals.std()),
        "train_mean": float(tails.mean()),
        "train_std": float(tails.std()),
        "frames": int(min(s["frames"] for s in per_seed)),
        "wall_s_per_seed": float(np.mean([s["wall_s"] for s in per_seed])),
        "uncontrolled": per_seed[0]["uncontrolled"],
        "test_mean": float(tests.mean()),
        "test_std": float(tests.std()),
        "test_uncontrolled": per_seed[0]["test_uncontrolled"],
        "num_envs": num_envs,
        "threads": torch.get_num_threads(),
    }


def summarise(root: str | Path, *, num_envs: int = 8, images: str | Path | None = None, progress: bool = False) -> dict:
    """:func:`summary_of`, also written to ``root/summary.json``, with the curve drawn
    into ``images/<root name>.png`` (default: ``root``)."""
    root = Path(root)
    summary = summary_of(root, num_envs=num_envs, progress=progress)
    images = Path(images) if images is not None else root
    images.mkdir(parents=True, exist_ok=True)
    png = plot_runs([root], images / f"{root.name}.png", progress=progress)
    summary["png"] = str(png.resolve())
    write_text(root / "summary.json", json.dumps(summary, indent=1))
    print(
        f"{summary['algo']}/{summary['env']}: eval {summary['eval_mean']:.4g} +- {summary['eval_std']:.3g}, "
        f"test starts {summary['test_mean']:.4g} +- {summary['test_std']:.3g} "
        f"(uncontrolled {summary['test_uncontrolled']:.4g}), "
        f"training tail {summary['train_mean']:.4g} over {len(summary['seeds'])} "
        f"seed{'s' if len(summary['seeds']) > 1 else ''}, {summary['frames']} "
        f"transitions, {summary['wall_s_per_seed']:.0f} s per seed"
    )
    return summary


def learning_curve(run: str | Path, progress: bool = True) -> str:
    """Draw ``run/learning_curve.png`` (as ``beacon-torch plot`` would) and say where,
    or why not (no episode ended yet); ``progress``: a bar for its uncontrolled
    episode."""
    try:
        return f"learning curve: {plot_runs([run], Path(run) / 'learning_curve.png', progress=progress)}"
    except ValueError as err:
        return f"no learning curve: {err}"
