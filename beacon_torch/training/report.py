"""A benchmark protocol to cite: per (env, algorithm), the normalised score of every
seed's deterministic policy (0 = no control on the same episodes, 1 = the score the
paper's PPO reaches), their interquartile mean over the seeds and its bootstrap 95 %
confidence interval, as a table and a figure.

The evaluation episodes are fixed: by default the 8 developed states of the held-out
test set (``beacon_torch.starts``), one episode each, beside no control from the same
states; with ``starts="own"`` the env's own start (the paper's episodes),
``evaluation.EVAL_SEED`` seeding 8 members; float32 as in training. 1 stays the paper's
PPO score, measured on its own start. A summary recorded before its seeds were scored
on the test set gives a row on its own start, marked so. ``beacon-torch report
RUN_DIRS...`` reads the ``summary.json`` of each run directory
(``evaluation.summarise`` writes it; a directory without one is summarised first).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy import stats

from beacon_torch import received
from beacon_torch.files import create_file, refuse_existing, save_figure, write_text
from beacon_torch.registry import ENVS, env_class
from beacon_torch.training.evaluation import CURVE_POINTS, summarise

BOOTSTRAP = 10_000  # resamples of the seeds
CONFIDENCE = 0.95


def normalisable(env_id: str) -> bool:
    """Whether the protocol can normalise ``env_id``'s scores: its card gives the
    paper's PPO score, the scale's "= 1"."""
    return env_class(env_id).paper_ppo is not None


def reference(env_id: str) -> float:
    """The paper's PPO score of ``env_id`` (its base env's for a variant)."""
    score = env_class(env_id).paper_ppo
    if score is None:
        raise ValueError(
            f"{env_id} has no paper score on its card (paper_ppo): the protocol has nothing to normalise by"
        )
    return score


def normalised(score, uncontrolled, env_id: str):
    """0 at the uncontrolled score, 1 at the paper's PPO score."""
    return (np.asarray(score, dtype=float) - uncontrolled) / (reference(env_id) - uncontrolled)


def iqm(values, axis=None) -> float:
    """The interquartile mean as rliable defines it (``scipy.stats.trim_mean``): the
    mean after cutting a quarter of the values, whole values only, from each end (with
    3 seeds nothing is cut: the mean; with 5, the middle three)."""
    value = stats.trim_mean(np.asarray(values, dtype=float), 0.25, axis=axis)
    return float(value) if axis is None else value


def bootstrap_interval(values, resamples: int = BOOTSTRAP, seed: int = 0) -> tuple[float, float]:
    """The percentile bootstrap interval of the IQM over the seeds
    (``scipy.stats.bootstrap``, resampled with replacement from a fixed generator, so
    that a report is reproducible); one seed, or seeds all equal: that value twice."""
    x = np.asarray(values, dtype=float)
    if len(x) < 2 or np.ptp(x) == 0:
        return float(x.mean()), float(x.mean())
    result = stats.bootstrap(
        (x,),
        lambda sample, axis=-1: iqm(sample, axis=axis),
        n_resamples=resamples,
        confidence_level=CONFIDENCE,
        method="percentile",
        rng=np.random.default_rng(seed),
    )
    return float(result.confidence_interval.low), float(result.confidence_interval.high)


# which episodes a row scores: the held-out test set's developed starts, or the env's own
# start (the paper's episodes, where its PPO reference was measured)
EPISODES = {"test": "test set", "own": "own start"}


def held_out(summary: dict) -> bool:
    """Whether ``summary`` records its seeds' scores on the test set."""
    return "test_uncontrolled" in summary and all("test" in s for s in summary["seeds"])


def scaled(uncontrolled: float, env_id: str) -> bool:
    """Whether scores beside no control scoring ``uncontrolled`` can be normalised: no
    control below the paper's PPO. Where it scores above (sloshing's and mixing's calmer
    developed states), the scale from no control to the paper's score runs backwards and
    a normalised number would rank a policy worse than no control above one that beats
    it."""
    return uncontrolled < reference(env_id)


