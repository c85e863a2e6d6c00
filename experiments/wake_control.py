"""The drag of a wake-control env (cylinder-v0, the pinball levels) under trained
policies against no control, per action.

    .venv/bin/python experiments/wake_control.py POLICY [POLICY ...] [--episodes 3] [--out DIR]
    .venv/bin/python experiments/wake_control.py --plot RECORD.json FIGURE.png [--base-flow CD]

POLICY: a run directory (``runs/ppo/cylinder-v0/seed0``), a policy file
(``pretrained.export``'s) or a shipped pair (``ppo/cylinder-v0``), run on the env and
the env parameters it was trained with. From the developed start, each deterministic
policy acts for ``--episodes`` episodes' worth of actions (at each episode's end the
env's counter is set back and the flow goes on), with an uncontrolled member beside
it, in float32 as the policies were trained. Per action it records the env's
diagnostics (the drag and lift coefficients, the actuation) and rewards of both, and it
reports the mean drag coefficient over the first episode (the actions every training
and evaluation episode has) and over the second half of the run (the regime, what
Rabault et al.'s single runs report), each against no control over the same actions.
Writes a new dated ``ENV_control-DATE-TIME.json`` to ``--out``; ``--carry RECORD``
puts an earlier record's rows of the same env and run length ahead of the new ones (a
policy added to a table whose other policies' run folders are on another machine), each
naming the record and machine it was measured on. ``--plot`` draws a
record's drag and actuation into a new figure (the cylinder page's
docs/img/cylinder-control.png), with ``--base-flow`` the drag of the steady base flow
as a line. The quantities are the env's diagnostics and the figure is drawn as
``beacon-torch eval`` draws them (``--figure``): what this script adds is the run past
an episode's end.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path


def wake(env_id: str) -> tuple[str, float]:
    """The diagnostic drawn beside the drag and the time units of an action of the wake
    env ``env_id``; a one-line error for an env that is not one."""
    from beacon_torch.envs import cylinder, pinball

    wakes = {
        "cylinder": ("jet", cylinder.DT * cylinder.SUBSTEPS),
        "pinball": ("power", pinball.DT * pinball.SUBSTEPS),
    }
    name = str(env_id).split("-")[0]
    if name not in wakes:
        raise ValueError(f"{env_id} is not a wake-control env (a {' or '.join(wakes)} env)")
    return wakes[name]


def policy_of(name: str):
    """The raw-observation policy of a run directory, a policy file or a shipped pair,
    the env it was trained on and its parameters."""
    from beacon_torch import pretrained, received

    if Path(name).is_dir():
        with tempfile.TemporaryDirectory() as folder:
            return policy_of(str(pretrained.export(name, Path(folder) / "policy.pt")))
    if Path(name).is_file():
        policy = pretrained.load_file(name)
        record = received.torch_file(name, "policy file")
        return policy, record["env"], record.get("params", {})
    info = pretrained.info(name)
    return pretrained.load(name), info["env"], info.get("params", {})


def control(name: str, episodes: int, compile: bool = True, loaded=None) -> dict:
    """``episodes`` episodes' worth of actions of the policy ``name`` and of no control
    from the developed start, per action and in the two means; ``loaded``: what
    ``policy_of(name)`` gives, when already read."""
    import numpy as np
    import torch

    import beacon_torch

    policy, env_id, params = loaded or policy_of(name)
    wake(env_id)
    env = beacon_torch.make(env_id, 2, compile=compile, params=params)  # the policy's member, no control
    actions = episodes * env.episode_length
    td = env.reset()
    keys = list(env.physics.diagnostics) + ["reward"]
    rows = {key: [] for key in keys} | {f"uncontrolled_{key}": [] for key in keys}
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
            for key in keys:
                seen = (td["reward"] if key == "reward" else td["diagnostics", key]).reshape(2).tolist()
                rows[key].append(seen[0])
                rows[f"uncontrolled_{key}"].append(seen[1])
    drag, free = np.array(rows["drag"]), np.array(rows["uncontrolled_drag"])
    episode, half = slice(0, env.episode_length), slice(actions // 2, actions)
    reduction = lambda part: float(1.0 - drag[part].mean() / free[part].mean())
    return {
        "policy": name,
        "env": env_id,
        "params": params,
        "actions": actions,
        "episode_length": env.episode_length,
        "cd_episode": float(drag[episode].mean()),
        "cd_episode_uncontrolled": float(free[episode].mean()),
        "reduction_episode": reduction(episode),
        "cd_second_half": float(drag[half].mean()),
        "cd_second_half_uncontrolled": float(free[half].mean()),
        "reduction_second_half": reduction(half),
        "score_episode": float(np.sum(rows["reward"][episode])),
        "score_episode_uncontrolled": float(np.sum(rows["uncontrolled_reward"][episode])),
        "per_action": rows,
    }


# what a row of a record holds that the tables and validation/wake_reference.py read
ROW_NUMBERS = (
    "cd_episode",
    "cd_episode_uncontrolled",
    "reduction_episode",
    "cd_second_half",
    "cd_second_half_uncontrolled",
    "reduction_second_half",
    "score_episode",
    "score_episode_uncontrolled",
)


def carried(path: str, episodes: int) -> list[dict]:
    """The rows of an earlier record of this script (read as received data), each run
    for ``episodes`` episodes' worth of actions with finite numbers, marked with the
    record and machine they were measured on; a one-line error for any other file."""
    from beacon_torch import received

    record = received.json_file(path, "control record")
    rows = record.get("rows") if isinstance(record, dict) else None
    if not isinstance(rows, list) or not rows:
        raise ValueError(f"{path}: not a record of experiments/wake_control.py (no rows)")
    for k, row in enumerate(rows):
        where = f"{path}: row {k}"
        if not isinstance(row, dict) or not isinstance(row.get("policy"), str) or not isinstance(row.get("env"), str):
            raise ValueError(f"{where} names no policy and env")
        wake(row["env"])
        length, actions = row.get("episode_length"), row.get("actions")
        if not isinstance(length, int) or isinstance(length, bool) or actions != episodes * length:
            raise ValueError(f"{where}: {actions!r} actions, not {episodes} episodes' worth")
        if not isinstance(row.get("params"), dict) or not all(received.finite_number(row.get(k)) for k in ROW_NUMBERS):
            raise ValueError(f"{where}: its parameters or its means are not a record's")
        per_action = row.get("per_action")
        if not isinstance(per_action, dict) or not all(
            isinstance(v, list) and len(v) == actions and all(map(received.finite_number, v))
            for v in per_action.values()
        ):
            raise ValueError(f"{where}: its per-action values are not {actions} finite numbers each")
        row.setdefault("record", Path(path).name)
        row.setdefault("machine", str(record.get("machine", "")))
    return rows


def table(rows: list[dict]) -> str:
    lines = [
        f"| policy | mean C_D, first episode ({rows[0]['episode_length']} actions) | no control | reduction "
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


def rotation_table(rows: list[dict]) -> str:
    """The pinball policies' actuation beside their drag: the rotations' mean power and
    the net drag power (drag and power coefficients summed) over the first episode
    against no control's drag, the episode's reward, and over the second half of the
    run each cylinder's mean rate as a fraction of the bound (positive
    anticlockwise), the summed lift and the drag's standard deviation beside no
    control's (how much of the shedding's fluctuation the control leaves)."""
    import numpy as np

    from beacon_torch.envs import pinball

    n = rows[0]["episode_length"]
    lines = [
        f"| policy | mean power, first episode ({n} actions) | net drag power against no control | episode reward "
        "| no control | rates of the bound, second half: front, top, bottom | mean lift, second half "
        "| standard deviation of C_D, second half: policy, no control |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        seen = {key: np.array(values) for key, values in r["per_action"].items()}
        first, half = slice(0, n), slice(r["actions"] // 2, r["actions"])
        net = 1.0 - (seen["drag"][first] + seen["power"][first]).mean() / seen["uncontrolled_drag"][first].mean()
        bound = float(r["params"].get("max_rotation", pinball.PinballParams().max_rotation))
        rates = ", ".join(f"{seen[f'omega_{c}'][half].mean() / bound:+.2f}" for c in ("front", "top", "bottom"))
        lines.append(
            f"| {r['policy']} | {seen['power'][first].mean():.2f} | {-100 * net:+.1f} % | {r['score_episode']:.1f} "
            f"| {r['score_episode_uncontrolled']:.1f} | {rates} | {seen['lift'][half].mean():+.2f} "
            f"| {seen['drag'][half].std():.4f}, {seen['uncontrolled_drag'][half].std():.4f} |"
        )
    return "\n".join(lines)


def plot(record: str, figure: str, base_flow: float | None = None) -> None:
    """A record's drag coefficients and actuation over time, drawn as ``beacon-torch
    eval`` draws an env's diagnostics (``evaluation.draw_diagnostics``); ``base_flow``:
    the steady base flow's drag coefficient, drawn as a line."""
    import json

    import numpy as np

    from beacon_torch.files import refuse_existing
    from beacon_torch.training.evaluation import draw_diagnostics

    refuse_existing([figure], "give another FIGURE")
    rows = json.loads(open(record).read())["rows"]
    env_id = rows[0].get("env", "cylinder-v0")  # the cylinder's first records name no env
    actuation, action_time = wake(env_id)
    first = rows[0]["per_action"]
    series = [("no control", {"drag": first["uncontrolled_drag"], actuation: np.zeros(len(first[actuation]))})]
    series += [(r["policy"], {"drag": r["per_action"]["drag"], actuation: r["per_action"][actuation]}) for r in rows]
    lines = None if base_flow is None else {"drag": (base_flow, f"steady base flow ({base_flow:.3f})")}
    times = action_time * np.arange(1, rows[0]["actions"] + 1)
    length = rows[0].get("episode_length", 80)
    title = f"{env_id} from the developed start\n(the episode's counter set back every {length} actions)"
    print(
        "figure:",
        draw_diagnostics(series, figure, title=title, times=times, xlabel="time from the developed start", lines=lines),
    )


