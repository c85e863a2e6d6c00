"""The edges a user touches: every recipe's command line refuses a bad setting in one line
naming it and what it admits, before any work; files read from a run or a user are read
within bounds; reports refuse what they cannot honestly normalise; the functional API
and the multi-agent layouts check what they are given; env ids and cached starts are
checked; and the small surprises a new user met are gone. (A resume that a full disk or
kill -9 interrupts stays resumable: tests/test_kill.py.)"""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import beacon_torch
from beacon_torch import cache, received, threads
from beacon_torch.cli import main as cli
from beacon_torch.training import config, report
from beacon_torch.training.config import GradConfig, MPCConfig, PPOConfig, SACConfig, TD3Config, configure
from beacon_torch.training.run import LOG_BYTES, BadRun, load_checkpoint, read_log
from recipes import mpc, ppo

from conftest import PPO, copy_run, lock_held_elsewhere, random_policy_file

ROOT = Path(__file__).resolve().parents[1]

CORES = threads.cores()


def refused(cls, argv: list[str], capsys) -> str:
    """The one line a recipe's command line answers ``argv`` with (status 2)."""
    with pytest.raises(SystemExit) as stop:
        config.parse(cls, argv)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err and "Traceback" not in "\n".join(err)
    return err[-1]


# ---------------------------------------------------------------- the command lines

PLAN = ["--env", "burgers-v0"]


@pytest.mark.parametrize(
    "argv, words",
    [
        ([*PLAN, "--lr", "nan"], "setting 'lr' must be finite and > 0, got nan"),
        ([*PLAN, "--lr", "-1"], "setting 'lr' must be finite and > 0"),
        ([*PLAN, "--discount", "nan"], "setting 'discount' must be finite and in (0, 1], got nan"),
        ([*PLAN, "--threads", "-1"], f"setting 'threads' must be an integer in [0, {CORES}]"),
        ([*PLAN, "--threads", "100000"], f"setting 'threads' must be an integer in [0, {CORES}]"),
        ([*PLAN, "--actions", "-5"], "setting 'actions' must be a non-negative integer, got -5"),
        ([*PLAN, "--seed", "-1"], "setting 'seed' must be an integer in [0, 9223372036854775807], got -1"),
        ([*PLAN, "--seed", str(2**64)], "setting 'seed' must be an integer in [0, 9223372036854775807]"),
        ([*PLAN, "--horizon", "0"], "setting 'horizon' must be a positive integer, got 0"),
        ([*PLAN, "--param", "amp=1e9"], "setting 'params' (--param): parameter 'amp' must be in [0, 1e8]"),
        ([*PLAN, "--param", "amp=1e-400"], "--param amp=1e-400: '1e-400' is too small for a float: it would be 0"),
        ([*PLAN, "--param", "amp=1", "--param", "amp=2"], "--param amp is given twice"),
        ([*PLAN, "--plan-param", "nope=1"], "setting 'plan_params' (--plan-param): unknown parameter 'nope'"),
        ([*PLAN, "--plan-param", "amp=nan"], "setting 'plan_params' (--plan-param): parameter 'amp' must be finite"),
        (["--env", "nope-v0"], "unknown env id 'nope-v0'"),
        (["--env", "../x:burgers-v0"], "env id '../x:burgers-v0': an id is NAME-vN, or MODULE:NAME-vN"),
        (
            ["--env", "lorenz-v0"],
            "mpc needs continuous actions; lorenz-v0 has discrete ones (use lorenz-continuous-v0)",
        ),
    ],
)
def test_every_bad_planner_setting_is_one_line_naming_it_before_any_work(argv, words, capsys):
    assert words in refused(MPCConfig, argv, capsys)