def test_scaled(summary: dict) -> bool:
    """Whether ``summary``'s test-set scores can be normalised: recorded, and
    :func:`scaled` beside no control from the test set's developed starts."""
    return held_out(summary) and scaled(summary["test_uncontrolled"], summary["env"])


def row(summary: dict, starts: str = "test") -> dict:
    """The protocol's numbers of one (env, algorithm) summary, on the episodes
    ``starts`` names (:data:`EPISODES`); a summary whose test-set scores cannot be
    normalised (recorded before its seeds were scored on the test set, or
    :func:`test_scaled` false) is scored on its own start, and the row says so."""
    if starts not in EPISODES:
        raise ValueError(f"starts must be one of {', '.join(EPISODES)}, got {starts!r}")
    env_id = summary["env"]
    test = starts == "test" and test_scaled(summary)
    scores = [s["test"] if test else s["eval"] for s in summary["seeds"]]
    uncontrolled = summary["test_uncontrolled"] if test else summary["uncontrolled"]
    norm = normalised(scores, uncontrolled, env_id)
    low, high = bootstrap_interval(norm)
    return {
        "env": env_id,
        "algo": summary["algo"],
        "episodes": "test" if test else "own",
        "seeds": len(scores),
        "scores": scores,
        "uncontrolled": uncontrolled,
        "reference": reference(env_id),
        "normalised": norm.tolist(),
        "iqm": iqm(norm),
        "ci": (low, high),
        "score_iqm": iqm(scores),
        "frames": summary["frames"],
        "wall_s_per_seed": summary["wall_s_per_seed"],
    }


def check_summary(summary, file: str | Path, scored: bool = True) -> dict:
    """Refuse a summary the protocol cannot score: an unknown env, no seeds, a score
    or count that is not a finite number, an uncontrolled score equal to the
    reference (nothing to normalise by); with ``scored`` false, a summary of an env
    without a reference on its card is data all the same (recorded, not normalised)."""

    def bad(what: str):
        return ValueError(f"{file}: not a summary of trained seeds ({what})")

    finite = received.finite_number
    if not isinstance(summary, dict):
        raise bad("not a JSON object")
    if not isinstance(summary.get("env"), str) or summary["env"] not in ENVS:
        raise bad(f"unknown env {summary.get('env')!r}")
    if scored and not normalisable(summary["env"]):
        raise bad(f"{summary['env']} has no paper score on its card (paper_ppo) to normalise by")
    if not isinstance(summary.get("algo"), str):
        raise bad("no algorithm")
    seeds = summary.get("seeds")
    if (
        not isinstance(seeds, list)
        or not seeds
        or not all(isinstance(s, dict) and finite(s.get("eval")) for s in seeds)
    ):
        raise bad("'seeds' must list at least one seed, each with a finite 'eval' score")
    if ("test_uncontrolled" in summary or any("test" in s for s in seeds)) and not (
        finite(summary.get("test_uncontrolled")) and all(finite(s.get("test")) for s in seeds)
    ):
        raise bad("test-set scores must be finite numbers, one per seed, with a finite 'test_uncontrolled'")
    for key in ("uncontrolled", "frames", "wall_s_per_seed"):
        if not finite(summary.get(key)) or summary[key] < 0 and key != "uncontrolled":
            raise bad(f"{key!r} must be a finite number, got {_short(summary.get(key))}")
    if not isinstance(summary["frames"], int) or summary["frames"] > MAX_COUNT:
        raise bad(f"'frames' must be a count of transitions (an integer up to {MAX_COUNT:.0e})")
    if summary["wall_s_per_seed"] > MAX_SECONDS:
        raise bad(f"'wall_s_per_seed' must be at most {MAX_SECONDS:.0e} s, got {_short(summary['wall_s_per_seed'])}")
    for s in seeds:
        if "curve" in s and not _curve(s["curve"]):
            raise bad(
                "a seed's 'curve' must hold 'frames' (counts, not decreasing), 'score' (finite numbers) and "
                f"'wall_s' (finite seconds, or none), as many of each, at most {CURVE_POINTS}"
            )
    if "train_mean" in summary and not finite(summary["train_mean"]):
        raise bad(f"'train_mean' must be finite, got {_short(summary['train_mean'])}")
    if not normalisable(summary["env"]):
        return summary
    if summary["uncontrolled"] == reference(summary["env"]):
        raise bad(f"its uncontrolled score equals the reference {reference(summary['env'])}: no scale to normalise by")
    pairs = [([s["eval"] for s in seeds], summary["uncontrolled"])]
    if held_out(summary):
        if summary["test_uncontrolled"] == reference(summary["env"]):
            raise bad("its test-set uncontrolled score equals the reference: no scale to normalise by")
        pairs.append(([s["test"] for s in seeds], summary["test_uncontrolled"]))
    with np.errstate(over="ignore", invalid="ignore"):
        for scores, uncontrolled in pairs:
            norm = normalised(scores, uncontrolled, summary["env"])
            if not np.isfinite(norm).all() or not np.isfinite(np.abs(norm).sum()):
                raise bad("its scores are too far from the uncontrolled one to normalise in floating point")
    return summary


