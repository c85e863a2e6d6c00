"""pinball-v0: the rotating cylinders' forcing, loads and power, the steady flow at
Re 30 against the recorded validation, the page's tables."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import torch

import beacon_torch
from beacon_torch.envs import pinball
from beacon_torch.registry import env_spec
from validation import pinball as steady

from conftest import random_policy_file

ROOT = Path(__file__).resolve().parents[1]

F64 = dict(dtype=torch.float64, device="cpu")


# the validations' records and the trained policies' evaluations, each in its own room
FOLDERS = [ROOT / room / "results" / "pinball" for room in ("validation", "experiments")]


def recorded(name: str) -> Path:
    (path,) = [folder / name for folder in FOLDERS if (folder / name).is_file()]
    return path


def latest(pattern: str) -> dict:
    (path,) = sorted((p for folder in FOLDERS for p in folder.glob(pattern)), key=lambda p: p.name)[-1:]
    return json.loads(path.read_text())


def test_forcing_gives_a_turning_cylinder_its_rigid_rotation():
    # a field that turns rigidly about the front cylinder's centre is what the forcing
    # must leave on that cylinder's forced faces at a unit angular velocity: the wall's
    # velocity is the field's there, and the quadratic along the normal is exact for it
    box = pinball.Box(20, **F64)
    front = pinball.CYLINDERS[0]
    omega = torch.tensor([[1.0], [0.0], [0.0]], **F64)
    for body, xs, ys, component in (
        (box.body_u, box.x.faces, box.y.centres, 0),
        (box.body_v, box.x.centres, box.y.faces, 1),
    ):
        x, y = xs[:, None], ys[None, :]
        field = (-(y - front.y) if component == 0 else (x - front.x)).expand(len(xs), len(ys))[..., None].clone()
        forced = body(field.to(torch.float64), omega).reshape(-1)
        mine = body.forced[body.groups[0] == 1]
        assert len(mine) > 50
        torch.testing.assert_close(forced[mine], field.reshape(-1)[mine], rtol=0, atol=1e-12)
        # the other cylinders stand still: their inner faces at rest
        others = body.forced[body.groups[0] == 0]
        inner = body.inside.reshape(-1, 3)[others].abs().sum(-1) > 0
        assert forced[others][inner].abs().max() == 0


def test_turning_cylinders_spend_power_and_feel_the_torque_against_them():
    env = beacon_torch.make("pinball-v0", 2, dtype=torch.float64, **pinball.CARD.test_settings)
    td = env.reset()
    action = torch.tensor([[1.0, 0.0, 0.0], [0.0, -1.0, 1.0]], dtype=torch.float64)
    td = env.step(td.set("action", action))["next"]
    state = env.state
    # the front cylinder turns counter-clockwise in the first member: the fluid's torque
    # on it is clockwise; the rear pair turns outwards in the second
    assert state.omega[0, 0] > 0 and state.torque[0, 0] < 0
    assert state.omega[1, 1] < 0 and state.torque[1, 1] > 0
    power = td["diagnostics", "power"]
    assert bool((power > 0).all())
    # the rates the diagnostics report are the state's, ramped towards the commanded bound
    for k, name in enumerate(("front", "top", "bottom")):
        assert torch.equal(td["diagnostics", f"omega_{name}"], state.omega[:, k])
    assert 0 < state.omega[0, 0] <= float(env.params.max_rotation)
    drag = td["diagnostics", "drag"]
    assert torch.allclose(td["reward"][:, 0], -(drag + power))


@pytest.mark.slow(seconds=15)
def test_the_steady_flow_at_re_30_is_the_recorded_one():
    # HydroGym's set-up at the tests' grid from the free stream, as the validation ran
    # it: its first 10 time units
    record = latest("pinball_steady-*.json")
    (row,) = [r for r in record["rows"] if r["setup"] == "hydrogym-mesh" and r["cells_per_diameter"] == 10]
    got, want = steady.measure("hydrogym-mesh", 10, 10.0), row["history"][9]
    assert got["time"] == want["time"] == 10.0
    torch.testing.assert_close(torch.tensor(got["drag"]), torch.tensor(want["drag"]), rtol=1e-9, atol=0)
    torch.testing.assert_close(torch.tensor(got["lift"]), torch.tensor(want["lift"]), rtol=0, atol=1e-9)
    # the steady flow on the mirror-symmetric grid is mirror-symmetric
    assert abs(got["lift"][0]) < 1e-9 and got["lift"][1] == pytest.approx(-got["lift"][2], abs=1e-9)


def test_the_recorded_steady_forces_are_within_2_percent_of_hydrogyms_and_on_the_page():
    record = latest("pinball_steady-*.json")
    rows = [r for r in record["rows"] if r["setup"] == "hydrogym-mesh"]
    finest = max(rows, key=lambda r: r["cells_per_diameter"])
    for got, want in zip(finest["drag"], steady.HYDROGYM["drag"], strict=True):
        assert got == pytest.approx(want, rel=0.02)
    for got, want in zip(finest["lift"][1:], steady.HYDROGYM["lift"][1:], strict=True):
        assert got == pytest.approx(want, rel=0.02)
    assert all(r["last_change"] < 1e-5 for r in record["rows"])  # converged
    page = (ROOT / "docs" / "envs" / "pinball.md").read_text()
    block = re.search(r"<!-- steady: .*?-->\n(.*?)<!-- end of the steady -->", page, re.S)
    assert block and block.group(1).strip() == steady.table(record["rows"]).strip()


def test_bad_parameters_get_one_line():
    with pytest.raises(ValueError, match="'cells_per_diameter' = 15 must be even"):
        beacon_torch.make("pinball-v0", 1, cells_per_diameter=15)
    with pytest.raises(ValueError, match="'re' = 25 and 'cells_per_diameter' = 30: the explicit diffusion is unstable"):
        beacon_torch.make("pinball-v0", 1, re=25, cells_per_diameter=30)


def test_the_recorded_hopf_threshold_is_within_5_percent_of_deng_et_al_and_on_the_page():
    record = latest("pinball_thresholds-*.json")
    sweeps = [r for r in record["rows"] if r["kind"] == "hopf"]
    finest = max(sweeps, key=lambda r: r["cells_per_diameter"])
    assert steady.threshold(finest["points"]) == pytest.approx(steady.DENG["hopf"], rel=0.05)
    page = (ROOT / "docs" / "envs" / "pinball.md").read_text()
    block = re.search(r"<!-- thresholds: .*?-->\n(.*?)<!-- end of the thresholds -->", page, re.S)
    assert block and block.group(1).strip() == steady.threshold_table(record["rows"]).strip()


def test_a_growth_rate_is_read_off_a_clean_mode():
    # the fit of the validation recovers a known damped oscillation and a real growth
    import numpy as np

    t = np.arange(0, 80, steady.SAMPLE)
    oscillating = 1e-6 * np.exp(0.031 * t) * np.cos(0.62 * t + 0.3) + 1e-9 * np.exp(-0.5 * t)
    rate = steady.growth(oscillating, 2, skip=20.0)
    assert rate.real == pytest.approx(0.031, abs=1e-6) and abs(rate.imag) == pytest.approx(0.62, abs=1e-6)
    drifting = 1e-6 * np.exp(-0.012 * t)
    assert steady.growth(drifting, 1, skip=20.0).real == pytest.approx(-0.012, abs=1e-9)


def test_the_chaotic_level_is_chaotic_and_the_periodic_one_is_not():
    # the recorded regimes: a positive leading Lyapunov exponent at Re 130 on every
    # grid run, clear of its error; at Re 30 and 100 none that is
    record = latest("pinball_regimes-*.json")
    rows = {(r["re"], r["cells_per_diameter"]): r for r in record["rows"]}
    for (re_, _cells), r in rows.items():
        if re_ == 130.0:
            assert r["lyapunov"] > 3 * r["lyapunov_error"] > 0
        if re_ < 120.0:  # Re 30 and 100: periodic
            assert r["lyapunov"] < 3 * r["lyapunov_error"]
    page = (ROOT / "docs" / "envs" / "pinball.md").read_text()
    block = re.search(r"<!-- regimes: .*?-->\n(.*?)<!-- end of the regimes -->", page, re.S)
    assert block and block.group(1).strip() == steady.regime_table(record["rows"]).strip()


def test_the_asymmetry_is_averaged_over_whole_periods_and_its_threshold_read_off_the_normal_form():
    # a lift oscillating about a mean: the mean over whole periods is the mean, to the
    # samples' resolution, where a window of 10.3 periods would be off by the part period
    import numpy as np

    t = np.arange(0.0, 200.0, steady.PITCHFORK_SAMPLE)
    front = np.sin(2 * np.pi * t / 9.7)
    total = 0.04 + 0.8 * np.sin(2 * np.pi * t / 9.7 + 0.4)
    mean, period = steady.whole_periods(front, total, window=400)
    assert mean == pytest.approx(0.04, abs=2e-3) and period * steady.PITCHFORK_SAMPLE == pytest.approx(9.7, rel=0.02)
    # settled asymmetries A = sqrt(a (Re - Rc)) above the threshold, zero below: the
    # threshold is the line's zero; drifting points and those near zero are left out
    points = [
        {"re": re, "asymmetry": float(np.sqrt(max(0.0, 2e-4 * (re - 67.0)))), "drift": 0.0} for re in range(60, 90, 4)
    ]
    points[-1]["drift"] = 0.5 * points[-1]["asymmetry"]  # not settled: a wrong value does not count
    points[-1]["asymmetry"] *= 3
    assert steady.pitchfork_threshold(points) == pytest.approx(67.0, abs=1e-9)


def test_the_recorded_pitchfork_threshold_is_within_5_percent_of_deng_et_al_and_on_the_page():
    # the developed flows: symmetric on average below the threshold, asymmetric past it
    record = latest("pinball_pitchfork-*.json")
    finest = max(record["rows"], key=lambda r: r["cells_per_diameter"])
    found = steady.pitchfork_threshold(finest["points"])
    assert found == pytest.approx(steady.DENG["pitchfork"], rel=0.05)
    for p in finest["points"]:
        if p["re"] < found - 4:
            assert abs(p["asymmetry"]) < 1e-3
        if p["re"] > found + 8:
            assert abs(p["asymmetry"]) > 0.02 and steady.settled(p)
    page = (ROOT / "docs" / "envs" / "pinball.md").read_text()
    block = re.search(r"<!-- pitchfork: .*?-->\n(.*?)<!-- end of the pitchfork -->", page, re.S)
    assert block and block.group(1).strip() == steady.pitchfork_table(record["rows"]).strip()


def test_each_levels_reference_is_a_steady_symmetric_flow_below_the_uncontrolled_drag():
    record = latest("pinball_base-*.json")
    for row in record["rows"]:
        for level in row["levels"]:
            top, bottom = level["drag_base"][1:]
            assert top == pytest.approx(bottom, rel=1e-9) and abs(level["lift_base"][0]) < 1e-9
            assert abs(level["drag_drift"]) < 1e-4  # the drag has settled
            if level["re"] < 120:  # the periodic flows' base flows are steady to round-off
                assert level["unit_change"] < 1e-9
            assert level["history"][-1]["unit_change"] <= level["history"][100]["unit_change"]  # decays, never grows
            assert 0.01 < level["reduction"] < 0.1
    page = (ROOT / "docs" / "envs" / "pinball.md").read_text()
    block = re.search(r"<!-- base flows: .*?-->\n(.*?)<!-- end of the base flows -->", page, re.S)
    assert block and block.group(1).strip() == steady.base_table(record["rows"]).strip()


@pytest.mark.slow(seconds=20)
def test_the_wake_control_benchmark_runs_a_pinball_policy_beside_no_control(tmp_path, monkeypatch):
    """experiments/wake_control.py on a pinball policy: the env and grid come from the
    policy file, the turning member spends power and pays it in its reward, the member
    beside it spends none, and a non-wake env is refused in one line."""
    import numpy as np

    monkeypatch.setattr(pinball.PinballPhysics, "episode_length", 6)  # short episodes: the test's time

    from experiments import wake_control as control

    params = {"cells_per_diameter": 10}
    policy = random_policy_file(tmp_path / "policy.pt", "pinball-v0", params, hidden=8)
    row = control.control(str(policy), 2, compile=False)
    seen = {key: np.array(values) for key, values in row["per_action"].items()}
    assert row["env"] == "pinball-v0" and row["params"] == params and len(seen["drag"]) == 12
    assert (seen["uncontrolled_power"] == 0).all() and seen["power"].mean() > 0.01
    # the rotation rates are recorded, within the bound, none for the member left alone
    rates = np.stack([seen[f"omega_{name}"] for name in ("front", "top", "bottom")])
    assert (np.abs(rates) <= float(pinball.PinballParams().max_rotation)).all() and np.abs(rates).max() > 0.1
    assert all((seen[f"uncontrolled_omega_{name}"] == 0).all() for name in ("front", "top", "bottom"))
    # the actuation's table: the power and net drag power over the first episode, the
    # rates over the second half as fractions of the bound
    line = control.rotation_table([row]).splitlines()[2]
    net = (seen["drag"][:6] + seen["power"][:6]).mean() / seen["uncontrolled_drag"][:6].mean() - 1
    rates = (rates[:, 6:].mean(1) / float(pinball.PinballParams().max_rotation)).tolist()
    assert line.startswith(f"| {policy} | {seen['power'][:6].mean():.2f} | {100 * net:+.1f} % |")
    assert ", ".join(f"{x:+.2f}" for x in rates) in line
    # and how much the drag still fluctuates there, beside no control
    assert line.endswith(f"| {seen['drag'][6:].std():.4f}, {seen['uncontrolled_drag'][6:].std():.4f} |")
    np.testing.assert_allclose(seen["reward"], -(seen["drag"] + seen["power"]), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(seen["uncontrolled_reward"], -seen["uncontrolled_drag"], rtol=1e-6)
    assert row["score_episode"] == pytest.approx(seen["reward"][:6].sum(), rel=1e-9)
    assert control.wake("pinball-chaotic-v0") == ("power", 0.5)
    with pytest.raises(ValueError, match="burgers-v0 is not a wake-control env"):
        control.wake("burgers-v0")


def test_a_control_record_carries_an_earlier_records_rows_ahead_of_the_new_ones(tmp_path, monkeypatch, capsys):
    """experiments/wake_control.py --carry: an earlier record's rows (policies whose run
    folders are on another machine) go ahead of the new policies' in the new record,
    naming the record and machine they were measured on; a record of another env or run
    length, a policy carried already or rows that are not a record's are one line,
    before any policy runs."""
    from experiments import wake_control as control

    n = 4
    keys = ("drag", "power", "lift", "reward", "omega_front", "omega_top", "omega_bottom")

    def row(name, env="pinball-periodic-v0", actions=3 * n, value=1.0):
        per_action = {key: [value] * actions for key in keys} | {f"uncontrolled_{k}": [2.0] * actions for k in keys}
        numbers = dict.fromkeys(control.ROW_NUMBERS, 1.0)
        return (
            {"policy": name, "env": env, "params": {}, "actions": actions, "episode_length": n}
            | numbers
            | {"per_action": per_action}
        )

    earlier = tmp_path / "earlier.json"
    earlier.write_text(json.dumps({"machine": "elsewhere", "rows": [row("ppo/a"), row("grad/b")]}))
    ran = []
    monkeypatch.setattr(control, "policy_of", lambda name: (None, "pinball-periodic-v0", {}))
    monkeypatch.setattr(control, "control", lambda name, episodes, compile, loaded: ran.append(name) or row(name))
    out = tmp_path / "out"
    monkeypatch.setattr("sys.argv", ["wake_control.py", "shac/c", "--carry", str(earlier), "--out", str(out)])
    control.main()
    (record,) = out.glob("pinball-periodic_control-*.json")
    rows = json.loads(record.read_text())["rows"]
    assert [r["policy"] for r in rows] == ["ppo/a", "grad/b", "shac/c"] and ran == ["shac/c"]
    assert (rows[0]["record"], rows[0]["machine"]) == ("earlier.json", "elsewhere") and "record" not in rows[2]
    capsys.readouterr()
    for rows, message in (
        ([row("ppo/a", env="burgers-v0")], "burgers-v0 is not a wake-control env"),
        ([row("ppo/a", env="pinball-v0")], "the policies are of different envs"),
        ([row("ppo/a", actions=2 * n)], "row 0: 8 actions, not 3 episodes' worth"),
        ([row("shac/c")], "shac/c: in the carried record already"),
        ([row("ppo/a", value=float("nan"))], "row 0: its per-action values are not 12 finite numbers each"),
        ([], "not a record of experiments/wake_control.py"),
    ):
        earlier.write_text(json.dumps({"rows": rows}))
        with pytest.raises(SystemExit):
            control.main()
        assert message in capsys.readouterr().err
    assert ran == ["shac/c"] and len(list(out.iterdir())) == 1


def test_a_pinball_levels_reference_holds_its_recorded_base_flow_after_the_measured_transient():
    """validation/wake_reference.py on the pinball: the held reward is minus the level's
    recorded base-flow drag (summed, on the policies' grid, no power), the transient
    ends where the best policy's drag stays within a tenth of the excess; a level the
    record lacks is one line."""
    import numpy as np

    from validation import wake_reference as reference

    base = latest("pinball_base-*.json")
    (level,) = [lv for row in base["rows"] if row["cells_per_diameter"] == 20 for lv in row["levels"] if lv["re"] == 30]
    cd_base, n = sum(level["drag_base"]), pinball.EPISODE_LENGTH
    free = np.full(n, cd_base + 0.2)
    # one policy reaches the base flow's drag after 10 actions of 0.1 power, one never
    fast = np.where(np.arange(n) < 10, cd_base + 0.15, cd_base + 0.001)
    slow = np.full(n, cd_base + 0.1)

    def row(name, drag, power):
        per_action = {"drag": drag.tolist(), "uncontrolled_drag": free.tolist(), "reward": (-(drag + power)).tolist()}
        return {"policy": name, "env": "pinball-v0", "params": {}, "episode_length": n, "per_action": per_action}

    control = {"rows": [row("fast", fast, np.where(np.arange(n) < 10, 0.1, 0.0)), row("slow", slow, 0.0 * slow)]}
    got = reference.reference(control, base)
    assert got["env"] == "pinball-v0" and got["cd_base"] == pytest.approx(cd_base, rel=1e-12)
    assert got["held_reward_per_action"] == -got["cd_base"] and got["transient_actions"] == 10
    expected = -10 * (cd_base + 0.25) - (n - 10) * cd_base
    assert got["transient_policy"] == "fast" and got["reference"] == pytest.approx(expected, rel=1e-12)
    assert got["reference"] > max(p["score"] for p in got["policies"])
    control["rows"][0]["params"] = {"re": 31.0}
    with pytest.raises(ValueError, match="no flow at Re 31 on 20 cells"):
        reference.reference(control, base)


@pytest.mark.parametrize(
    "record, block", [("pinball", ""), ("pinball-periodic", "periodic "), ("pinball-chaotic", "chaotic ")]
)
def test_the_recorded_policies_boat_tail_past_the_base_flows_reference_as_the_page_says(record, block):
    """The page's control tables of a level are the newest wake_control record's, and
    its reference record is what validation/wake_reference.py computes again from the
    records it names: the policies' net drag power is below no control's and their
    scores above the base flow's reference, which is no "= 1" at Re 30, 100 or 130."""
    import numpy as np

    from experiments import wake_control as control
    from validation import wake_reference as reference

    rows = latest(f"{record}_control-*.json")["rows"]
    page = (ROOT / "docs" / "envs" / "pinball.md").read_text()
    for name, make in (("control", control.table), ("rotations", control.rotation_table)):
        found = re.search(rf"<!-- {block}{name}: .*?-->\n(.*?)<!-- end of the {block}{name} -->", page, re.S)
        assert found and found.group(1).strip() == make(rows).strip(), name
    record = latest(f"{record}_reference-*.json")["rows"][0]
    again = reference.reference(*(json.loads(recorded(name).read_text()) for name in record["records"]))
    assert again == {k: v for k, v in record.items() if k != "records"}
    assert f"{record['reference']:.1f}" in page
    for row, policy in zip(rows, record["policies"], strict=True):
        seen = {key: np.array(values[:100]) for key, values in row["per_action"].items()}
        # boat-tailing: the rear pair turning with their outer sides downstream
        assert seen["omega_top"][50:].mean() < 0 < seen["omega_bottom"][50:].mean()
        assert (seen["drag"] + seen["power"]).mean() < seen["uncontrolled_drag"].mean()
        assert row["score_episode"] > record["reference"] and policy["score"] == pytest.approx(row["score_episode"])
    assert env_spec(row["env"]).card.paper_ppo is None
