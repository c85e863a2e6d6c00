"""The PPO recipe and ``beacon-torch train``: short runs on small batches."""

import pytest
import torch

from beacon_torch.cli import main
from beacon_torch.recipes.config import PPO, ppo_config
from beacon_torch.recipes.common import make_env
from beacon_torch.recipes.ppo import make_actor, train


def test_config_holds_the_papers_table_and_checks_overrides():
    assert ppo_config("rayleigh-v0").entropy == 0.001 and ppo_config("rayleigh-v0").n_rollout == 1000
    assert ppo_config("sloshing-v0").epochs == 16 and ppo_config("sloshing-v0").critic_lr == 1e-3
    assert ppo_config("mixing-continuous-v0") == PPO["mixing-v0"]
    assert ppo_config("lorenz-v0", epochs=4).epochs == 4
    with pytest.raises(ValueError, match="unknown PPO setting"):
        ppo_config("lorenz-v0", epoch=4)
    with pytest.raises(ValueError, match="frames"):
        ppo_config("lorenz-v0", frames=-5)


@pytest.mark.parametrize("env_id", ["lorenz-v0", "vortex-v0"])  # discrete and continuous
def test_ppo_runs_updates_its_networks_and_resumes(env_id, tmp_path):
    cfg = ppo_config(env_id, frames=400, n_rollout=200, num_envs=4, epochs=2)
    torch.manual_seed(0)
    before = make_actor(make_env(env_id, cfg.num_envs), cfg.hidden).state_dict()
    last = train(env_id, cfg, tmp_path, progress=False)
    assert last["frames"] == 400 and torch.isfinite(torch.tensor(last["loss"]))
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    assert state["frames"] == 400 and state["env"] == env_id
    assert any(not torch.equal(before[k], state["actor"][k]) for k in before), "PPO did not change the actor"
    assert list((tmp_path / "ppo").rglob("*.csv")), "no CSV log"
    # resuming continues from the checkpoint to the new total
    more = ppo_config(env_id, frames=600, n_rollout=200, num_envs=4, epochs=2)
    assert train(env_id, more, tmp_path, progress=False, resume=True)["frames"] == 600


def test_train_command_and_its_errors(tmp_path, capsys):
    out = tmp_path / "run"
    rc = main(["train", "lorenz-v0", "--frames", "200", "--num-envs", "4", "--set", "n_rollout=200", "--set", "epochs=1", "--out", str(out), "--no-progress"])
    assert rc == 0 and (out / "seed0" / "checkpoint.pt").is_file()
    assert main(["train", "lorenz-v0", "--frames", "400", "--num-envs", "4", "--set", "n_rollout=200", "--set", "epochs=1", "--resume", str(out), "--no-progress"]) == 0
    assert torch.load(out / "seed0" / "checkpoint.pt", weights_only=False)["frames"] == 400
    capsys.readouterr()
    assert main(["train", "nope-v0"]) == 2
    assert "nope-v0" in capsys.readouterr().err
    assert main(["train", "lorenz-v0", "--frames", "-1"]) == 2
    assert "frames" in capsys.readouterr().err
    assert main(["train", "lorenz-v0", "--resume", str(tmp_path / "missing")]) == 2
    assert "no checkpoint" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["train", "lorenz-v0", "--algo", "sac"])


def test_eval_and_plot_round_trip_a_run(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["train", "vortex-v0", "--frames", "400", "--seeds", "2", "--num-envs", "4", "--set", "n_rollout=200", "--set", "epochs=1", "--out", str(out), "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["eval", str(out / "seed0"), "--members", "2"]) == 0
    text = capsys.readouterr().out
    assert "uncontrolled" in text and (out / "seed0" / "controlled.gif").stat().st_size > 1000
    png = tmp_path / "curve.png"
    assert main(["plot", str(out), "--scalar", "reward", "--out", str(png)]) == 0
    assert png.stat().st_size > 10_000
    # nothing ended within 400 transitions: the episode-score curve has nothing to draw
    assert main(["plot", str(out), "--out", str(png)]) == 2
    assert "episode_score" in capsys.readouterr().err
    assert main(["eval", str(tmp_path / "nothing")]) == 2
    assert "not a run directory" in capsys.readouterr().err


TINY = ["--frames", "256", "--num-envs", "4", "--set", "frames_per_batch=64", "--set", "init_random_frames=64", "--set", "batch_size=32", "--set", "updates_per_batch=4", "--set", "hidden=32", "--no-progress"]


@pytest.mark.parametrize("algo, env_id", [("td3", "vortex-v0"), ("dqn", "lorenz-v0")])
def test_off_policy_recipes_train_resume_with_their_buffer_and_evaluate(algo, env_id, tmp_path, capsys):
    out = tmp_path / algo
    assert main(["train", env_id, "--algo", algo, "--out", str(out), *TINY]) == 0
    state = torch.load(out / "seed0" / "checkpoint.pt", weights_only=False)
    assert state["algo"] == algo and state["frames"] == 256
    first = {k: v.clone() for k, v in state["actor"].items()}
    assert (out / "seed0" / "buffer").exists()  # the collected transitions survive a stop
    more = [a if a != "256" else "384" for a in TINY]
    assert main(["train", env_id, "--algo", algo, "--resume", str(out), *more]) == 0
    state = torch.load(out / "seed0" / "checkpoint.pt", weights_only=False)
    assert state["frames"] == 384
    assert any(not torch.equal(first[k], state["actor"][k]) for k in first), "training did not change the policy"
    capsys.readouterr()
    assert main(["eval", str(out), "--members", "2", "--no-gif"]) == 0
    assert "uncontrolled" in capsys.readouterr().out


def test_algorithms_must_fit_the_action_space(capsys):
    assert main(["train", "lorenz-v0", "--algo", "td3"]) == 2
    assert "continuous" in capsys.readouterr().err
    assert main(["train", "vortex-v0", "--algo", "dqn"]) == 2
    assert "discrete" in capsys.readouterr().err