def _curve(curve) -> bool:
    """Whether a seed's ``curve`` is what :func:`~beacon_torch.training.evaluation.curve_of`
    writes: three lists of numbers of one length (``wall_s`` possibly empty), within
    bounds."""
    finite = received.finite_number
    if not isinstance(curve, dict) or set(curve) != {"frames", "score", "wall_s"}:
        return False
    frames, score, wall = curve["frames"], curve["score"], curve["wall_s"]
    if not all(isinstance(x, list) for x in (frames, score, wall)) or len(frames) > CURVE_POINTS:
        return False
    counts = all(isinstance(f, int) and not isinstance(f, bool) and 0 <= f <= MAX_COUNT for f in frames)
    return (
        counts
        and all(a <= b for a, b in zip(frames[:-1], frames[1:], strict=True))
        and len(score) == len(frames)
        and all(finite(v) for v in score)
        and len(wall) in (0, len(frames))
        and all(finite(w) and 0 <= w <= MAX_SECONDS for w in wall)
    )


# beyond any run (a billion transitions a second for three centuries; a century)
MAX_COUNT = 10**19
MAX_SECONDS = 3.2e9


def _short(value) -> str:
    """A value as an error message shows it: numbers in a few digits."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        try:
            return f"{float(value):.4g}"
        except OverflowError:
            return f"an integer of {len(str(abs(value)))} digits"
    return repr(value)[:60]


def read(file: str | Path, scored: bool = True) -> dict:
    """A ``summary.json`` file, checked (:func:`check_summary`)."""
    return check_summary(received.json_file(file, "summary"), file, scored)


def summaries(run_dirs, progress: bool = False) -> list[dict]:
    """The summary of each run directory (a ``summary.json`` file, or a directory
    holding one or to be summarised, with progress bars if ``progress``), checked."""
    out = []
    for run in map(Path, run_dirs):
        if run.is_file():
            out.append(read(run))
        elif (run / "summary.json").is_file():
            out.append(read(run / "summary.json"))
        else:
            out.append(check_summary(summarise(run, progress=progress), run / "summary.json"))
    if not out:
        raise ValueError("no summaries to report")
    return out


def _fixed(x: float) -> str:
    """Two decimals, or three significant digits for a number too large for them."""
    return f"{x:.2f}" if abs(x) < 1e6 else f"{x:.3g}"


def table(rows: list[dict]) -> str:
    lines = [
        "| env | algorithm | episodes | seeds | normalised score, IQM [95 % CI] | score, IQM (per seed) | "
        "uncontrolled | paper's PPO (= 1) | transitions | wall time per seed |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in sorted(rows, key=lambda r: (r["algo"], r["env"])):
        per_seed = ", ".join(f"{s:.4g}" for s in r["scores"])
        lines.append(
            f"| {r['env']} | {r['algo']} | {EPISODES[r['episodes']]} | {r['seeds']} | "
            f"**{_fixed(r['iqm'])}** [{_fixed(r['ci'][0])}, {_fixed(r['ci'][1])}] | {r['score_iqm']:.4g} ({per_seed}) "
            f"| {r['uncontrolled']:.4g} | {r['reference']:g} | {r['frames']:,} | {r['wall_s_per_seed'] / 60:.1f} min |"
        )
    return "\n".join(lines)


def figure(rows: list[dict], path: str | Path) -> Path:
    """The normalised IQM of every (env, algorithm) with its interval, 0 and 1 marked."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = sorted(rows, key=lambda r: (r["env"], r["algo"]))
    fig = Figure(figsize=(9, 0.4 * len(rows) + 1.2), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    algos = sorted({r["algo"] for r in rows})
    for k, r in enumerate(rows):
        color = f"C{algos.index(r['algo'])}"
        ax.errorbar(
            r["iqm"], k, xerr=[[r["iqm"] - r["ci"][0]], [r["ci"][1] - r["iqm"]]], fmt="o", color=color, capsize=3
        )
        ax.scatter(r["normalised"], [k] * len(r["normalised"]), s=8, color=color, alpha=0.4)
    ax.axvline(0.0, color="k", ls="--", lw=1, label="uncontrolled")
    ax.axvline(1.0, color="k", ls=":", lw=1, label="the paper's PPO")
    labels = [f"{r['algo']} {r['env']}" + (" (own start)" if r["episodes"] == "own" else "") for r in rows]
    ax.set_yticks(range(len(rows)), labels, fontsize=8)
    ax.set_xlabel("normalised score (IQM over seeds, 95 % bootstrap interval; dots: seeds)")
    ax.grid(alpha=0.3, axis="x")
    # beside the axes, where it covers no point
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
    fig.tight_layout()
    save_figure(fig, path)
    return Path(path)


def report(
    run_dirs,
    md: str | Path,
    numbers: str | Path,
    png: str | Path,
    *,
    starts: str = "test",
    replace: bool = False,
    progress: bool = False,
) -> dict:
    """The protocol's table (``md``), numbers (``numbers``, JSON) and figure (``png``)
    of the run directories, on the episodes ``starts`` names (:func:`row`): new files,
    or with ``replace`` (the results page's own generated files) in place of earlier
    ones."""
    rows = [row(s, starts) for s in summaries(run_dirs, progress)]
    text = table(rows)
    for path in (md, numbers, png):
        Path(path).parent.mkdir(parents=True, exist_ok=True)
    write = write_text if replace else lambda path, text: create_file(path, lambda tmp: tmp.write_text(text))
    write(md, text + "\n")
    write(numbers, json.dumps(rows, indent=1))
    if not replace:
        refuse_existing([png])
    png = figure(rows, png)
    return {"rows": rows, "table": text, "png": str(png)}


def write_block(page: str | Path, begin: str, end: str, block: str) -> Path:
    """Replace the generated part of a markdown page, between the lines ``begin`` and
    ``end``, with ``block`` (appended with its markers when the page has none), leaving
    the hand-written rest as it is."""
    page = Path(page)
    text = page.read_text() if page.exists() else ""
    new = f"{begin}\n{block}\n{end}"
    if begin in text:
        if end not in text[text.index(begin) :]:
            raise ValueError(f"{page}: the generated part starting {begin!r} has no end marker {end!r}")
        text = text[: text.index(begin)] + new + text[text.index(end, text.index(begin)) + len(end) :]
    else:
        text = text + "\n" + new + "\n"
    write_text(page, text)
    return page
