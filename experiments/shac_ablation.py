"""Each of SAPO's settings of the actor-critic alone against its defaults, and more
updates for the same transitions (fewer members, shorter horizons): a seed per run, a
tenth of PPO's transitions (the recipe's budget), the deterministic policy scored on the
env's own start and on the test set's 8 developed starts, normalised as on the results
page (0: no control, 1: the env's reference).

    .venv/bin/python experiments/shac_ablation.py [--envs ...] [--variants ...] [--seed 0]
    .venv/bin/python experiments/shac_ablation.py --page docs/gradients.md

A variant is a set of settings on top of the env's defaults (``VARIANTS``). Each run
trains into ``--runs`` (``runs/shac_ablation/ENV/VARIANT/seedK``, a run folder ``beacon-torch
eval`` reads; an existing one is resumed, so that a stopped campaign goes on) and
writes a new ``ablation-ENV-VARIANT-seedK-DATE-TIME.json`` to ``--out``: the settings, the
scores, the transitions and the run's wall seconds (its own clock; compare only runs
that shared the machine alike). ``--page`` writes the newest record of each (env,
variant, seed) as the page's table, a row per (env, variant) with the mean over seeds.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve()
ROOT = HERE.parents[1]
ENVS = ("burgers-v0", "vortex-v0", "sloshing-v0")
# SAPO's pieces (Xing et al., ICLR 2025), each alone, then all of them together
VARIANTS = {
    "defaults": {},
    "stochastic": {"actor": "stochastic"},
    "twin-critics": {"critics": 2},
    "no-target": {"target_critic": False},
    "adamw": {"optimizer": "adamw"},
    "layer-norm": {"layer_norm": True},
    "clip-0.5": {"grad_clip": 0.5},
    "adaptive-horizon": {"adaptive_horizon": True},
    "mixed-estimator": {"actor": "stochastic", "estimator": "mixed"},
    "sapo": {
        "actor": "stochastic",
        "critics": 2,
        "target_critic": False,
        "optimizer": "adamw",
        "layer_norm": True,
        "grad_clip": 0.5,
    },
    # the deterministic policy's pre-squash outputs kept where tanh passes the gradient
    "squash-margin": {"squash_margin": 0.01},
    # the same loop without its critic (recipes/grad.py) at the actor-critic's settings
    "critic-less": {"critic": False},
    "critic-less-squash-margin": {"critic": False, "squash_margin": 0.01},
    # SHAC's own schedule of the rates, on the loop without its critic
    "critic-less-lr-linear": {"critic": False, "squash_margin": 0.01, "lr_schedule": "linear"},
    # each piece again on the loop without its critic (recipes/grad.py's defaults), whose
    # rewards' gradient is all the policy follows; the stochastic policy has no squash's
    # margin (its draws are squashed, not its outputs)
    "critic-less-stochastic": {"critic": False, "squash_margin": 0.0, "actor": "stochastic"},
    "critic-less-mixed-estimator": {"critic": False, "squash_margin": 0.0, "actor": "stochastic", "estimator": "mixed"},
    "critic-less-adamw": {"critic": False, "squash_margin": 0.01, "optimizer": "adamw"},
    "critic-less-layer-norm": {"critic": False, "squash_margin": 0.01, "layer_norm": True},
    "critic-less-clip-0.5": {"critic": False, "squash_margin": 0.01, "grad_clip": 0.5},
    "critic-less-adaptive-horizon": {"critic": False, "squash_margin": 0.01, "adaptive_horizon": True},
    # members staggered over an episode's phases (vortex's default): from one start a
    # deterministic policy steps identical members in step, the same transitions many times
    "critic-less-stagger": {"critic": False, "squash_margin": 0.01, "stagger": True},
    # staggered, and a larger rate for the few updates a tenth of PPO's budget holds
    "critic-less-stagger-lr-5e-3": {"critic": False, "squash_margin": 0.01, "stagger": True, "lr": 5e-3},
    # staggered, longer horizons for the same transitions
    "critic-less-stagger-horizon-32": {"critic": False, "squash_margin": 0.01, "stagger": True, "horizon": 32},
    "critic-less-stagger-horizon-64": {"critic": False, "squash_margin": 0.01, "stagger": True, "horizon": 64},
    # staggered, each member's objective in units of its own rewards' size
    "critic-less-stagger-member-scale": {"critic": False, "squash_margin": 0.01, "stagger": True, "member_scale": True},
    # staggered, every seed starting near no control (its output layer a hundredth of
    # torch's initialisation), not from a random policy of its own
    "critic-less-stagger-init-0.01": {"critic": False, "squash_margin": 0.01, "stagger": True, "init_scale": 0.01},
    "critic-less-stagger-init-0": {"critic": False, "squash_margin": 0.01, "stagger": True, "init_scale": 0.0},
    "critic-less-stagger-init-0.01-lr-5e-3": {
        "critic": False,
        "squash_margin": 0.01,
        "stagger": True,
        "init_scale": 0.01,
        "lr": 5e-3,
    },
    "critic-less-stagger-init-0.01-members-16": {
        "critic": False,
        "squash_margin": 0.01,
        "stagger": True,
        "init_scale": 0.01,
        "num_envs": 16,
    },
    "critic-less-stagger-init-0.01-members-16-lr-5e-3": {
        "critic": False,
        "squash_margin": 0.01,
        "stagger": True,
        "init_scale": 0.01,
        "num_envs": 16,
        "lr": 5e-3,
    },
    "critic-less-stagger-members-16": {"critic": False, "squash_margin": 0.01, "stagger": True, "num_envs": 16},
    # the actor-critic on the loop's own settings (recipes/grad.py's defaults), its critic
    # closing each horizon at full and at a tenth of the weight: what lies past a horizon
    # is what the loop without it cannot see. These and the longer horizons were measured
    # at the rate 5e-3, the loop's default then
    "grad-settings-critic": {"grad_settings": True, "lr": 5e-3},
    "grad-settings-value-weight-0.1": {"grad_settings": True, "value_weight": 0.1, "lr": 5e-3},
    # the loop at its own defaults with longer horizons: fewer updates, each seeing further
    # (and with fewer members, as many updates as at 16 actions)
    "grad-horizon-32": {"critic": False, "grad_settings": True, "horizon": 32, "lr": 5e-3},
    "grad-horizon-64": {"critic": False, "grad_settings": True, "horizon": 64, "lr": 5e-3},
    "grad-horizon-64-members-4": {"critic": False, "grad_settings": True, "horizon": 64, "num_envs": 4, "lr": 5e-3},
    # the loop at its own defaults with larger rates (1e-2 became the default)
    "grad-lr-1e-2": {"critic": False, "grad_settings": True, "lr": 1e-2},
    "grad-lr-2e-2": {"critic": False, "grad_settings": True, "lr": 2e-2},
    # what else might carry the later, smaller sloshing into the objective: no discount
    # within a horizon, raw observations, no clipping of its small late gradients
    "grad-gamma-1": {"critic": False, "grad_settings": True, "gamma": 1.0},
    "grad-raw-observations": {"critic": False, "grad_settings": True, "norm_steps": 0},
    "grad-clip-100": {"critic": False, "grad_settings": True, "grad_clip": 100.0},
    # half and all of sloshing's episode a horizon, with as many updates as the defaults'
    # (its episodes start from one stored state: few members still span the episode)
    "grad-horizon-100-members-2": {"critic": False, "grad_settings": True, "horizon": 100, "num_envs": 2},
    "grad-horizon-200-members-1": {
        "critic": False,
        "grad_settings": True,
        "horizon": 200,
        "num_envs": 1,
        "stagger": False,
    },
    # the defaults' very updates, with the policy's gradient through the critic's closing
    # values and through the rest logged apart (one more backward pass an update)
    "gradient-split": {"gradient_split": True},
    # the closing values at a fraction of their weight in the policy's objective
    "value-weight-0.1": {"value_weight": 0.1, "gradient_split": True},
    "value-weight-0.1-squash-margin": {"value_weight": 0.1, "squash_margin": 0.01, "gradient_split": True},
    # more updates for the same transitions: fewer members, or shorter horizons
    "members-16": {"num_envs": 16},
    "members-4": {"num_envs": 4},
    "horizon-16": {"horizon": 16},
    "horizon-8": {"horizon": 8},
}
BEGIN, END = "<!-- actor-critic settings: experiments/shac_ablation.py -->", "<!-- end of actor-critic settings -->"
SPLIT = "<!-- closing values' gradient: experiments/shac_ablation.py -->", "<!-- end of closing values' gradient -->"


def run(env_id: str, variant: str, seed: int, runs: Path, frames: int | None = None) -> dict:
    """Train one seed of ``variant`` on ``env_id`` (or finish it) and score its policy;
    ``frames``: fewer transitions than the recipe's budget (a trial)."""
    from beacon_torch.training import report
    from beacon_torch.training.config import GradConfig, SHACConfig, configure
    from beacon_torch.training.evaluation import HELD_OUT, evaluate_run
    from beacon_torch.training.run import CHECKPOINT, load_checkpoint

    out = runs / env_id / variant / f"seed{seed}"
    settings = dict(VARIANTS[variant], seed=seed, out=str(out), progress=False, threads=1, logger="csv")
    if frames is not None:
        settings["frames"] = frames
    # the two share their per-env settings but for the five the loop without a critic
    # changed: a variant is built on the actor-critic's settings unless it names the
    # loop's own, and names what differs from them, those five included
    kind = SHACConfig if settings.pop("critic", True) else GradConfig
    base = GradConfig if settings.pop("grad_settings", False) else SHACConfig
    if kind is not base:
        based = configure(base, env_id)
        for name in ("squash_margin", "stagger", "num_envs", "lr", "init_scale"):
            settings.setdefault(name, getattr(based, name))
    resume = (out / CHECKPOINT).is_file()
    cfg = configure(kind, env_id, resume=resume, **settings)
    if not resume or load_checkpoint(out)["frames"] < cfg.frames:
        recipe().main(cfg)
    state = load_checkpoint(out)
    row = {
        "env": env_id,
        "variant": variant,
        "settings": VARIANTS[variant],
        "seed": seed,
        "frames": state["frames"],
        "wall_s": state["elapsed"],
    }
    split = gradient_split(out)
    if split:
        row["gradient_split"] = split
    for name, starts in (("own", None), ("test", HELD_OUT)):
        result = evaluate_run(out, num_envs=8, starts=starts)
        row[f"{name}_score"] = result["score_mean"]
        row[f"{name}_uncontrolled"] = result["uncontrolled"]
        if report.normalisable(env_id):
            row[f"{name}_normalised"] = float(report.normalised(result["score_mean"], result["uncontrolled"], env_id))
    return row