def main() -> None:
    from beacon_torch.files import save_rows

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("policies", nargs="*", help="run directories, policy files or shipped pairs (ALGO/ENV)")
    parser.add_argument("--episodes", type=int, default=3, help="episodes' worth of actions from the developed start")
    parser.add_argument("--no-compile", action="store_true", help="eager physics")
    parser.add_argument("--out", default="runs/wake_control")
    parser.add_argument("--carry", metavar="RECORD", help="an earlier record whose rows go ahead of the new ones")
    parser.add_argument("--plot", nargs=2, metavar=("RECORD", "FIGURE"), help="draw a record's drag and actuation")
    parser.add_argument("--base-flow", type=float, help="with --plot: the steady base flow's drag coefficient (a line)")
    args = parser.parse_args()
    if args.plot:
        return plot(*args.plot, base_flow=args.base_flow)
    if not args.policies:
        parser.error("name at least one policy (a run directory, a policy file or ALGO/ENV)")
    if args.episodes < 1:
        parser.error(f"--episodes must be at least 1, got {args.episodes}")
    try:
        earlier = carried(args.carry, args.episodes) if args.carry else []
        loaded = {name: policy_of(name) for name in args.policies}
        envs = {env_id for _, env_id, _ in loaded.values()} | {row["env"] for row in earlier}
        wake(min(envs))
    except (ValueError, FileNotFoundError) as err:
        parser.error(str(err))
    if len(envs) > 1:
        parser.error(f"the policies are of different envs ({', '.join(sorted(envs))}): one env a record")
    twice = sorted({row["policy"] for row in earlier} & set(args.policies))
    if twice:
        parser.error(f"{', '.join(twice)}: in the carried record already")
    rows = earlier + [control(name, args.episodes, not args.no_compile, loaded[name]) for name in args.policies]
    print(table(rows))
    if wake(rows[0]["env"])[0] == "power":  # the pinball's rotations
        print(rotation_table(rows))
    print("results:", save_rows(rows, args.out, f"{rows[0]['env'].removesuffix('-v0')}_control"))


if __name__ == "__main__":
    main()
