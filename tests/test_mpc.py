"""Gradient model-predictive control (``recipes/mpc.py``): its predictions are the env's
own episodes, its iterations improve them, and planned episodes are judged by the
recipes' evaluation protocol."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from beacon_torch.training import evaluation
from beacon_torch.training.env import make_env
from recipes import mpc

# lorenz's reward counts x < 0, whose gradient is zero: the planner's model has the
# smooth stand-in
SMOOTH = ["--plan-param", "reward_width=1"]


def test_a_plan_predicts_the_envs_own_rewards_and_its_iterations_improve_it():
    """float64, two lorenz members with the smooth reward (deterministic): the predicted
    return of a plan is the sum of the rewards the env gives for those actions from its
    current state, a graph back to the plan, and predicting leaves the env where it
    was; five iterations from zero actions give a plan predicted to do better."""
    args = mpc.parse(["--env", "lorenz-continuous-v0", "--param", "reward_width=1", "--horizon", "6"])
    env = make_env(args.env, 2, norm_steps=0, params=args.params, dtype="float64", compile=False)
    base = env.base_env
    env.reset()
    for _ in range(5):
        env.rand_step()
    state = {k: v.clone() for k, v in base.state._asdict().items()}
    generator = torch.Generator().manual_seed(0)
    plan = (2 * torch.rand(6, 2, 1, dtype=torch.float64, generator=generator) - 1).requires_grad_()
    predicted = mpc.predicted_return(base, base, plan, args, torch.Generator())
    (gradient,) = torch.autograd.grad(predicted.sum(), plan)
    assert torch.isfinite(gradient).all() and gradient.abs().sum() > 0
    for k, v in base.state._asdict().items():
        assert torch.equal(v, state[k]), f"predicting moved the env's {k}"

    stats = {"actions": 0, "cpu_s": 0.0, "dropped": 0}
    args = dataclasses.replace(args, iterations=5)
    zero = torch.zeros_like(plan.detach())
    improved = mpc.improve(base, base, zero, args, torch.Generator(), stats)
    assert stats["dropped"] == 0 and (improved.abs() <= 1).all()
    before, after = (mpc.predicted_return(base, base, p, args, torch.Generator()).detach() for p in (zero, improved))
    assert (after > before).all(), (before, after)

    rewards = torch.stack([env.step(base.current().set("action", a))["next", "reward"][..., 0] for a in plan.detach()])
    torch.testing.assert_close(predicted.detach(), rewards.sum(0), rtol=1e-12, atol=1e-12)


def test_planned_episodes_beat_no_control_and_are_recorded_once(tmp_path, capsys):
    """Two lorenz episodes from the test set's starts, planned 8 actions ahead with 3
    iterations each (the default 20 and 10 reach further): more time with x < 0 than no
    control from the same starts, the record written once and then refused. The
    record gives the env's diagnostics averaged over the episodes, the uncontrolled
    ones those of the evaluation's own rollout."""
    out = tmp_path / "lorenz"
    argv = ["--env", "lorenz-continuous-v0", *SMOOTH, "--horizon", "8", "--iterations", "3"]
    argv += ["--num-envs", "2", "--threads", "1", "--no-progress", "--out", str(out)]
    record = mpc.main(mpc.parse(argv))
    assert record["score_mean"] > record["uncontrolled"] and record["normalised"] > 0, record
    assert record["planned_actions"] == 500 and record["dropped_iterations"] == 0
    assert json.loads((out / "mpc.json").read_text())["normalised"] == record["normalised"]
    free, _ = evaluation.uncontrolled_episodes("lorenz-continuous-v0", 2, starts="test")
    assert set(record["diagnostics"]) == {"x", "y", "z"}
    for name, means in record["diagnostics"].items():
        expected = np.nanmean(evaluation._per_action(free, name), -1).mean()
        assert means["uncontrolled"] == pytest.approx(expected, rel=1e-12), name
        assert np.isfinite(means["planned"]) and means["planned"] != means["uncontrolled"], name
        assert means["relative_change"] == pytest.approx(means["planned"] / means["uncontrolled"] - 1.0), name
    with pytest.raises(SystemExit):
        mpc.parse(argv)
    assert "mpc.json exists and is not overwritten" in capsys.readouterr().err