def gradient_split(out: Path) -> dict:
    """Where the run logged its gradient split: per quarter of its updates, the medians of
    the closing values' gradient norm over the rest's, of the cosine between the two, and
    of the closing values' share of the objective (empty if not logged)."""
    from beacon_torch.training.evaluation import read_scalar

    _, closing = read_scalar(out, "closing_grad_norm")
    if not closing.size:
        return {}
    rest, cosine, share = (read_scalar(out, name)[1] for name in ("reward_grad_norm", "grad_cosine", "closing_share"))
    # the first update's critic is untrained (a zero last layer: no gradient at all)
    ratio = closing / np.maximum(rest, np.finfo(float).tiny)
    quarters = {"ratio": ratio, "cosine": cosine, "share": share}
    return {
        name: [float(np.median(part)) for part in np.array_split(values[1:], 4) if part.size]
        for name, values in quarters.items()
    }


def recipe():
    """``recipes/shac.py`` as a module."""
    from beacon_torch.arguments import load_script

    return load_script(ROOT / "recipes" / "shac.py", "recipe_shac")


def newest_records(folder: Path) -> tuple[dict, dict]:
    """The newest row of each (env, variant, seed) in ``folder``'s records, as
    ``{(env, variant): {seed: row}}``, and where and when each was measured."""
    from beacon_torch import received

    newest: dict[tuple[str, str], dict[int, dict]] = {}
    # where and when each (env, variant, seed) of the table was measured: its newest record's
    when_seed: dict[tuple[str, str, int], str] = {}
    for path in sorted(folder.glob("ablation-*.json"), key=lambda p: p.name[-20:]):
        record = received.json_file(path, "an actor-critic settings record")
        day = "-".join((path.stem[-15:-11], path.stem[-11:-9], path.stem[-9:-7]))
        cpu = str(record.get("machine", "")).split(",")[0].replace("(R)", "").replace(" Processor", "")
        for row in record["rows"]:
            newest.setdefault((row["env"], row["variant"]), {})[row["seed"]] = row
            when_seed[row["env"], row["variant"], row["seed"]] = f"{day}, {cpu}"
    return newest, when_seed


