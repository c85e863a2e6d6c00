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
import re
from pathlib import Path

import numpy as np
from scipy import stats

from beacon_torch import received
from beacon_torch.core.card import Reference
from beacon_torch.files import create_file, refuse_existing, save_figure, write_text
from beacon_torch.registry import ENVS, env_spec
from beacon_torch.training.evaluation import CURVE_POINTS, summarise
from beacon_torch.training.run import ALGORITHMS as RUN_ALGORITHMS

BOOTSTRAP = 10_000  # resamples of the seeds
CONFIDENCE = 0.95


def normalisable(env_id: str) -> bool:
    """Whether the protocol can normalise ``env_id``'s scores: its card gives the
    scale's "= 1" (the paper's PPO score or another declared reference)."""
    return env_spec(env_id).card.scale_reference() is not None


def scale_reference(env_id: str) -> Reference:
    """The "= 1" of ``env_id``'s scores (its base env's for a variant), with its source."""
    found = env_spec(env_id).card.scale_reference()
    if found is None:
        raise ValueError(f"{env_id} has no reference on its card (paper_ppo or reference): nothing to normalise by")
    return found


def reference(env_id: str, uncontrolled: float) -> float:
    """The reference score of ``env_id`` beside no control scoring ``uncontrolled``."""
    return scale_reference(env_id).value(uncontrolled)


