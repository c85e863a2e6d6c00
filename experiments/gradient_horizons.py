"""How the gradient of a differentiated horizon grows with its length: per env, the norm
of the gradient of the horizon's discounted return (the gradient recipes' objective)
with respect to a fresh policy's weights, for horizons from one action to an episode.

    .venv/bin/python experiments/gradient_horizons.py --envs lorenz-continuous-v0 burgers-v0
        [--members 8] [--horizons 1 2 4 8 ...] [--param NAME=VALUE] [--seed 0] [--grad-checkpoint] [--out DIR]
    .venv/bin/python experiments/gradient_horizons.py --page docs/gradients.md

Each horizon starts from the same states (the env's own starts, after the recipes'
64 random steps that set the observation normalisation), the policy TD3's
deterministic actor as the gradient recipes build it (torch's initialisation, the
seed's), float32 as the recipes run. What is recorded per horizon: the gradient's
norm, whether it was finite, the members that blew up and the CPU time. A chaotic
env's norm grows exponentially with the horizon past its Lyapunov time: the longest
horizon whose gradient still carries information is what the recipes' default
horizons are chosen from (:func:`knee`, :func:`default_horizon`). Writes, per env, a
new ``gradient-horizons-ENV-DATE-TIME.json`` (machine, rows) and a figure beside it;
``--page`` writes the newest record of each env in ``--out`` as the page's table and
its figure (``docs/img/gradient-horizons.png``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve()
BEGIN, END = "<!-- gradient horizons: experiments/gradient_horizons.py -->", "<!-- end of gradient horizons -->"


class Start:
    """One env's starts and a fresh policy, built once (the 64 random actions of the
    observation normalisation cost more than a short horizon on the 2-D flows): every
    horizon measured from it begins from the same states, generator and weights, as if
    the env and policy were built anew (``checkpoint``: each action recomputed in the
    backward pass, as the recipes run the 2-D flows)."""

    def __init__(
        self,
        env_id: str,
        members: int,
        seed: int,
        params: dict | None = None,
        checkpoint: bool = False,
        device: str = "cpu",
    ):
        from beacon_torch.core.state import map_state
        from beacon_torch.training import networks
        from beacon_torch.training.env import NORM_STEPS, make_env

        self.env_id, self.members, self.params, self.checkpoint, self.device = (
            env_id,
            members,
            params or {},
            checkpoint,
            str(device),
        )
        self.env = make_env(
            env_id,
            members,
            seed=seed,
            norm_steps=NORM_STEPS,
            differentiable=True,
            grad_checkpoint=checkpoint,
            compile=False,
            device=device,
            params=self.params,
        )
        torch.manual_seed(seed)
        self.actor = networks.deterministic_actor(self.env, 64, paper_init=False).to(device)
        self.td = self.env.reset().clone()
        base = self.env.base_env
        self.state = map_state(torch.Tensor.clone, base.state)
        self.count, self.rng = base.step_count.clone(), base.rng.get_state()

    def norm(self, horizon: int, gamma: float = 0.99) -> dict:
        """The gradient norm of one horizon of ``horizon`` actions from the starts."""
        env, base = self.env, self.env.base_env
        base.set_state(self.state, self.count)
        base.rng.set_state(self.rng)
        td = self.td.clone()
        synchronize(self.device)
        start, wall = time.process_time(), time.perf_counter()
        total, ended = 0.0, torch.zeros(self.members, dtype=torch.bool, device=self.device)
        for h in range(horizon):
            td, td_next = env.step_and_maybe_reset(self.actor(td))
            total = total + gamma**h * td["next", "reward"][..., 0]
            ended |= td["next", "terminated"][..., 0]
            td = td_next
        loss = -total.mean() / horizon
        grads = torch.autograd.grad(loss, list(self.actor.parameters()), allow_unused=True)
        norm = torch.linalg.vector_norm(torch.stack([g.norm() for g in grads if g is not None]))
        synchronize(self.device)
        return dict(
            env=self.env_id,
            params=self.params,
            horizon=horizon,
            members=self.members,
            norm=float(norm),
            finite=bool(torch.isfinite(norm)),
            blown_up=int(ended.sum()),
            grad_checkpoint=self.checkpoint,
            device=self.device,
            cpu_s=time.process_time() - start,
            wall_s=time.perf_counter() - wall,
        )


def synchronize(device) -> None:
    # a GPU's queued work must end inside the interval it is timed in
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def horizons_within(env_id: str, horizons: list[int], measure, budget_s: float | None) -> list[dict]:
    """``measure(h)`` for each horizon in increasing order, stopping before a horizon
    whose predicted time (the last one's, scaled by the horizons' ratio) would take
    the run past ``budget_s`` seconds of wall time; the horizons left out are printed."""
    rows, spent = [], 0.0
    for h in sorted(horizons):
        if budget_s is not None and rows:
            predicted = rows[-1]["wall_s"] * h / rows[-1]["horizon"]
            if spent + predicted > budget_s:
                left = [k for k in horizons if k >= h]
                print(f"{env_id}: horizons {left} left out, past the {budget_s:.0f} s budget", flush=True)
                break
        row = measure(h)
        spent += row["wall_s"]
        rows.append(row)
        print(
            f"{env_id} horizon {h}: norm {row['norm']:.4g} ({row['blown_up']} blown up, "
            f"{row['cpu_s']:.1f} CPU s, {row['wall_s']:.1f} s)",
            flush=True,
        )
    return rows


def draw(rows: list[dict], path: Path, new: bool = True) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from beacon_torch.files import save_figure

    fig = Figure(figsize=(6.5, 4), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for env_id in dict.fromkeys(r["env"] for r in rows):
        own = [r for r in rows if r["env"] == env_id and r["finite"] and r["norm"] > 0]
        ax.plot([r["horizon"] for r in own], [r["norm"] for r in own], "o-", ms=3, label=env_id)
    ax.set_xscale("log")
    if any(r["finite"] and r["norm"] > 0 for r in rows):
        ax.set_yscale("log")
    zero = sorted({r["env"] for r in rows} - {r["env"] for r in rows if r["norm"] > 0})
    if zero:  # a reward that is piecewise constant in the state: no gradient at all
        ax.set_title(f"zero gradient at every horizon: {', '.join(zero)}", fontsize=8)
    ax.set_xlabel("differentiated actions in the horizon")
    ax.set_ylabel("gradient norm of the horizon's return")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, new=new)


# a doubling of the horizon that multiplies the gradient's norm by more than this,
# past anything shorter horizons gave, marks where it starts growing exponentially
KNEE_GROWTH = 10.0
# the short-horizon actor-critic's own default (Xu et al.): the longest horizon chosen
CAP = 32


def knee(rows: list[dict]) -> int | None:
    """The longest measured horizon before the gradient's norm starts growing
    exponentially: the first horizon ``h`` (of 8 actions or more, past the start-up of
    a reward that reacts late) whose next measured horizon's norm exceeds
    ``KNEE_GROWTH`` times the largest at ``h`` or below (a non-finite norm counts as
    growth); None if the norm never grows so within an episode."""
    rows = sorted(rows, key=lambda r: r["horizon"])
    for k in range(len(rows) - 1):
        seen = max(r["norm"] for r in rows[: k + 1])
        after = rows[k + 1]
        if rows[k]["horizon"] >= 8 and (not after["finite"] or after["norm"] > KNEE_GROWTH * seen):
            return rows[k]["horizon"]
    return None


def default_horizon(rows: list[dict]) -> int:
    """The horizon the measurements allow the recipes: the knee's (or an episode's),
    at most ``CAP``, a power of two."""
    longest = knee(rows) or max(r["horizon"] for r in rows)
    return min(CAP, 2 ** (int(longest).bit_length() - 1))


def reaches_episode(rows: list[dict]) -> bool:
    """Whether the measured horizons reach the env's episode, or a knee was found: only
    then does :func:`default_horizon` bound what the recipes may differentiate (a record
    cut short by its time budget says nothing of the horizons it left out)."""
    from beacon_torch.registry import env_spec

    return knee(rows) is not None or max(r["horizon"] for r in rows) >= env_spec(rows[0]["env"]).physics.episode_length


def newest(folder: Path) -> dict[str, list[dict]]:
    """The newest record's rows of each env in ``folder`` (lorenz's with its smooth
    reward: its default one has no gradient)."""
    from beacon_torch import received

    found: dict[str, tuple[str, list[dict]]] = {}
    for path in sorted(folder.glob("gradient-horizons-*.json"), key=lambda p: p.name[-20:]):
        rows = received.json_file(path, "a gradient horizons record")["rows"]
        for env_id in dict.fromkeys(r["env"] for r in rows):
            own = [r for r in rows if r["env"] == env_id]
            if any(r["norm"] > 0 for r in own):
                found[env_id] = own
    return found


def page_table(records: dict[str, list[dict]]) -> str:
    from beacon_torch.training.config import SHACConfig, configure

    lines = [
        "| env | horizons measured | members | norm at 1 / 8 / 32 actions | norm at the longest | knee "
        "| default horizon | the actor-critic's horizon |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for env_id, rows in records.items():
        by = {r["horizon"]: r for r in rows}
        at = " / ".join(f"{by[h]['norm']:.2g}" if h in by else "-" for h in (1, 8, 32))
        last = max(rows, key=lambda r: r["horizon"])
        found, whole, longest = knee(rows), reaches_episode(rows), last["horizon"]
        if whole:
            measured, knee_cell, default = f"1 to {longest}", found or "none", default_horizon(rows)
        else:
            measured, knee_cell = f"1 to {longest} (time budget)", f"none to {longest}"
            default = f"{default_horizon(rows)} or more"
        lines.append(
            f"| {env_id} | {measured} | {rows[0]['members']} | {at} | {last['norm']:.2g} ({longest}) "
            f"| {knee_cell} | {default} | {configure(SHACConfig, env_id).horizon} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", default=[], help="env ids with continuous actions")
    parser.add_argument(
        "--page",
        type=Path,
        default=None,
        help="write the newest record of each env in --out as the table and figure of this page",
    )
    parser.add_argument("--members", type=int, default=8)
    parser.add_argument("--horizons", nargs="+", type=int, default=None, help="default: 1, 2, 4, ... to an episode")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", help="a physical parameter")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--budget-s",
        type=float,
        default=None,
        help="per env: leave out the longer horizons that would take it past this many seconds",
    )
    parser.add_argument("--grad-checkpoint", action="store_true", help="recompute each action in the backward pass")
    parser.add_argument("--out", type=Path, default=HERE.parent / "results" / "gradient_horizons")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    from beacon_torch.files import save_rows
    from beacon_torch.params import parse_assignments
    from beacon_torch.registry import env_spec

    params = dict(parse_assignments(args.param))
    if args.page is not None:
        from beacon_torch.training.report import write_block

        records = newest(args.out)
        draw(
            [r for rows in records.values() for r in rows],
            args.page.parent / "img" / "gradient-horizons.png",
            new=False,
        )
        print(write_block(args.page, BEGIN, END, page_table(records)))
        return
    if not args.envs:
        parser.error("give --envs to measure, or --page to write the records")
    for env_id in args.envs:
        length = env_spec(env_id).physics.episode_length
        horizons = args.horizons or sorted({*(2**k for k in range(length.bit_length()) if 2**k <= length), length})
        start = Start(env_id, args.members, args.seed, params, checkpoint=args.grad_checkpoint, device=args.device)
        rows = horizons_within(env_id, horizons, start.norm, args.budget_s)
        # a record per env, written as soon as it is measured
        path = save_rows(rows, args.out, f"gradient-horizons-{env_id}")
        draw(rows, path.with_suffix(".png"))
        print(f"written to {path} and {path.with_suffix('.png')}", flush=True)


if __name__ == "__main__":
    main()