def page_table(folder: Path) -> str:
    """The newest record of each (env, variant, seed) in ``folder`` as a markdown table,
    a row per (env, variant): the mean over its seeds and each seed's score."""
    newest, when_seed = newest_records(folder)
    measured: dict[tuple[str, str], set[str]] = {}
    for (env_id, variant, _), when in when_seed.items():
        measured.setdefault((env_id, variant), set()).add(when)
    lines = [
        "| env | settings | seeds | normalised, own start: mean (seeds) | normalised, test set: mean (seeds) "
        "| transitions | minutes a seed | measured |",
        "|---|---|---|---|---|---|---|---|",
    ]

    def scores(rows: list[dict], name: str) -> str:
        if any(f"{name}_normalised" not in row for row in rows):
            return "-"
        # no control from the test starts above the reference: the scale runs backwards
        if not all(_scaled(row[f"{name}_uncontrolled"], row["env"]) for row in rows):
            return "- (a)"
        values = [row[f"{name}_normalised"] for row in rows]
        each = f" ({', '.join(f'{v:.2f}' for v in values)})" if len(values) > 1 else ""
        return f"{sum(values) / len(values):.2f}{each}"

    others = sorted({env_id for env_id, _ in newest} - set(ENVS))
    for env_id in (*ENVS, *others):
        for variant in VARIANTS:
            seeds = newest.get((env_id, variant))
            if seeds is None:
                continue
            rows = [seeds[k] for k in sorted(seeds)]
            shown = ", ".join(f"{k}={v}" for k, v in rows[0]["settings"].items()) or "the defaults"
            frames = sorted({row["frames"] for row in rows})
            minutes = sum(row["wall_s"] for row in rows) / len(rows) / 60
            when = "; ".join(sorted(measured[env_id, variant]))
            lines.append(
                f"| {env_id} | {variant}: {shown} | {len(rows)} | {scores(rows, 'own')} | {scores(rows, 'test')} | "
                f"{' or '.join(f'{f:,}' for f in frames)} | {minutes:.1f} | {when} |"
            )
    return "\n".join(lines)