def normalised(score, uncontrolled, env_id: str):
    """0 at the uncontrolled score, 1 at the reference score (:func:`reference`)."""
    return (np.asarray(score, dtype=float) - uncontrolled) / (reference(env_id, uncontrolled) - uncontrolled)


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
    control below the reference. Where it scores above (sloshing's and mixing's calmer
    developed states), the scale from no control to the paper's score runs backwards and
    a normalised number would rank a policy worse than no control above one that beats
    it."""
    return uncontrolled < reference(env_id, uncontrolled)


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
    if not test and "uncontrolled" not in summary:
        why = "asked for the own start" if starts == "own" else "its test-set scores cannot be normalised"
        raise ValueError(
            f"{summary['algo']}/{env_id}: scored from the test set's starts only, and {why} (no control scores "
            f"above the reference from those starts, or --starts own)"
        )
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
        "reference": reference(env_id, uncontrolled),
        "reference_source": scale_reference(env_id).label(),
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

    def score(value) -> bool:
        return received.finite_number(value) and abs(value) <= MAX_SCORE

    finite = received.finite_number
    if not isinstance(summary, dict):
        raise bad("not a JSON object")
    if not isinstance(summary.get("env"), str) or summary["env"] not in ENVS:
        raise bad(f"unknown env {_short(summary.get('env'))}")
    if scored and not normalisable(summary["env"]):
        raise bad(f"{summary['env']} has no reference on its card (paper_ppo or reference) to normalise by")
    if not isinstance(summary.get("algo"), str) or summary["algo"] not in ALGORITHMS:
        raise bad(f"unknown algorithm {_short(summary.get('algo'))}; known: {', '.join(ALGORITHMS)}")
    seeds = summary.get("seeds")
    # a summary holds the scores from the env's own start (``eval`` beside
    # ``uncontrolled``), from the test set's (``test`` beside ``test_uncontrolled``), or
    # both; a planner's record may hold the test set's alone
    own = "uncontrolled" in summary or "test_uncontrolled" not in summary
    if (
        not isinstance(seeds, list)
        or not seeds
        or not all(isinstance(s, dict) and (not own or score(s.get("eval"))) for s in seeds)
    ):
        raise bad(f"'seeds' must list at least one seed, each with a finite 'eval' score of at most {MAX_SCORE:.0e}")
    if ("test_uncontrolled" in summary or any("test" in s for s in seeds)) and not (
        score(summary.get("test_uncontrolled")) and all(score(s.get("test")) for s in seeds)
    ):
        raise bad(
            f"test-set scores must be finite numbers of at most {MAX_SCORE:.0e}, one per seed, with a finite "
            f"'test_uncontrolled'"
        )
    names = [s["seed"] for s in seeds if "seed" in s]
    if not all(isinstance(n, (str, int)) and not isinstance(n, bool) for n in names) or len(set(names)) < len(names):
        raise bad("each seed must be listed once, under a name of its own ('seed')")
    if own and not score(summary.get("uncontrolled")):
        raise bad(
            f"'uncontrolled' must be a finite number of at most {MAX_SCORE:.0e}, got "
            f"{_short(summary.get('uncontrolled'))}"
        )
    for key in ("frames", "wall_s_per_seed"):
        if not finite(summary.get(key)) or summary[key] < 0:
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
    pairs = [("own-start", [s["eval"] for s in seeds], summary["uncontrolled"])] if own else []
    if held_out(summary):
        pairs.append(("test-set", [s["test"] for s in seeds], summary["test_uncontrolled"]))
    for name, scores, uncontrolled in pairs:
        ref = reference(summary["env"], uncontrolled)
        # a scale within round-off of zero would turn round-off into the score
        if abs(ref - uncontrolled) <= SCALE_TOLERANCE * max(abs(ref), abs(uncontrolled), 1.0):
            raise bad(
                f"its {name} uncontrolled score {uncontrolled:.6g} is within round-off of the reference {ref:g}: "
                f"no scale to normalise by"
            )
        norm = normalised(scores, uncontrolled, summary["env"])
        if not (np.abs(norm) <= MAX_NORMALISED).all():
            raise bad(
                f"its {name} scores normalise to {_short(float(np.abs(norm).max()))}, beyond any policy's "
                f"(at most {MAX_NORMALISED:g} times the way from no control to the reference)"
            )
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
# beyond any score of an env (the largest, lorenz's, counts at most its 2,000 steps)
MAX_SCORE = 1e9
# a normalised score beyond a thousand times the way to the reference is no policy's:
# a scale too small for its scores
MAX_NORMALISED = 1e3
# the least scale from no control to the reference, relative to their size: float32
# episodes round at about 1e-7
SCALE_TOLERANCE = 1e-6
# the algorithms whose results a report may show: the recipes' and the planner's
ALGORITHMS = (*RUN_ALGORITHMS, "mpc")


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


# the record the gradient model-predictive control (recipes/mpc.py) writes
PLANNER_RECORD = "mpc.json"


def planner_summary(file: str | Path, scored: bool = True) -> dict:
    """A planner's record (``mpc.json``) as a summary of one "seed" (nothing is trained;
    its seed is that of the planner's noise): its score on the episodes it planned, the
    test set's or the env's own, beside no control from the same starts; no training
    transitions; its CPU time as the wall time."""
    record = received.json_file(file, "planner's record")

    def bad(what: str):
        return ValueError(f"{file}: not a planner's record to report ({what})")

    if not isinstance(record, dict) or not isinstance(record.get("env"), str):
        raise bad("no env")
    if "score_mean" not in record:
        raise bad(f"it holds the cost of {_short(record.get('planned_actions'))} planned actions, no episode's score")
    if record.get("starts") not in EPISODES:
        raise bad(f"episodes from {_short(record.get('starts'))} starts; the protocol scores 'test' or 'own'")
    cost = [record.get(k) for k in ("cpu_s_per_action", "planned_actions")]
    if not all(received.finite_number(c) and 0 <= c <= MAX_SECONDS for c in cost):
        raise bad("its cost per action and count of planned actions must be finite and non-negative")
    test = record["starts"] == "test"
    seed = {"seed": str((record.get("settings") or {}).get("seed", 0))[:20]}
    seed["test" if test else "eval"] = record["score_mean"]
    summary = {
        "env": record["env"],
        "algo": "mpc",
        "seeds": [seed],
        "test_uncontrolled" if test else "uncontrolled": record.get("uncontrolled"),
        "frames": 0,
        "wall_s_per_seed": cost[0] * cost[1],
    }
    return check_summary(summary, file, scored)


def summaries(run_dirs, progress: bool = False) -> list[dict]:
    """The summary of each run directory (a ``summary.json`` file, or a directory
    holding one or to be summarised, with progress bars if ``progress``) or planner's
    record (``mpc.json``, or a directory holding one), checked; a pair of an env and an
    algorithm given twice is refused (its seeds would count twice)."""
    out = []
    for run in map(Path, run_dirs):
        if run.is_file():
            out.append(planner_summary(run) if run.name == PLANNER_RECORD else read(run))
        elif (run / "summary.json").is_file():
            out.append(read(run / "summary.json"))
        elif (run / PLANNER_RECORD).is_file():
            out.append(planner_summary(run / PLANNER_RECORD))
        else:
            out.append(check_summary(summarise(run, progress=progress), run / "summary.json"))
    if not out:
        raise ValueError("no summaries to report")
    pairs = [f"{s['algo']}/{s['env']}" for s in out]
    twice = sorted({p for p in pairs if pairs.count(p) > 1})
    if twice:
        raise ValueError(f"{', '.join(twice)}: given more than once; a pair's seeds are one summary")
    return out


def _cell(text) -> str:
    """``text`` as a markdown table's cell shows it, whatever it holds: no markup, no
    HTML, no column break."""
    escaped = str(text).replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
    return re.sub(r"([\\`*_{}\[\]|~])", r"\\\1", escaped).replace("\n", " ")


def _reference_cell(row: dict) -> str:
    """The reference score of a row and its source (a row written before the sources
    were recorded shows its number alone)."""
    source = row.get("reference_source", "")
    if " x no control" in source:
        return f"{row['reference']:.4g} = {source}"
    return source or f"{row['reference']:g}"


def table(rows: list[dict]) -> str:
    lines = [
        "| env | algorithm | episodes | seeds | normalised score, IQM [95 % CI] | score, IQM (per seed) | "
        "uncontrolled | reference (= 1), its source | transitions | wall time per seed |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in sorted(rows, key=lambda r: (r["algo"], r["env"])):
        per_seed = ", ".join(f"{s:.4g}" for s in r["scores"])
        lines.append(
            f"| {_cell(r['env'])} | {_cell(r['algo'])} | {EPISODES[r['episodes']]} | {r['seeds']} | "
            f"**{r['iqm']:.2f}** [{r['ci'][0]:.2f}, {r['ci'][1]:.2f}] | {r['score_iqm']:.4g} ({per_seed}) "
            f"| {r['uncontrolled']:.4g} | {_cell(_reference_cell(r))} | {r['frames']:,} "
            f"| {r['wall_s_per_seed'] / 60:.1f} min |"
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
    ax.axvline(1.0, color="k", ls=":", lw=1, label="the reference (the paper's PPO where there is one)")
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
    write(numbers, json.dumps(rows, indent=1, allow_nan=False))
    if not replace:
        refuse_existing([png])
    png = figure(rows, png)
    return {"rows": rows, "table": text, "png": str(png)}


# a documentation page that a generated block is written into (the largest is about
# 60 kB)
PAGE_BYTES = 4 * 2**20


def write_block(page: str | Path, begin: str, end: str, block: str) -> Path:
    """Replace the generated part of a markdown page, between the lines ``begin`` and
    ``end``, with ``block`` (appended with its markers when the page has none), leaving
    the hand-written rest as it is."""
    page = Path(page)
    exists = page.exists() or page.is_symlink()
    text = received.text_file(page, "markdown page", PAGE_BYTES) if exists else ""
    new = f"{begin}\n{block}\n{end}"
    if begin in text:
        if end not in text[text.index(begin) :]:
            raise ValueError(f"{page}: the generated part starting {begin!r} has no end marker {end!r}")
        text = text[: text.index(begin)] + new + text[text.index(end, text.index(begin)) + len(end) :]
    else:
        text = text + "\n" + new + "\n"
    write_text(page, text)
    return page
