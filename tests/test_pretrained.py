"""Shipped policies (``beacon_torch.pretrained``): every one loads and acts in its env's
action spec; the export folds a training's observation normalisation into the network."""

import dataclasses

import pytest
import torch

import beacon_torch
from beacon_torch import pretrained
from beacon_torch.cli import main as cli
from beacon_torch.training import config
from beacon_torch.training.env import make_env
from beacon_torch.training.run import load_checkpoint
from recipes import ppo

from conftest import FAST


@pytest.mark.parametrize("name", pretrained.available())
def test_every_shipped_policy_acts_in_the_action_spec(name):
    algo, env_id = name.split("/")
    policy = pretrained.load(name)
    env = beacon_torch.make(env_id, 2, seed=0, **FAST.get(env_id, {}))
    with torch.no_grad():
        rollout = env.rollout(3, policy)
    assert env.full_action_spec[env.action_key].is_in(rollout[env.action_key][:, 0])
    reward = env.reward_key if isinstance(env.reward_key, tuple) else (env.reward_key,)
    assert torch.isfinite(rollout[("next", *reward)]).all()
    info = pretrained.info(name)
    assert info["env"] == env_id and info["algo"] == algo and info["frames"] > 0


@pytest.fixture
def shipped(tmp_path, monkeypatch):
    """A policy trained here with normalisation statistics, exported into a private
    shipping folder."""
    run = tmp_path / "run"
    ppo.main(
        config.configure(
            config.PPOConfig,
            "vortex-v0",
            frames=400,
            n_rollout=200,
            num_envs=4,
            epochs=2,
            norm_steps=16,
            out=str(run),
            progress=False,
        )
    )
    folder = tmp_path / "shipped"
    folder.mkdir()
    monkeypatch.setattr(pretrained, "HERE", folder)
    pretrained.export(run, pretrained.path_of("ppo/vortex-v0"), seed=0, score=1.0)
    return run


def test_export_folds_the_normalisation_into_the_first_layer(shipped):
    assert pretrained.available() == ["ppo/vortex-v0"]
    state = load_checkpoint(shipped)
    assert not torch.equal(state["obs_norm"]["scale"], torch.ones_like(state["obs_norm"]["scale"]))
    trained = make_env("vortex-v0", 5, seed=3, norm=state["obs_norm"])
    from beacon_torch.training import networks

    actor = networks.policy(trained, "stochastic_actor", 64)
    actor.load_state_dict(state["modules"]["actor"])
    raw = beacon_torch.make("vortex-v0", 5, seed=3).reset()
    folded = pretrained.load("ppo/vortex-v0")
    with torch.no_grad():
        got = folded(raw)["action"]
        # both computed in float64 from the stored float32 values, so that what differs
        # is the folding's own rounding, bounded from the weights and the inputs
        x = raw["observation"].double()
        norm = {k: state["obs_norm"][k].double() for k in ("loc", "scale")}
        unfolded = actor.double()(raw.clone().set("observation", (x - norm["loc"]) / norm["scale"]))["action"]
        weights = {k: v.double() for k, v in folded.module[0].state_dict().items()}
        exact = folded.double()(raw.clone().set("observation", x))["action"]
    w1, b1 = weights["module.0.module.trunk.0.weight"], weights["module.0.module.trunk.0.bias"]
    w2, w3 = weights["module.0.module.mean.0.weight"], weights["module.0.module.mean.2.weight"]
    eps, n = torch.finfo(torch.float32).eps, w1.shape[1]
    # the first layer's folded weight W / scale is rounded once, its bias b - (W / scale) loc
    # carries a float32 dot product of n terms; tanh passes a difference on at most as is
    first = eps * (x.abs() @ w1.abs().T + (n + 2) * (norm["loc"].abs() @ w1.abs().T) + b1.abs())
    bound = first @ w2.abs().T @ w3.abs().T
    assert ((exact - unfolded).abs() <= bound + 1e-12).all(), ((exact - unfolded).abs().max(), bound.min())
    assert pretrained.info("ppo/vortex-v0")["score"] == 1.0
    with torch.no_grad():
        torch.testing.assert_close(pretrained.load("ppo", "vortex-v0")(raw)["action"], got)
    with pytest.raises(ValueError, match="algorithm alone"):
        pretrained.load("ppo/vortex-v0", "vortex-v0")


