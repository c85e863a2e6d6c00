"""Every shipped policy evaluated again, as a user gets it.

    .venv/bin/python experiments/pretrained.py [--num-envs 8] [--page docs/results.md] [--changed]

Loads each policy of ``beacon_torch.pretrained.available()`` through
``pretrained.load`` (raw observations, the training's normalisation folded into the
network), runs it deterministically on the fixed evaluation episodes
(``evaluation.EVAL_SEED``, float32) beside no control on the same episodes, and writes
the table into the page between its markers, and the numbers to
``experiments/results/pretrained.json``. Each policy is also run from the test set of
developed starts (``beacon_torch.starts``, its 8 states) beside no control from the
same states: how it does away from the start it was trained from. The score recorded in the file at shipping
came from the training's checkpoint (normalisation as a transform); the two agree to
round-off, up to what chaotic envs make of it over an episode. ``--changed`` evaluates
only the policies shipped since the numbers file was written (a policy whose shipping
record, seed, transitions and recorded score, differs from its row's, or is new) and
keeps the other rows (normalised again by the cards' current references): the
cavities' policies take minutes each. ``--test-again PART`` evaluates the kept policies
whose name holds PART from the test starts again (after their env's start sets changed).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from beacon_torch import pretrained, starts
from beacon_torch.training.evaluation import EVAL_SEED, evaluate_policy
from beacon_torch.training.report import normalisable, normalised, scaled, write_block

ROOT = Path(__file__).resolve().parents[1]
BEGIN, END = "<!-- shipped policies: experiments/pretrained.py -->", "<!-- end of shipped policies -->"


def scale(score: float, uncontrolled: float, env_id: str) -> float | None:
    """The normalised score; None where the env's card has no reference to
    normalise by."""
    return float(normalised(score, uncontrolled, env_id)) if normalisable(env_id) else None


def evaluate_all(
    num_envs: int = 8, seed: int = EVAL_SEED, keep: list[dict] = (), test_again: tuple[str, ...] = ()
) -> list[dict]:
    """One row per shipped policy: its deterministic score against no control. A row of
    ``keep`` (taken with the same num_envs and seed) stands for its policy while the
    policy's shipping record is the one the row holds; its test-start scores too, unless
    the policy's name holds one of ``test_again`` (its env's test set has changed)."""
    kept = {
        row["policy"]: {k: v for k, v in row.items() if not k.startswith("test_")}
        if any(part in row["policy"] for part in test_again)
        else row
        for row in keep
    }
    rows = []
    for name in pretrained.available():
        algo, env_id = name.split("/")
        info = pretrained.info(name)
        old = kept.get(name)
        same = old is not None and (old["trained_seed"], old["frames"], old["recorded"]) == (
            info.get("seed"),
            info["frames"],
            info.get("score"),
        )
        if same and "test_score" in old:
            # the scores stand; their normalisation follows the card's current reference
            rows.append(
                {
                    **old,
                    "normalised": scale(old["score"], old["uncontrolled"], env_id),
                    "test_normalised": scale(old["test_score"], old["test_uncontrolled"], env_id),
                }
            )
            continue
        policy = pretrained.load(name)
        row = dict(old) if same else {}
        if not same:
            start = time.perf_counter()
            result = evaluate_policy(env_id, policy, num_envs=num_envs, seed=seed)
            row = {
                "policy": name,
                "trained_seed": info.get("seed"),
                "frames": info["frames"],
                "score": result["score_mean"],
                "score_std": result["score_std"],
                "uncontrolled": result["uncontrolled"],
                "normalised": scale(result["score_mean"], result["uncontrolled"], env_id),
                "recorded": info.get("score"),
                "seconds": time.perf_counter() - start,
            }
        test = evaluate_policy(env_id, policy, num_envs=starts.SETS["test"][1], seed=seed, starts="test")
        row.update(
            test_score=test["score_mean"],
            test_uncontrolled=test["uncontrolled"],
            test_normalised=scale(test["score_mean"], test["uncontrolled"], env_id),
        )
        rows.append(row)
        print(f"{name}: {row['score']:.4g} / test starts {row['test_score']:.4g}", flush=True)
    return rows


def table(rows: list[dict], num_envs: int, seed: int) -> str:
    lines = [
        f"Every shipped policy, loaded with `beacon_torch.pretrained.load` and run "
        f"deterministically on {num_envs} episodes"
        f" of evaluation seed {seed} (float32), against no control on the same episodes (`experiments/pretrained.py`):",
        "",
        "| policy | trained on (seed) | own start: score (std over episodes) | uncontrolled | normalised "
        "| recorded at shipping | test starts: score | uncontrolled | normalised |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        recorded = "-" if r["recorded"] is None else f"{r['recorded']:.4g}"
        if r["normalised"] is None:
            own = test_normalised = "- (b)"
        else:
            # no control from the developed starts above the paper's score: a backward scale
            backward = not scaled(r["test_uncontrolled"], r["policy"].split("/", 1)[1])
            own, test_normalised = f"{r['normalised']:.2f}", "- (a)" if backward else f"{r['test_normalised']:.2f}"
        lines.append(
            f"| {r['policy']} | {r['frames']:,} ({r['trained_seed']}) | {r['score']:.4g} "
            f"({r['score_std']:.2g}) | {r['uncontrolled']:.4g} | {own} | {recorded} "
            f"| {r['test_score']:.4g} | {r['test_uncontrolled']:.4g} | {test_normalised} |"
        )
    lines += [
        "",
        "The test starts are the 8 developed, uncontrolled states of the test set "
        "(`beacon_torch.starts`, [quick start](quickstart.md#start-sets-train-validation-and-test-episodes)); "
        "each policy was trained from the env's own start only. (a): no control from these starts already "
        "scores above the reference, so the scale from one to the other runs backwards and is not used "
        "(sloshing's and mixing's developed states are calmer than their own start). (b): the env's card has "
        "no reference, the scale's 1; its page sets the scores beside what its case offers.",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--num-envs", type=int, default=8, help="evaluation episodes per policy")
    parser.add_argument("--seed", type=int, default=EVAL_SEED)
    parser.add_argument(
        "--page", default=str(ROOT / "docs" / "results.md"), help="the page whose marked part is rewritten"
    )
    parser.add_argument("--json", default=str(ROOT / "experiments" / "results" / "pretrained.json"))
    parser.add_argument(
        "--changed",
        action="store_true",
        help="evaluate only the policies shipped since --json was written, keep its other rows",
    )
    parser.add_argument(
        "--test-again",
        nargs="+",
        default=(),
        metavar="PART",
        help="with --changed: evaluate again from the test starts the kept policies whose name holds PART "
        "(after their env's start sets changed)",
    )
    args = parser.parse_args(argv)
    if args.num_envs < 1:
        parser.error(f"--num-envs must be at least 1, got {args.num_envs}")
    keep = []
    if args.changed and Path(args.json).is_file():
        before = json.loads(Path(args.json).read_text())
        if (before["num_envs"], before["seed"]) == (args.num_envs, args.seed):
            keep = before["rows"]
        else:
            print(
                f"{args.json} was taken with {before['num_envs']} members and seed {before['seed']}: "
                f"evaluating every policy"
            )
    rows = evaluate_all(args.num_envs, args.seed, keep, tuple(args.test_again))
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(
        json.dumps({"num_envs": args.num_envs, "seed": args.seed, "torch": torch.__version__, "rows": rows}, indent=1)
    )
    text = table(rows, args.num_envs, args.seed)
    write_block(args.page, BEGIN, END, text)
    print(text)


if __name__ == "__main__":
    # one thread, as the scores recorded at shipping were computed; set here rather than
    # in main so that a caller's process keeps its own setting
    torch.set_num_threads(1)
    main()