def split_table(folder: Path) -> str:
    """The runs that logged their gradient split, a row per (env, variant): per quarter of
    the updates, the closing values' gradient norm over the rest's, the cosine between
    the two and the values' share of the objective (medians, each a mean over the seeds),
    beside the normalised score from the env's own start."""
    newest, _ = newest_records(folder)
    lines = [
        "| env | settings | seeds | closing / rest gradient norm, by quarter | cosine, by quarter "
        "| closing values' share of the objective, by quarter | normalised, own start |",
        "|---|---|---|---|---|---|---|",
    ]

    def quarters(rows: list[dict], name: str, form: str) -> str:
        each = np.array([row["gradient_split"][name] for row in rows]).mean(0)
        return ", ".join(format(v, form) for v in each)

    others = sorted({env_id for env_id, _ in newest} - set(ENVS))
    for env_id in (*ENVS, *others):
        for variant in VARIANTS:
            rows = [row for row in newest.get((env_id, variant), {}).values() if "gradient_split" in row]
            if not rows:
                continue
            shown = ", ".join(f"{k}={v}" for k, v in rows[0]["settings"].items() if k != "gradient_split")
            score = "-"
            if all("own_normalised" in row for row in rows):
                score = f"{sum(row['own_normalised'] for row in rows) / len(rows):.2f}"
            lines.append(
                f"| {env_id} | {variant}: {shown or 'the defaults'} | {len(rows)} | {quarters(rows, 'ratio', '.3g')} "
                f"| {quarters(rows, 'cosine', '.2f')} | {quarters(rows, 'share', '.2f')} | {score} |"
            )
    return "\n".join(lines)


def _scaled(uncontrolled: float, env_id: str) -> bool:
    from beacon_torch.training import report

    return report.scaled(uncontrolled, env_id)


def main() -> None:
    from beacon_torch.registry import continuous_envs

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", default=list(ENVS), choices=continuous_envs())
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--frames", type=int, default=None, help="fewer transitions than the budget (a trial)")
    parser.add_argument("--runs", type=Path, default=ROOT / "runs" / "shac_ablation")
    parser.add_argument("--out", type=Path, default=HERE.parent / "results" / "shac_ablation")
    parser.add_argument("--page", type=Path, default=None, help="write --out's newest records as this page's table")
    args = parser.parse_args()
    if args.page is not None:
        from beacon_torch.training.report import write_block

        print(write_block(args.page, BEGIN, END, page_table(args.out)))
        print(write_block(args.page, *SPLIT, split_table(args.out)))
        return
    from beacon_torch.files import save_rows

    for env_id in args.envs:
        for variant in args.variants:
            row = run(env_id, variant, args.seed, args.runs, args.frames)
            print(
                f"{env_id} {variant}: own {row.get('own_normalised', float('nan')):.2f}, "
                f"test {row.get('test_normalised', float('nan')):.2f}, {row['wall_s'] / 60:.1f} min",
                flush=True,
            )
            print(
                f"written to {save_rows([row], args.out, f'ablation-{env_id}-{variant}-seed{args.seed}')}", flush=True
            )


if __name__ == "__main__":
    main()