@pytest.mark.parametrize(
    "cls, argv, words",
    [
        (PPOConfig, ["--env", "lorenz-v0", "--hidden", "5000"], "setting 'hidden' must be an integer in [1, 4096]"),
        (
            SACConfig,
            ["--env", "burgers-v0", "--hidden", str(10**7)],
            "setting 'hidden' must be an integer in [1, 4096]",
        ),
        (
            TD3Config,
            ["--env", "burgers-v0", "--init-random-frames", "-1"],
            "'init_random_frames' must be a non-negative",
        ),
        (PPOConfig, ["--env", "lorenz-v0", "--threads", "100000"], f"must be an integer in [0, {CORES}]"),
        (PPOConfig, ["--env", "lorenz-v0", "--seed", str(2**64)], "setting 'seed' must be an integer in [0, "),
        (GradConfig, ["--env", "burgers-v0", "--collectors", "2"], "grad differentiates through the env in this"),
        (
            PPOConfig,
            ["--env", "lorenz-v0", "--collectors", "2", "--n-rollout", "100"],
            "n_rollout (100) must be a multiple of the members collecting it, num_envs x collectors (16 x 2 = 32)",
        ),
        (PPOConfig, ["--env", "lorenz-v0", "--n-rollout", str(10**10), "--frames", str(10**11)], "a collected batch"),
    ],
)
def test_settings_a_tool_would_refuse_later_are_refused_at_the_start(cls, argv, words, capsys):
    assert words in refused(cls, argv, capsys)


def test_environment_variables_are_checked_like_settings(monkeypatch, capsys):
    monkeypatch.setenv("BEACON_TORCH_THREADS", "100000")
    assert "$BEACON_TORCH_THREADS must be an integer in [1, " in refused(PPOConfig, ["--env", "lorenz-v0"], capsys)
    monkeypatch.setenv("BEACON_TORCH_THREADS", "1")
    monkeypatch.setenv("BEACON_TORCH_COMPILE", "maybe")
    assert "$BEACON_TORCH_COMPILE must be 1, true" in refused(PPOConfig, ["--env", "lorenz-v0"], capsys)
    for off in ("0", "false", "No", "off"):
        monkeypatch.setenv("BEACON_TORCH_COMPILE", off)
        assert config.parse(PPOConfig, ["--env", "lorenz-v0"]).compile is False
    monkeypatch.setenv("BEACON_TORCH_COMPILE", "true")
    assert config.parse(PPOConfig, ["--env", "lorenz-v0"]).compile is True


def test_a_tracker_that_would_ask_for_a_key_is_refused_at_the_start(monkeypatch, tmp_path, capsys):
    monkeypatch.setenv("HOME", str(tmp_path))  # no ~/.netrc login
    monkeypatch.delenv("WANDB_API_KEY", raising=False)
    monkeypatch.delenv("WANDB_MODE", raising=False)
    line = refused(PPOConfig, ["--env", "lorenz-v0", "--logger", "wandb"], capsys)
    assert "setting 'logger' = 'wandb' needs a Weights & Biases key" in line and "WANDB_MODE=offline" in line