def test_planned_episodes_stopped_and_resumed_are_those_of_one_run(tmp_path, monkeypatch, capsys):
    """Two lorenz episodes planned 3 actions ahead, stopped at the 100th action and
    resumed from the checkpoint of the 80th: the record is the one of a run without the
    stop, and the checkpoint is gone with it. A checkpoint under way is not started
    over without --resume, nor resumed with other settings or once altered."""
    argv = ["--env", "lorenz-continuous-v0", *SMOOTH, "--horizon", "3", "--iterations", "2", "--num-envs", "2"]
    argv += ["--threads", "1", "--no-progress", "--checkpoint-every", "40"]
    whole = mpc.main(mpc.parse([*argv, "--out", str(tmp_path / "whole")]))

    out = tmp_path / "stopped"
    improve, calls = mpc.improve, []

    def stopping(*args):
        calls.append(1)
        if len(calls) == 100:
            raise KeyboardInterrupt
        return improve(*args)

    monkeypatch.setattr(mpc, "improve", stopping)
    with pytest.raises(KeyboardInterrupt):
        mpc.main(mpc.parse([*argv, "--out", str(out)]))
    monkeypatch.setattr(mpc, "improve", improve)
    checkpoint = out / mpc.CHECKPOINT
    assert checkpoint.is_file() and not (out / "mpc.json").exists()

    with pytest.raises(FileExistsError, match="holds planned episodes under way: give --resume"):
        mpc.main(mpc.parse([*argv, "--out", str(out)]))
    with pytest.raises(ValueError, match="setting 'iterations' = 3 differs from the planned episodes' 2"):
        mpc.main(mpc.parse([*argv, "--iterations", "3", "--out", str(out), "--resume"]))
    kept = checkpoint.read_bytes()
    saved = torch.load(checkpoint, weights_only=True)
    saved["plan"] = saved["plan"][:2]
    torch.save(saved, checkpoint)
    with pytest.raises(ValueError, match=r"not a checkpoint of these planned episodes \(plan must be"):
        mpc.main(mpc.parse([*argv, "--out", str(out), "--resume"]))
    checkpoint.write_bytes(kept)

    resumed = mpc.main(mpc.parse([*argv, "--out", str(out), "--resume"]))
    assert "resuming" in capsys.readouterr().out and not checkpoint.exists()
    for key in (
        "score_mean",
        "score_std",
        "uncontrolled",
        "normalised",
        "planned_actions",
        "dropped_iterations",
        "diagnostics",
    ):
        assert resumed[key] == whole[key], key
    assert resumed["planned_actions"] == 500


def test_the_cost_of_planned_actions_is_recorded_without_an_episode(tmp_path):
    argv = ["--env", "burgers-v0", "--actions", "2", "--horizon", "2", "--iterations", "1", "--out", str(tmp_path)]
    record = mpc.main(mpc.parse(argv))
    assert record["planned_actions"] == 2 and record["cpu_s_per_action"] > 0 and "normalised" not in record
    # the first action (which compiles, where compiled) is counted apart
    assert record["first_action_cpu_s"] > 0


def test_a_planned_actions_cost_leaves_out_each_processs_first_action():
    planner = mpc.Planner.__new__(mpc.Planner)
    planner.stats = {"actions": 3, "cpu_s": 12.0, "dropped": 0, "first_actions": 1, "first_cpu_s": 10.0}
    assert planner.cost() == {"cpu_s_per_action": 1.0, "first_action_cpu_s": 10.0}
    # resumed once: two processes, two first actions
    planner.stats = {"actions": 4, "cpu_s": 22.0, "dropped": 0, "first_actions": 2, "first_cpu_s": 20.0}
    assert planner.cost() == {"cpu_s_per_action": 1.0, "first_action_cpu_s": 10.0}
    # a single action: nothing else to count
    planner.stats = {"actions": 1, "cpu_s": 10.0, "dropped": 0, "first_actions": 1, "first_cpu_s": 10.0}
    assert planner.cost()["cpu_s_per_action"] == 10.0