def test_the_readme_snippet_runs_without_a_warning():
    """A shipped policy is frozen for evaluation: its actions carry no graph that a
    plain env would have to drop (and warn about)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        policy = pretrained.load("ppo/sloshing-v0")
        rollout = beacon_torch.make("sloshing-v0", 2).rollout(5, policy)
    assert rollout.shape == (2, 5) and not any(p.requires_grad for p in policy.parameters())
    policy.requires_grad_(True)  # fine-tuning, as documented
    assert all(p.requires_grad for p in policy.parameters())


def test_eval_runs_a_shipped_policy_and_writes_its_animation(shipped, tmp_path, capsys):
    assert cli(["eval", "--pretrained", "ppo/vortex-v0", "--num-envs", "2", "--out", str(tmp_path)]) == 0
    assert "pretrained ppo" in capsys.readouterr().out and (tmp_path / "ppo" / "vortex-v0.gif").stat().st_size > 1000
    assert cli(["eval", "--pretrained", "td3/vortex-v0", "--no-gif"]) == 2
    assert "no pretrained td3 policy for vortex-v0" in capsys.readouterr().err
    assert cli(["eval"]) == 2
    assert "one of the two" in capsys.readouterr().err


def test_the_benchmark_evaluates_every_shipped_policy_into_the_page(shipped, tmp_path, monkeypatch):
    """experiments/pretrained.py runs each shipped policy as a user loads it and writes
    its table between the page's markers; the folded normalisation scores what the
    training's checkpoint scores on the same episodes."""
    import json

    from beacon_torch.training.evaluation import evaluate_run
    from experiments import pretrained as bench

    page = tmp_path / "results.md"
    page.write_text(f"# Results\n\nby hand\n\n{bench.BEGIN}\nold\n{bench.END}\n\nnotes\n")
    bench.main(["--num-envs", "2", "--page", str(page), "--json", str(tmp_path / "pretrained.json")])
    text = page.read_text()
    assert "old" not in text and "by hand" in text and text.endswith("notes\n")
    assert "| ppo/vortex-v0 | 400 (0) |" in text
    (row,) = json.loads((tmp_path / "pretrained.json").read_text())["rows"]
    assert row["policy"] == "ppo/vortex-v0" and row["recorded"] == 1.0
    checkpoint = evaluate_run(shipped, num_envs=2)
    assert row["uncontrolled"] == checkpoint["uncontrolled"]
    assert abs(row["score"] - checkpoint["score_mean"]) <= 1e-4 * max(1.0, abs(checkpoint["score_mean"]))
    assert row["normalised"] == pytest.approx((row["score"] - row["uncontrolled"]) / (38 - row["uncontrolled"]))
    # and from the test set's developed starts, beside no control from the same states
    held_out = evaluate_run(shipped, num_envs=8, starts="test")
    assert row["test_uncontrolled"] == held_out["uncontrolled"] != row["uncontrolled"]
    assert abs(row["test_score"] - held_out["score_mean"]) <= 1e-4 * max(1.0, abs(held_out["score_mean"]))
    assert "test starts" in text
    # --changed keeps the row of a policy shipped as it was, and evaluates it again once
    # it is shipped anew
    bench.main(["--num-envs", "2", "--page", str(page), "--json", str(tmp_path / "pretrained.json"), "--changed"])
    assert json.loads((tmp_path / "pretrained.json").read_text())["rows"] == [row]
    # --test-again evaluates a kept policy from the test starts again, its own-start row kept
    numbers = json.loads((tmp_path / "pretrained.json").read_text())
    numbers["rows"][0]["test_score"] = 1e9
    (tmp_path / "pretrained.json").write_text(json.dumps(numbers))
    changed = ["--num-envs", "2", "--page", str(page), "--json", str(tmp_path / "pretrained.json"), "--changed"]
    bench.main([*changed, "--test-again", "td3/"])
    assert json.loads((tmp_path / "pretrained.json").read_text())["rows"][0]["test_score"] == 1e9
    bench.main([*changed, "--test-again", "vortex"])
    assert json.loads((tmp_path / "pretrained.json").read_text())["rows"] == [row]
    pretrained.export(shipped, pretrained.path_of("ppo/vortex-v0"), seed=0, score=2.0)
    bench.main(["--num-envs", "2", "--page", str(page), "--json", str(tmp_path / "pretrained.json"), "--changed"])
    (again,) = json.loads((tmp_path / "pretrained.json").read_text())["rows"]
    assert again["recorded"] == 2.0 and again["seconds"] != row["seconds"] and "| 2 |" in page.read_text()
    # an env whose card has no paper score: its scores stand, not normalised
    spec = beacon_torch.registry.ENVS["vortex-v0"]  # a card without the paper's score
    monkeypatch.setitem(
        beacon_torch.registry.ENVS,
        "vortex-v0",
        dataclasses.replace(spec, card=dataclasses.replace(spec.card, paper_ppo=None)),
    )
    bench.main(["--num-envs", "2", "--page", str(page), "--json", str(tmp_path / "pretrained.json"), "--changed"])
    (bare,) = json.loads((tmp_path / "pretrained.json").read_text())["rows"]
    assert bare["normalised"] is bare["test_normalised"] is None and bare["score"] == again["score"]
    assert "| - (b) | 2 |" in page.read_text()
    with pytest.raises(SystemExit):
        bench.main(["--num-envs", "0", "--page", str(page)])


def test_the_trace_splits_a_shipped_policys_episode_into_its_stretches(shipped, tmp_path, capsys):
    """experiments/policy_trace.py plays a shipped policy from the env's own start: its
    stretches of actions cover the episode and sum to what the evaluation scores."""
    import json

    from beacon_torch.training.evaluation import evaluate_run
    from experiments import policy_trace

    written = policy_trace.main(["--env", "vortex-v0", "--algos", "ppo", "--stretch", "300", "--out", str(tmp_path)])
    *stretches, totals = json.loads(written.read_text())["rows"]
    assert [(row["first_action"], row["actions"]) for row in stretches] == [(0, 300), (300, 300), (600, 200)]
    assert sum(row["ppo_reward"] for row in stretches) == pytest.approx(totals["totals"]["ppo"], rel=1e-9)
    assert totals["totals"]["ppo"] == pytest.approx(evaluate_run(shipped, num_envs=1)["score_mean"], rel=1e-4)
    assert all(row["ppo_action_size"] >= 0 for row in stretches)
    assert "| 600 to 799 |" in capsys.readouterr().out


def test_a_generated_part_without_its_end_marker_is_refused(tmp_path):
    from beacon_torch.training.report import write_block

    page = tmp_path / "page.md"
    page.write_text("# Page\n\n<!-- begin -->\nold\n")
    with pytest.raises(ValueError, match="no end marker"):
        write_block(page, "<!-- begin -->", "<!-- end -->", "new")
    page.write_text("# Page\n")
    assert (
        write_block(page, "<!-- begin -->", "<!-- end -->", "new").read_text()
        == "# Page\n\n<!-- begin -->\nnew\n<!-- end -->\n"
    )
