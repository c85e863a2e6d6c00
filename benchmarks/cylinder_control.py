"""The drag of cylinder-v0 under trained policies against no control, per action.

    .venv/bin/python benchmarks/cylinder_control.py POLICY [POLICY ...] [--actions 240] [--out DIR]
    .venv/bin/python benchmarks/cylinder_control.py --plot RECORD.json FIGURE.png [--base-flow RECORD.json]

POLICY: a run directory (``runs/ppo/cylinder-v0/seed0``), a policy file
(``pretrained.export``'s) or a shipped pair (``ppo/cylinder-v0``), run on the env
parameters it was trained with. From the developed start, each deterministic policy acts for
``--actions`` actions (three episodes' worth by default: at each episode's end the
env's counter is set back and the flow goes on), with an uncontrolled member beside
it, in float32 as the policies were trained. Per action it records the drag and lift
coefficients of both and the jets' rate, and it reports the mean drag coefficient over
the first episode (the 80 actions every training and evaluation episode has) and over
the second half of the run (the regime Rabault et al. report, their single runs'
measure), each against no control over the same actions. Writes a new dated
``cylinder_control-DATE-TIME.json`` to ``--out``. ``--plot`` draws a record's drag
coefficients and jets' rates into a new figure (the page's,
docs/img/cylinder-control.png), with ``--base-flow`` the drag of the steady base flow
(`python -m beacon_torch.envs.cylinder.base_flow`) as a line. The quantities are the env's diagnostics
and the figure is drawn as ``beacon-torch eval`` draws them (``--figure``): what this
script adds is the run past an episode's end.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path


def policy_of(name: str):
    """The raw-observation policy of a run directory, a policy file or a shipped pair,
    and the env parameters it was trained with."""
    from beacon_torch import pretrained, received

    if Path(name).is_dir():
        with tempfile.TemporaryDirectory() as folder:
            return policy_of(str(pretrained.export(name, Path(folder) / "policy.pt")))
    if Path(name).is_file():
        policy = pretrained.load_file(name, "cylinder-v0")
        return policy, received.torch_file(name, "policy file").get("params", {})
    return pretrained.load(name), pretrained.info(name).get("params", {})


def control(name: str, actions: int, compile: bool = True) -> dict:
    """``actions`` actions of the policy ``name`` and of no control from the developed
    start, per action and in the two means."""
    import numpy as np
    import torch

    import beacon_torch

    policy, params = policy_of(name)
    env = beacon_torch.make("cylinder-v0", 2, compile=compile, params=params)  # the policy's member, no control
    td = env.reset()
    rows = {"drag": [], "lift": [], "uncontrolled_drag": [], "uncontrolled_lift": [], "jet": []}
    with torch.no_grad():
        for k in range(actions):
            if k and k % env.episode_length == 0:
                # the episode's end: the flow goes on from where it is
                env.set_state(env.state, 0)
                td = env.current()
            action = policy(td.clone())[env.action_key]
            action[1] = env.null_action()[1]
            td = env.step(td.set(env.action_key, action))["next"]
            # the env's own diagnostics, as beacon-torch eval draws them
            seen = {key: td["diagnostics", key].tolist() for key in ("drag", "lift", "jet")}
            rows["drag"].append(seen["drag"][0])
            rows["lift"].append(seen["lift"][0])
            rows["uncontrolled_drag"].append(seen["drag"][1])
            rows["uncontrolled_lift"].append(seen["lift"][1])
            rows["jet"].append(seen["jet"][0])
    drag, free = np.array(rows["drag"]), np.array(rows["uncontrolled_drag"])
    episode, half = slice(0, env.episode_length), slice(actions // 2, actions)
    reduction = lambda part: float(1.0 - drag[part].mean() / free[part].mean())
    return {
        "policy": name,
        "params": params,
        "actions": actions,
        "cd_episode": float(drag[episode].mean()),
        "cd_episode_uncontrolled": float(free[episode].mean()),
        "reduction_episode": reduction(episode),
        "cd_second_half": float(drag[half].mean()),
        "cd_second_half_uncontrolled": float(free[half].mean()),
        "reduction_second_half": reduction(half),
        "per_action": rows,
    }


def table(rows: list[dict]) -> str:
    lines = [
        "| policy | mean C_D, first episode (80 actions) | no control | reduction "
        "| mean C_D, second half of the run | no control | reduction |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['policy']} | {r['cd_episode']:.4f} | {r['cd_episode_uncontrolled']:.4f} | "
            f"{100 * r['reduction_episode']:.1f} % | {r['cd_second_half']:.4f} | "
            f"{r['cd_second_half_uncontrolled']:.4f} | {100 * r['reduction_second_half']:.1f} % |"
        )
    return "\n".join(lines)


def plot(record: str, figure: str, base_flow: str | None = None) -> None:
    """A record's drag coefficients and jets' rates over time, drawn as ``beacon-torch
    eval`` draws an env's diagnostics (``evaluation.draw_diagnostics``)."""
    import json

    import numpy as np

    from beacon_torch.envs import cylinder
    from beacon_torch.files import refuse_existing
    from beacon_torch.training.evaluation import draw_diagnostics

    refuse_existing([figure], "give another FIGURE")
    rows = json.loads(open(record).read())["rows"]
    first = rows[0]["per_action"]
    series = [("no control", {"drag": first["uncontrolled_drag"], "jet": np.zeros(len(first["jet"]))})]
    series += [(r["policy"], {"drag": r["per_action"]["drag"], "jet": r["per_action"]["jet"]}) for r in rows]
    lines = None
    if base_flow:
        cd = json.loads(open(base_flow).read())["rows"][0]["cd_base"]
        lines = {"drag": (cd, f"steady base flow ({cd:.3f})")}
    times = cylinder.DT * cylinder.SUBSTEPS * np.arange(1, rows[0]["actions"] + 1)
    title = "cylinder-v0 from the developed start: the episode's counter set back every 80 actions"
    print(
        "figure:",
        draw_diagnostics(series, figure, title=title, times=times, xlabel="time from the developed start", lines=lines),
    )


def main() -> None:
    from beacon_torch.files import save_rows

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("policies", nargs="*", help="run directories or shipped pairs (ALGO/cylinder-v0)")
    parser.add_argument("--actions", type=int, default=240, help="actions from the developed start")
    parser.add_argument("--no-compile", action="store_true", help="eager physics")
    parser.add_argument("--out", default="runs/cylinder_control")
    parser.add_argument("--plot", nargs=2, metavar=("RECORD", "FIGURE"), help="draw a record's drag and jets")
    parser.add_argument("--base-flow", help="with --plot: a record of beacon_torch.envs.cylinder.base_flow (a line)")
    args = parser.parse_args()
    if args.plot:
        return plot(*args.plot, base_flow=args.base_flow)
    if not args.policies:
        parser.error("name at least one policy (a run directory or ALGO/cylinder-v0)")
    if args.actions < 80:
        parser.error(f"--actions must cover an episode (80), got {args.actions}")
    rows = [control(name, args.actions, not args.no_compile) for name in args.policies]
    print(table(rows))
    print("results:", save_rows(rows, args.out, "cylinder_control"))


if __name__ == "__main__":
    main()
