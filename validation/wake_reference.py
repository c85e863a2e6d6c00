"""The "= 1" of a wake-control env's normalised score (cylinder-v0, the pinball levels):
the reward of an episode that passes through the measured transient and then holds the
steady base flow's drag, with no lift and no actuation.

    .venv/bin/python validation/wake_reference.py CONTROL.json BASE_FLOW.json [--out DIR]

CONTROL.json is a record of ``experiments/wake_control.py`` (the drag per action of
trained policies of one env from the developed start, beside no control), BASE_FLOW.json
the record of the env's steady base flow: ``python -m beacon_torch.envs.cylinder.base_flow``'s
for the cylinder, ``validation/pinball.py base``'s for the pinball (the level's
Re on the policies' grid). A controller that only stabilises the wake cannot bring the
drag below the base flow's, and cannot reach it at once: the shedding takes a transient
to die out. Its end is measured on the recorded policies as a settling time: the first
action from which the best policy's drag excess over the base flow stays within a tenth
of the uncontrolled shedding's mean excess (90 % of the reachable reduction). The
reference episode has the best policy's rewards up to there, then the base flow's
reward at every remaining action (the cylinder's: Rabault et al.'s, -(C_D(base) -
0.159) in force, no lift; the pinball's: minus the summed drag, no power). Also
recorded, per policy and for no control: the drag reduction over the evaluation
episode and in the regime after the transient, the numbers the env's page sets beside
the published ones. Writes a new dated ``ENV_reference-DATE-TIME.json``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve()
# the share of the uncontrolled excess over the base flow's drag left at the end of
# the transient
SETTLED = 0.1


def cylinder_rewards(drag, lift):
    """cylinder-v0's reward of an action of mean drag and lift coefficients (Rabault et
    al.'s: the drag below an offset, less a lift penalty, in force)."""
    from beacon_torch.envs.cylinder.channel import DIAMETER, DRAG_OFFSET, LIFT_PENALTY, U_MEAN

    force = U_MEAN**2 * DIAMETER / 2.0  # the force of a unit coefficient
    return DRAG_OFFSET - force * drag - LIFT_PENALTY * force * np.abs(lift)


def held(env_id: str, base_flow: dict, params: dict) -> tuple[float, float]:
    """The steady base flow's drag coefficient (the pinball's: summed over its
    cylinders) in the record ``base_flow``, for ``env_id`` with ``params``, and the
    reward of an action that holds it."""
    from beacon_torch.registry import ENVS

    if env_id == "cylinder-v0":
        cd_base = base_flow["rows"][0]["cd_base"]
        return cd_base, float(cylinder_rewards(cd_base, 0.0))
    if env_id.startswith("pinball"):
        spec = ENVS[env_id]
        level = spec.physics.Params(**{**spec.physical_defaults(), **params})
        cells, re = int(level.cells_per_diameter), float(level.re)
        for row in base_flow["rows"]:
            for found in row["levels"] if row["cells_per_diameter"] == cells else []:
                if found["re"] == re:
                    cd_base = float(sum(found["drag_base"]))
                    return cd_base, -cd_base
        raise ValueError(f"the base-flow record has no flow at Re {re:g} on {cells} cells per diameter")
    raise ValueError(f"{env_id} is not a wake-control env with a recorded base flow")


def reference(control: dict, base_flow: dict) -> dict:
    """The reference episode's reward and what it is made of, from the two records'
    contents (their ``rows``)."""
    first = control["rows"][0]
    env_id = first.get("env", "cylinder-v0")  # the cylinder's first records name no env
    cd_base, held_reward = held(env_id, base_flow, first.get("params", {}))
    n = first.get("episode_length", 80)
    policies = []
    for row in control["rows"]:
        drag = np.asarray(row["per_action"]["drag"][:n])
        free = np.asarray(row["per_action"]["uncontrolled_drag"][:n])
        if "reward" in row["per_action"]:
            rewards = np.asarray(row["per_action"]["reward"][:n])
        else:  # the cylinder's first records hold the drag and lift, not the reward
            rewards = cylinder_rewards(drag, np.asarray(row["per_action"]["lift"][:n]))
        policies.append(dict(policy=row["policy"], drag=drag, free=free, rewards=rewards))
    excess = np.mean(policies[0]["free"]) - cd_base
    threshold = cd_base + SETTLED * excess
    # per policy: the first action from which its drag stays under the threshold
    for p in policies:
        above = np.nonzero(p["drag"] > threshold)[0]
        p["settled_at"] = int(above[-1] + 1) if len(above) else 0
    best = min(policies, key=lambda p: (p["settled_at"], -p["rewards"][: p["settled_at"]].sum()))
    end = best["settled_at"]
    if end >= n:
        raise ValueError(f"no recorded policy settles within an episode ({n} actions) below C_D {threshold:.4f}")
    value = float(best["rewards"][:end].sum() + (n - end) * held_reward)

    def reduction(drag, free) -> float:
        return float(1.0 - np.mean(drag) / np.mean(free))

    return {
        "env": env_id,
        "reference": value,
        "transient_actions": end,
        "transient_policy": best["policy"],
        "settled_threshold_cd": float(threshold),
        "settled_share": SETTLED,
        "cd_base": cd_base,
        "cd_uncontrolled": float(np.mean(policies[0]["free"])),
        "held_reward_per_action": float(held_reward),
        "episode_actions": n,
        "reference_reduction_episode": float(
            1.0 - (best["drag"][:end].sum() + (n - end) * cd_base) / (n * np.mean(policies[0]["free"]))
        ),
        "reference_reduction_regime": float(1.0 - cd_base / np.mean(policies[0]["free"][end:])),
        "policies": [
            dict(
                policy=p["policy"],
                score=float(p["rewards"].sum()),
                settled_at=p["settled_at"],
                reduction_episode=reduction(p["drag"], p["free"]),
                reduction_regime=reduction(p["drag"][end:], p["free"][end:]),
            )
            for p in policies
        ],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("control", type=Path, help="a record of experiments/wake_control.py")
    parser.add_argument("base_flow", type=Path, help="the record of the env's steady base flow")
    parser.add_argument("--out", type=Path, help="where the record goes (default: benchmarks/results/ENV_FAMILY)")
    args = parser.parse_args()
    from beacon_torch import received
    from beacon_torch.files import save_rows

    records = [
        received.json_file(path, what) for path, what in ((args.control, "control"), (args.base_flow, "base flow"))
    ]
    try:
        result = reference(*records)
    except (KeyError, TypeError, ValueError) as err:
        parser.error(f"{args.control.name} and {args.base_flow.name}: {err}")
    family = result["env"].split("-")[0]
    out = args.out or HERE.parent / "results" / family
    result["records"] = [path.name for path in (args.control, args.base_flow)]
    print(
        f"transient: {result['transient_actions']} actions ({result['transient_policy']}), then C_D "
        f"{result['cd_base']:.4f}, no lift, no actuation: reference {result['reference']:.6f} "
        f"({100 * result['reference_reduction_episode']:.2f} % over the episode)"
    )
    for p in result["policies"]:
        print(
            f"  {p['policy']}: {p['score']:.4f}, settled at {p['settled_at']}, "
            f"{100 * p['reduction_episode']:.2f} % over the episode, {100 * p['reduction_regime']:.2f} % after"
        )
    print("written to", save_rows([result], out, f"{result['env'].removesuffix('-v0')}_reference"))


if __name__ == "__main__":
    main()