def test_the_planner_refuses_discrete_actions_and_empty_horizons(capsys):
    with pytest.raises(SystemExit):
        mpc.parse(["--env", "lorenz-v0"])
    assert "lorenz-v0 has discrete ones (use lorenz-continuous-v0)" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        mpc.parse(["--env", "burgers-v0", "--horizon", "0"])
    assert "setting 'horizon' must be a positive integer" in capsys.readouterr().err


def test_a_member_that_blows_up_in_a_plan_leaves_the_others_plans_finite():
    """float64 lorenz, the second member's state scaled out of any range: its
    predicted return stops at the blow-up, every gradient is finite and the first
    member's is what it is alone."""
    args = mpc.parse(["--env", "lorenz-continuous-v0", "--param", "reward_width=1", "--horizon", "4"])
    grads = []
    for members in (2, 1):
        env = make_env(args.env, members, norm_steps=0, params=args.params, dtype="float64", compile=False)
        base = env.base_env
        env.reset()
        if members == 2:
            state = base.state._asdict()
            base.set_state({k: torch.cat([v[:1], v[1:] * 1e30]) for k, v in state.items()})
        plan = torch.full((4, members, 1), 0.3, dtype=torch.float64, requires_grad=True)
        predicted = mpc.predicted_return(base, base, plan, args, None)
        grads.append(torch.autograd.grad(predicted.sum(), plan)[0])
        if members == 2:
            assert torch.isfinite(predicted).all() and torch.isfinite(grads[0]).all()
            assert (grads[0][:, 1] == 0).all(), "the member that blew up still steers its plan"
    torch.testing.assert_close(grads[0][:, :1], grads[1], rtol=1e-12, atol=0.0)


def test_the_gradients_page_shows_a_recorded_plan_of_every_continuous_env():
    """Every single-agent env with continuous actions has a record of the planner (an
    evaluation, or the cost of planned actions where an episode takes more than an
    hour), and the page's table is the one its script writes from them."""
    from beacon_torch.registry import continuous_envs, env_spec
    from experiments import mpc_table as table

    rows = table.records()
    assert {r["env"] for r in rows} == set(continuous_envs())
    # evaluated: scored over whole episodes (normalised where the env has a reference score)
    evaluated = {r["env"] for r in rows if "score_mean" in r}
    assert {"lorenz-continuous-v0", "burgers-v0", "vortex-v0", "sloshing-v0", "ks-v0", "rayleigh-v0"} <= evaluated
    # the cylinder at FluidGym's 20 x 10 from the test starts: its drag below no control's
    (cylinder,) = [r for r in rows if r["env"] == "cylinder-v0"]
    assert (cylinder["settings"]["horizon"], cylinder["settings"]["iterations"]) == (20, 10)
    assert cylinder["planned_actions"] == env_spec("cylinder-v0").physics.episode_length
    assert cylinder["dropped_iterations"] == 0 and cylinder["diagnostics"]["drag"]["relative_change"] < -0.05
    assert all("normalised" in r for r in rows if "score_mean" in r and env_spec(r["env"]).card.paper_ppo is not None)
    # an env whose reference came after its record (ks-v0's physical limit) is scored by it
    (ks,) = [line for line in table.table(rows).splitlines() if line.startswith("| ks-v0 |")]
    assert "| **0.21** |" in ks and "(b)" not in ks
    # an env left unplanned is one whose episode at FluidGym's 20 x 10 takes over an hour
    for r in rows:
        if r["env"] not in evaluated:
            s = r["settings"]
            per_action = r["cpu_s_per_action"] * 200 / (s["horizon"] * s["iterations"])
            assert per_action * env_spec(r["env"]).physics.episode_length > 3600, r["env"]
    page = (Path(__file__).resolve().parents[1] / "docs" / "gradients.md").read_text()
    assert table.table(rows) in page