def test_help_shows_the_thread_count_a_run_will_use(capsys):
    with pytest.raises(SystemExit):
        config.parse(PPOConfig, ["--env", "lorenz-v0", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    count, why = threads.choose(None, "lorenz-v0", 16, training=True)
    assert f"(default: 0, which here is {count}: {why})" in text


def test_the_planners_outputs_are_checked_before_it_plans(tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    (tmp_path / "done").mkdir()
    (tmp_path / "done" / "mpc.json").write_text("{}")
    # a record's name planted as a link to someone else's file: refused, the file untouched
    (tmp_path / "planted").mkdir()
    (tmp_path / "precious.txt").write_text("mine\n")
    (tmp_path / "planted" / "mpc.json").symlink_to(tmp_path / "precious.txt")
    for out, words in (
        ("file", "is a file, not a directory"),
        ("dangling", "is a symbolic link to nothing"),
        ("done", "mpc.json exists and is not overwritten; give another --out"),
        ("planted", "mpc.json exists and is not overwritten; give another --out"),
    ):
        assert words in refused(MPCConfig, [*PLAN, "--out", str(tmp_path / out)], capsys)
    assert (tmp_path / "precious.txt").read_text() == "mine\n"


PLANNER = ["--env", "lorenz-continuous-v0", "--actions", "1", "--horizon", "1", "--iterations", "1", "--num-envs", "1"]


def run_planner(tmp_path, *args, limit: str = "", timeout: int = 300) -> subprocess.CompletedProcess:
    """``recipes/mpc.py`` in a process of its own (under a file-size limit if given)."""
    code = "import resource, runpy, signal, sys\nsignal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
    if limit:
        code += f"resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))\n"
    script = str(ROOT / "recipes" / "mpc.py")
    code += f"sys.argv = ['mpc.py'] + sys.argv[1:]\nrunpy.run_path({script!r}, run_name='__main__')\n"
    return subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=timeout, cwd=tmp_path
    )


@pytest.mark.slow(seconds=20)
def test_the_planner_on_a_full_disk_or_a_held_folder_says_so_in_one_line(tmp_path):
    out = tmp_path / "out"
    full = run_planner(tmp_path, *PLANNER, "--out", str(out), "--no-progress", limit="100")
    assert full.returncode == 2, full.stderr[-2000:]
    assert "mpc: error:" in full.stderr and len(full.stderr.strip().splitlines()) == 1, full.stderr
    assert not (out / "mpc.json").exists()
    held = tmp_path / "held"
    held.mkdir()
    with lock_held_elsewhere(held):
        second = run_planner(tmp_path, *PLANNER, "--out", str(held), "--no-progress")
        assert second.returncode == 2 and "another process is running in this directory" in second.stderr
        assert len(second.stderr.strip().splitlines()) == 1, second.stderr


def test_a_planner_record_is_never_written_with_nan(tmp_path, monkeypatch):
    cfg = mpc.parse([*PLANNER[:2], "--horizon", "1", "--iterations", "1", "--num-envs", "1", "--out", str(tmp_path)])
    nan = torch.tensor([float("nan")], dtype=torch.float64)
    monkeypatch.setattr(mpc, "planned_episodes", lambda *a, **k: (nan, {"actions": torch.ones(1)}))
    with pytest.raises(ValueError, match="the planned episodes' score_mean is nan; nothing is recorded"):
        mpc.main(cfg)
    assert not (tmp_path / "mpc.json").exists()


# ---------------------------------------------------------------- received files


def test_a_log_that_is_not_a_regular_file_of_sane_size_is_refused_without_reading(ppo_run, tmp_path, capsys):
    run = copy_run(ppo_run, tmp_path / "run")
    log = run / "ppo" / "scalars" / "reward.csv"
    log.unlink()
    os.mkfifo(log)  # reading it would wait for a writer forever
    with pytest.raises(BadRun, match="not a file, so not a log of a run"):
        read_log(log)
    with pytest.raises(BadRun, match="reward.csv: not a file"):
        ppo.main(configure(PPOConfig, "vortex-v0", out=str(run), resume=True, **{**PPO, "frames": 600}))
    log.unlink()
    with log.open("wb") as f:
        f.truncate(LOG_BYTES + 1)  # sparse: a gigabyte costs nothing on disk
    assert cli(["plot", str(run), "--scalar", "reward", "--out", str(tmp_path / "p.png")]) == 2
    assert f"more than a log of a run holds (at most {LOG_BYTES:,})" in capsys.readouterr().err


def test_a_policy_tensor_shorter_than_its_shape_is_refused(tmp_path):
    import zipfile

    good = random_policy_file(tmp_path / "good.pt", "lorenz-continuous-v0", {})
    source = zipfile.ZipFile(good)
    with zipfile.ZipFile(tmp_path / "short.pt", "w", compression=zipfile.ZIP_STORED) as out:
        for info in source.infolist():
            data = source.read(info.filename)
            if "/data/" in info.filename and len(data) > 16:
                data = data[:16]  # its shape's bytes would be read from the next entries
            out.writestr(info, data)
    with pytest.raises(received.BadFile, match="holds 16 bytes, fewer than the .* its shape needs"):
        received.torch_file(tmp_path / "short.pt", "policy file")


def test_a_page_to_write_into_must_be_a_regular_file_of_sane_size(tmp_path):
    with pytest.raises(received.BadFile, match="/dev/full: not a file, so not a markdown page"):
        report.write_block("/dev/full", "<!-- a -->", "<!-- b -->", "block")


# ---------------------------------------------------------------- reports


def summary(**changes) -> dict:
    seeds = [{"seed": f"seed{k}", "eval": s, "test": s} for k, s in enumerate((-1.5, -1.6, -1.4))]
    base = dict(
        env="burgers-v0",
        algo="ppo",
        seeds=seeds,
        uncontrolled=-3.4,
        test_uncontrolled=-4.6,
        frames=1000,
        wall_s_per_seed=10.0,
    )
    return {**base, **changes}


@pytest.mark.parametrize(
    "changes, words",
    [
        (dict(seeds=[{"seed": "s", "eval": 1e308, "test": 1.0}]), "each with a finite 'eval' score of at most 1e+09"),
        (dict(uncontrolled=-1.75 - 1e-15), "own-start uncontrolled score -1.75 is within round-off of the reference"),
        (dict(test_uncontrolled=-1e308), "test-set scores must be finite numbers of at most 1e+09"),
        (dict(uncontrolled=-1.7501), "its own-start scores normalise to"),
        (dict(seeds=[{"seed": "seed0", "eval": -1.5, "test": -1.5}] * 2), "each seed must be listed once"),
        (dict(algo="../../x"), "unknown algorithm '../../x'"),
        (dict(algo="<script>**x**</script>"), "unknown algorithm"),
    ],
)
def test_report_refuses_what_it_cannot_honestly_normalise(tmp_path, changes, words):
    path = tmp_path / "summary.json"
    path.write_text(json.dumps(summary(**changes)))
    with pytest.raises(ValueError, match="not a summary of trained seeds") as err:
        report.read(path)
    assert words in str(err.value)


def test_report_counts_a_pair_once_and_writes_its_cells_as_text(tmp_path):
    path = tmp_path / "summary.json"
    path.write_text(json.dumps(summary()))
    with pytest.raises(ValueError, match="ppo/burgers-v0: given more than once"):
        report.summaries([path, path])
    assert (
        report._cell("<script>a|b</script> **x** [l](u)")
        == "&lt;script&gt;a\\|b&lt;/script&gt; \\*\\*x\\*\\* \\[l\\](u)"
    )
    out = report.report([path], tmp_path / "r.md", tmp_path / "r.json", tmp_path / "r.png")
    json.loads((tmp_path / "r.json").read_text())  # valid JSON: no Infinity or NaN
    assert "| burgers-v0 | ppo | test set | 3 |" in out["table"]


def test_each_reference_says_where_its_one_comes_from_and_a_share_scales_with_no_control(tmp_path):
    """The results table names each "= 1" with its source; a published reduction
    (Vignon et al.'s Nusselt number, 2.0496 against 2.675 uncontrolled) is a share of no
    control's score from the same starts, so that the same reduction scores 1 whatever
    this grid's level of no control."""
    from beacon_torch.core.card import PAPER_PPO, Reference

    def pair(**changes) -> Path:
        path = tmp_path / f"{changes['env']}-{changes['algo']}.json"
        path.write_text(json.dumps(summary(**changes)))
        return path

    share = 2.0496 / 2.675
    assert report.reference("rayleigh-separable-v0", -500.0) == pytest.approx(-500.0 * share)
    assert report.normalised(-500.0 * share, -500.0, "rayleigh-separable-v0") == pytest.approx(1.0)
    assert report.normalised(-1000.0 * share, -1000.0, "rayleigh-separable-v0") == pytest.approx(1.0)
    assert report.normalised(-1.5, -3.0, "ks-v0") == pytest.approx(0.5)  # half the distance removed
    paths = [
        pair(env="burgers-v0", algo="ppo"),
        pair(
            env="ks-v0",
            algo="shac",
            uncontrolled=-6000.0,
            seeds=[{"seed": "seed0", "eval": -3000.0, "test": -3000.0}],
            test_uncontrolled=-6000.0,
        ),
    ]
    out = report.report(paths, tmp_path / "r.md", tmp_path / "r.json", tmp_path / "r.png")
    assert "| reference (= 1), its source |" in out["table"]
    assert "| -1.75 (the paper's PPO) |" in out["table"] and "| 0 (the physical limit) |" in out["table"]
    (ks,) = [r for r in out["rows"] if r["env"] == "ks-v0"]
    assert ks["normalised"] == [0.5]
    with pytest.raises(ValueError, match="source must be one of the paper's PPO, a published result"):
        Reference("a guess", "nowhere", score=1.0)
    with pytest.raises(ValueError, match="a score or a ratio to no control's score, one of the two"):
        Reference(PAPER_PPO, "the paper", score=1.0, ratio=0.5)


# ---------------------------------------------------------------- functional API, agents


def functional_burgers(members: int = 4):
    physics, params = beacon_torch.functional("burgers-v0", members)
    g = torch.Generator().manual_seed(0)
    state = physics.initial_state(params, g)
    return physics, params, state, physics.random_action(g), physics.noise(params, g)


def test_the_functional_step_refuses_what_its_physics_does_not_step():
    physics, params, state, action, noise = functional_burgers()
    other, other_params = beacon_torch.functional("lorenz-continuous-v0", 4)
    other_state = other.initial_state(other_params, torch.Generator())
    meta = type(state)(*(t.to("meta") for t in state))
    nan = type(state)(*(t * float("nan") for t in state))
    cases = [
        (dict(action=action[:, None]), ValueError, "action must be values in [-1, 1], one row per member"),
        (dict(action=action[:1]), ValueError, "got shape (1, 1)"),
        (dict(action=action.long()), TypeError, "got dtype torch.int64"),
        (dict(state=other_state), TypeError, "state must be its BurgersState"),
        (dict(state=meta), ValueError, "got a tensor on meta"),
        (dict(state=nan), ValueError, "state.u has values that are not finite"),
        (dict(noise={}), ValueError, "missing ['inlet']"),
        (dict(noise=None), ValueError, "draws noise for each action"),
        (dict(noise={"inlet": noise["inlet"][:1]}), ValueError, "noise['inlet'] must be what physics.noise draws"),
        (dict(params=other_params), TypeError, "params must be its BurgersParams"),
        (dict(params=None), TypeError, "params must be its BurgersParams"),
        (dict(stepping=torch.ones(4, dtype=torch.int64)), TypeError, "stepping must be which members take"),
        (dict(count=torch.zeros(4)), TypeError, "count must be the actions each member has taken"),
        (dict(physics=None), TypeError, "physics must be a case's Physics"),
    ]
    given = dict(physics=physics, params=params, state=state, action=action, noise=noise)
    for change, kind, words in cases:
        args = {**given, **change}
        with pytest.raises(kind) as err:
            beacon_torch.step(args.pop("physics"), args.pop("params"), args.pop("state"), args.pop("action"), **args)
        assert words in str(err.value) and "\n" not in str(err.value), (change, str(err.value))
    assert beacon_torch.step(physics, params, state, action, noise).reward.shape == (4,)


def test_functional_refuses_a_batch_beyond_memory_as_make_does():
    with pytest.raises(ValueError, match="sloshing-v0: 16,777,216 members need about .* GiB"):
        beacon_torch.functional("sloshing-v0", 2**24)


def test_the_multi_agent_layouts_refuse_unknown_agents_and_bad_actions():
    from beacon_torch.pettingzoo import parallel_env

    env = parallel_env("rayleigh-separable-v0")
    env.reset(seed=0)
    good = {agent: 0.1 for agent in env.agents}
    first = env.agents[0]
    for actions, kind, words in (
        ({**good, "nope": 0.1}, ValueError, "actions for unknown agents ['nope']"),
        ({**good, first: True}, TypeError, f"the action of {first} must be a real number"),
        ({**good, first: 1j}, TypeError, "(of dtype complex128)"),
        ({**good, first: np.zeros(3)}, ValueError, "(of shape (3,))"),
        ({**good, first: "a"}, TypeError, f"the action of {first} must be a real number"),
        ({**good, first: None}, TypeError, f"the action of {first} must be a real number"),
        ([0.1], TypeError, "actions must be a dict of agent to action"),
    ):
        with pytest.raises(kind) as err:
            env.step(actions)
        assert words in str(err.value), str(err.value)
    with pytest.raises(ValueError, match="unknown agent 'nope'; the agents are segment_0"):
        env.observation_space("nope")
    with pytest.raises(ValueError, match="unknown agent"):
        env.action_space("nope")
    assert set(env.step(good)[1]) == set(good)


# ---------------------------------------------------------------- ids and cached starts


@pytest.mark.parametrize("env_id", ["../../x:burgers-v0", ":burgers-v0", ".relative:burgers-v0", "a b:burgers-v0"])
def test_a_malformed_module_id_is_one_line_saying_what_an_id_looks_like(env_id, capsys):
    words = "an id is NAME-vN, or MODULE:NAME-vN with MODULE a Python module"
    with pytest.raises(ValueError, match=words):
        beacon_torch.make(env_id)
    from beacon_torch.pettingzoo import parallel_env

    with pytest.raises(ValueError, match=words):
        parallel_env(env_id)
    assert cli(["bench", "--envs", env_id]) == 2 and words in capsys.readouterr().err
    assert words in refused(PPOConfig, ["--env", env_id], capsys)


def test_a_choice_parameter_is_refused_none_unless_its_default_is():
    with pytest.raises(ValueError, match="parameter 'target' must be one of 'E1', 'E2', 'E3', got None"):
        beacon_torch.make("ks-v0", target=None)


def test_a_cached_start_beyond_its_cases_bounds_is_computed_again(tmp_path, monkeypatch):
    """sloshing at another gravity: its excited start goes to the user cache. Scaled by
    1e6 there (finite, but beyond the depth at which an episode ends), it is reported
    and computed again, not started from."""
    monkeypatch.setenv("BEACON_TORCH_CACHE", str(tmp_path))
    monkeypatch.setattr(cache, "_memory", {})
    first = beacon_torch.make("sloshing-v0", 1, g=9.0, dtype="float64").reset()["observation"]
    (stored,) = tmp_path.glob("sloshing-excited-*.pt")
    state = torch.load(stored, weights_only=True)
    torch.save({k: v * 1e6 for k, v in state.items()}, stored)
    monkeypatch.setattr(cache, "_memory", {})
    with pytest.warns(UserWarning, match="'h' holds values in .* beyond its case's bounds"):
        again = beacon_torch.make("sloshing-v0", 1, g=9.0, dtype="float64").reset()["observation"]
    torch.testing.assert_close(again, first, rtol=0, atol=0)


# ---------------------------------------------------------------- what a new user met


def test_gymnasium_reset_options_are_checked_like_the_torchrl_envs_keywords():
    import gymnasium

    env = gymnasium.make("beacon/lorenz-v0")
    with pytest.raises(ValueError, match=r"unknown reset option\(s\) \['reset_msk'\]; it takes none"):
        env.reset(options={"reset_msk": True})
    venv = gymnasium.make_vec("beacon/lorenz-v0", num_envs=2)
    with pytest.raises(ValueError, match=r"unknown reset option\(s\) \['reset_msk'\]; it takes \['reset_mask'\]"):
        venv.reset(options={"reset_msk": np.ones(2, dtype=bool)})
    assert venv.reset(options={"reset_mask": np.ones(2, dtype=bool)})[0].shape == (2, 6)


@pytest.mark.slow(seconds=15)
@pytest.mark.parametrize("env_id", ["cylinder-v0", "pinball-v0"])
def test_the_reset_info_of_the_wakes_carries_the_starts_loads(env_id):
    import gymnasium

    env = gymnasium.make(f"beacon/{env_id}")
    _, info = env.reset(seed=0)
    # the developed wake's drag, a few drag coefficients, not the zero of no step
    assert 1.0 < info["drag"] < 10.0 and info["lift"] != 0.0, info
    _, _, _, _, after = env.step(np.zeros(env.action_space.shape, dtype=np.float32))
    assert abs(after["drag"] - info["drag"]) < 0.05 * info["drag"], (info, after)


def test_a_planners_record_is_read_by_report(tmp_path):
    record = {
        "env": "burgers-v0",
        "starts": "test",
        "settings": {"seed": 0},
        "score_mean": -1.2,
        "uncontrolled": -4.6,
        "planned_actions": 400,
        "cpu_s_per_action": 2.0,
    }
    (tmp_path / "mpc.json").write_text(json.dumps(record))
    (row,) = report.report([tmp_path], tmp_path / "r.md", tmp_path / "r.json", tmp_path / "r.png")["rows"]
    assert row["algo"] == "mpc" and row["episodes"] == "test" and row["frames"] == 0
    assert row["wall_s_per_seed"] == 800.0 and row["scores"] == [-1.2]
    (tmp_path / "mpc.json").unlink()
    (tmp_path / "mpc.json").write_text(json.dumps({k: v for k, v in record.items() if k != "score_mean"}))
    with pytest.raises(ValueError, match="it holds the cost of 400 planned actions, no episode's score"):
        report.summaries([tmp_path])


@pytest.mark.slow(seconds=20)
def test_a_resumed_run_is_not_the_uninterrupted_one_as_the_training_page_says(tmp_path):
    settings = {**PPO, "num_envs": 2, "n_rollout": 100, "frames": 200}
    ppo.main(configure(PPOConfig, "lorenz-v0", out=str(tmp_path / "whole"), **settings))
    ppo.main(configure(PPOConfig, "lorenz-v0", out=str(tmp_path / "cut"), **{**settings, "frames": 100}))
    ppo.main(configure(PPOConfig, "lorenz-v0", out=str(tmp_path / "cut"), resume=True, **settings))
    whole, cut = (load_checkpoint(tmp_path / name)["modules"]["actor"] for name in ("whole", "cut"))
    assert any(not torch.equal(whole[k], cut[k]) for k in whole)
    page = " ".join((ROOT / "docs" / "training.md").read_text().split())
    assert "A resumed run is the same training statistically, not bit for bit" in page


def test_the_docs_site_has_a_landing_page():
    nav = (ROOT / "mkdocs.yml").read_text()
    assert "- Home: index.md" in nav and (ROOT / "docs" / "index.md").is_file()


def test_eval_of_a_run_on_an_unregistered_env_says_how_to_import_it(ppo_run, tmp_path, capsys):
    run = copy_run(ppo_run, tmp_path / "run")
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    state["env"] = "heat-v0"
    torch.save(state, run / "checkpoint.pt")
    assert cli(["eval", str(run), "--no-gif", "--num-envs", "1"]) == 2
    assert "beacon-torch --import MODULE" in capsys.readouterr().err
