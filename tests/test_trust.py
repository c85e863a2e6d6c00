"""Untrusted files and bad input: run directories, summaries and policy files from
someone else are read as data and checked, nothing is written outside or over what a
command did not create, no NaN is trained on, saved or reported, and every bad input
is one clear error. Each case plants what an attacker or an accident would leave and
asserts that nothing outside changed."""

import json
import os
import pickle
import signal
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import beacon_torch
from beacon_torch import files, pretrained
from beacon_torch.cli import main as cli
from beacon_torch.envs import shkadov
from beacon_torch.training import report
from beacon_torch.training.config import DQNConfig, PPOConfig, TD3Config, configure
from beacon_torch.training.evaluation import summarise
from beacon_torch.training.run import (
    BadRun,
    Diverged,
    buffer_folder,
    buffer_folders,
    check_checkpoint,
    load_checkpoint,
    read_log,
)
from recipes import dqn, ppo, td3
from tools import reproduce

from conftest import PPO, TD3, copy_run, lock_held_elsewhere

ROOT = Path(__file__).resolve().parents[1]


def snapshot(folder: Path) -> dict:
    """Every file under ``folder`` with its bytes: what must not change."""
    return {
        str(p.relative_to(folder)): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and not p.is_symlink()
    }


@pytest.fixture
def outside(tmp_path):
    """A folder of someone else's files that no command may touch."""
    folder = tmp_path / "outside"
    folder.mkdir()
    (folder / "precious.txt").write_text("mine\n")
    (folder / "keep.pkl").write_bytes(b"not yours")
    return folder


@pytest.fixture(scope="module")
def ended_run(tmp_path_factory, short_lorenz):
    """A run whose episodes end: one that can be summarised and published."""
    run = tmp_path_factory.mktemp("pair") / "ppo" / short_lorenz / "seed0"
    ppo.main(configure(PPOConfig, short_lorenz, out=str(run), **{**PPO, "num_envs": 1}))
    return run


# ---------------------------------------------------------------- writes outside, deletes
def test_a_planted_partial_checkpoint_link_is_refused_and_its_target_untouched(ppo_run, tmp_path, outside):
    run = copy_run(ppo_run, tmp_path / "run")
    os.symlink(outside / "precious.txt", run / "checkpoint.pt.partial")
    before = snapshot(outside)
    with pytest.raises(files.UnsafeFile, match="symbolic link"):
        ppo.main(configure(PPOConfig, "vortex-v0", out=str(run), resume=True, **{**PPO, "frames": 600}))
    assert snapshot(outside) == before and not (run / "checkpoint.pt").is_symlink()
    # even where no check ran first, a write replaces a link rather than following it
    os.symlink(outside / "precious.txt", tmp_path / "target.txt")
    files.write_text(tmp_path / "target.txt", "new")
    assert (tmp_path / "target.txt").read_text() == "new" and not (tmp_path / "target.txt").is_symlink()
    assert snapshot(outside) == before


def test_a_planted_partial_buffer_link_is_refused_and_its_target_untouched(tmp_path, outside):
    run = tmp_path / "run"
    td3.main(configure(TD3Config, "vortex-v0", out=str(run), **TD3))
    os.symlink(outside, run / "buffer.partial")
    before = snapshot(outside)
    with pytest.raises(files.UnsafeFile, match="symbolic link"):
        td3.main(configure(TD3Config, "vortex-v0", out=str(run), resume=True, **{**TD3, "frames": 384}))
    assert snapshot(outside) == before
    # the buffer is written into a folder the run creates, whatever lies beside it
    (run / "buffer.partial").unlink()
    (run / "buffer.partial").mkdir()
    (run / "buffer.partial" / "keep.pkl").write_bytes(b"not yours")
    td3.main(configure(TD3Config, "vortex-v0", out=str(run), resume=True, **{**TD3, "frames": 384}))
    assert (run / "buffer.partial" / "keep.pkl").read_bytes() == b"not yours" and load_checkpoint(run)["frames"] == 384


def test_eval_refuses_a_run_with_a_planted_animation_link(ppo_run, tmp_path, outside, capsys):
    run = copy_run(ppo_run, tmp_path / "run")
    os.symlink(outside / "precious.txt", run / "controlled.gif")
    before = snapshot(outside)
    assert cli(["eval", str(run), "--num-envs", "2"]) == 2
    err = capsys.readouterr().err
    assert "controlled.gif" in err and "symbolic link" in err and len(err.strip().splitlines()) == 1
    assert snapshot(outside) == before


# ---------------------------------------------------------------- documented commands replace nothing
def test_run_replaces_no_file(tmp_path, monkeypatch, capsys):
    """Under default names a command writes beside what is there (free numbered names);
    a name the user gives that is taken is refused before any work."""
    monkeypatch.chdir(tmp_path)
    mine = tmp_path / "runs" / "vortex-v0"
    mine.mkdir(parents=True)
    (mine / "run.png").write_text("mine")
    assert cli(["run", "vortex-v0", "--num-envs", "2"]) == 0
    assert (mine / "run.png").read_text() == "mine"
    assert (mine / "run-2.png").stat().st_size > 1000 and (mine / "scores-2.json").is_file()
    assert "run-2.png" in capsys.readouterr().out
    assert cli(["run", "vortex-v0", "--out", str(mine)]) == 2
    assert "run.png exists" in capsys.readouterr().err
    (tmp_path / "a.gif").write_text("mine")
    assert cli(["run", "vortex-v0", "--gif", "a.gif"]) == 2
    assert (tmp_path / "a.gif").read_text() == "mine" and not (mine / "run-3.png").exists()


def test_eval_plot_and_report_replace_no_file(ppo_run, tmp_path, monkeypatch, capsys):
    run = copy_run(ppo_run, tmp_path / "run")
    (run / "controlled.gif").write_text("mine")
    assert cli(["eval", str(run), "--num-envs", "1"]) == 0
    assert (run / "controlled.gif").read_text() == "mine" and (run / "controlled-2.gif").stat().st_size > 1000
    monkeypatch.chdir(tmp_path)
    (tmp_path / "learning_curve.png").write_text("mine")
    assert cli(["plot", str(run), "--scalar", "reward"]) == 0
    assert (tmp_path / "learning_curve.png").read_text() == "mine" and (tmp_path / "learning_curve-2.png").is_file()
    assert cli(["plot", str(run), "--scalar", "reward", "--out", "learning_curve.png"]) == 2
    assert "learning_curve.png exists" in capsys.readouterr().err
    (tmp_path / "rep").mkdir()
    (tmp_path / "rep" / "report.png").write_text("mine")
    summary = tmp_path / "summary.json"
    summary.write_text(json.dumps(summary_of()))
    assert cli(["report", str(summary), "--out", "rep"]) == 2
    assert (tmp_path / "rep" / "report.png").read_text() == "mine" and not (tmp_path / "rep" / "report.md").exists()
    assert cli(["report", str(summary)]) == 0 and cli(["report", str(summary)]) == 0
    assert (tmp_path / "runs" / "report" / "report-2.md").is_file()


def test_eval_pretrained_replaces_no_animation(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "ppo").mkdir()
    (tmp_path / "ppo" / "lorenz-v0.gif").write_text("mine")
    assert cli(["eval", "--pretrained", "ppo/lorenz-v0", "--num-envs", "1"]) == 0
    assert (tmp_path / "ppo" / "lorenz-v0.gif").read_text() == "mine"
    assert (tmp_path / "ppo" / "lorenz-v0-2.gif").stat().st_size > 1000


def test_publish_and_report_take_no_path_from_a_summary(ended_run, tmp_path, outside):
    pair = tmp_path / "runs" / "ppo" / "short-lorenz-v0"
    copy_run(ended_run, pair / "seed0")
    summary = {
        "algo": "../../../../outside/owned",
        "env": "short-lorenz-v0",
        "seeds": [{"seed": "seed0", "eval": 1.0, "frames": 400, "uncontrolled": 0.0}],
        "uncontrolled": 0.0,
        "frames": 400,
        "wall_s_per_seed": 1.0,
        "png": str(outside / "precious.txt"),
    }
    (pair / "summary.json").write_text(json.dumps(summary))
    recorded, images = tmp_path / "repo" / "recorded", tmp_path / "repo" / "img"
    before = snapshot(outside)
    with pytest.raises(ValueError, match="unknown algorithm"):
        reproduce.publish(pair, recorded, images)
    # a true summary naming a file outside as its curve: the curve published is drawn
    # again from the seeds' logs, and the file it names is never touched
    (recorded / "ppo").mkdir(parents=True)
    (recorded / "ppo" / "short-lorenz-v0.json").write_text(json.dumps({**summary, "algo": "ppo"}))
    true = summarise(pair, num_envs=1)
    (pair / "summary.json").write_text(json.dumps({**true, "png": str(outside / "precious.txt")}))
    reproduce.publish(pair, recorded, images, shipped=tmp_path / "repo" / "shipped")
    assert snapshot(outside) == before and not (tmp_path / "outside" / "owned.json").exists()
    assert (images / "ppo" / "short-lorenz-v0.png").stat().st_size > 1000
    assert json.loads((recorded / "ppo" / "short-lorenz-v0.json").read_text())["png"] != str(outside / "precious.txt")
    # a recorded summary naming an unknown algorithm stops the page, writing nothing
    (recorded / "x").mkdir()
    (recorded / "x" / "y.json").write_text(json.dumps(summary))
    page = tmp_path / "repo" / "results.md"
    with pytest.raises(ValueError, match="unknown algorithm"):
        reproduce.write_results_page(recorded, page, images)
    assert not page.exists() and snapshot(outside) == before


@pytest.mark.parametrize(
    "name", ["../../somewhere/evil/lorenz-v0", "ppo/../../x/lorenz-v0", "ppo\x00/lorenz-v0", "../lorenz-v0", 3]
)
def test_pretrained_load_reads_only_the_shipped_files(name, tmp_path):
    evil = tmp_path / "evil" / "lorenz-v0.pt"
    evil.parent.mkdir()
    torch.save({"env": "lorenz-v0"}, evil)
    with pytest.raises(ValueError, match="no pretrained|a trained pair is named ALGO/ENV"):
        pretrained.load(name)
    with pytest.raises(ValueError, match="a trained pair is named ALGO/ENV"):
        pretrained.load("ppo/../lorenz-v0")
    with pytest.raises(ValueError, match="unknown env id"):
        pretrained.info("ppo/lorenz")


# ---------------------------------------------------------------- nothing overwritten
def test_a_fresh_run_refuses_a_directory_holding_a_run(ppo_run, tmp_path, capsys):
    run = copy_run(ppo_run, tmp_path / "run")
    before = snapshot(run)
    with pytest.raises(FileExistsError, match="--resume"):
        ppo.main(configure(PPOConfig, "vortex-v0", out=str(run), **PPO))
    assert snapshot(run) == before
    # from the command line: one line and status 2
    done = subprocess.run(
        [
            sys.executable,
            str(ROOT / "recipes" / "ppo.py"),
            "--env",
            "vortex-v0",
            "--out",
            str(run),
            "--frames",
            "400",
            "--n-rollout",
            "200",
            "--num-envs",
            "4",
            "--no-progress",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 2 and "holds a run" in done.stderr and len(done.stderr.strip().splitlines()) == 1, (
        done.stderr
    )
    assert snapshot(run) == before
    # an empty directory, or one with files of the user's own, is fine for a new run
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("x")
    ppo.main(configure(PPOConfig, "vortex-v0", out=str(tmp_path / "mine"), **PPO))
    assert (tmp_path / "mine" / "notes.txt").read_text() == "x"


def test_a_second_process_on_a_running_directory_is_refused(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    with lock_held_elsewhere(run):
        with pytest.raises(files.UnsafeFile, match="another process"):
            ppo.main(configure(PPOConfig, "vortex-v0", out=str(run), **PPO))
        assert not (run / "checkpoint.pt").exists()
    # the kernel dropped the killed holder's lock
    ppo.main(configure(PPOConfig, "vortex-v0", out=str(run), **PPO))
    assert load_checkpoint(run)["frames"] == 400


def rewrite_checkpoint(run: Path, **changes):
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    for key, value in changes.items():
        *path, last = key.split(".")
        target = state
        for part in path:
            target = target[part]
        if value is None:
            del target[last]
        elif isinstance(value, str) and value == "nan":
            target[last] = {k: torch.full_like(v, float("nan")) for k, v in target[last].items()}
        else:
            target[last] = value
    torch.save(state, run / "checkpoint.pt")


@pytest.mark.parametrize(
    "change, words",
    [
        (dict(frames=10**12), "past its run's total"),
        (dict(frames=1e12), "'frames' must be a non-negative integer"),
        (dict(frames=-500), "'frames' must be a non-negative integer"),
        (dict(algo="../../x"), "unknown algorithm"),
        (dict(env="nowhere-v0"), "unknown env"),
        (dict(modules=None), "no 'modules'"),
        (dict(**{"policy.hidden": -5}), "width in \\[1, 4096\\]"),
        (dict(**{"policy.hidden": 100_000}), "width in \\[1, 4096\\]"),
        (dict(**{"policy.network": "os.system"}), "must name a network"),
        (dict(**{"obs_norm.scale": torch.zeros(8)}), "positive scale"),
        (dict(**{"modules.actor": "nan"}), "non-finite weights"),
        (dict(counters={"buffer_len": 5, "buffer_capacity": 2, "buffer_files": {}}), "capacity"),
    ],
)
def test_a_resume_and_an_eval_refuse_forged_checkpoint_records(ppo_run, tmp_path, change, words, capsys):
    run = copy_run(ppo_run, tmp_path / "run")
    rewrite_checkpoint(run, **change)
    logs = snapshot(run / "ppo")
    with pytest.raises(BadRun, match=words):
        ppo.main(configure(PPOConfig, "vortex-v0", out=str(run), resume=True, **{**PPO, "frames": 600}))
    assert snapshot(run / "ppo") == logs, "a refused resume changed the logs"
    assert cli(["eval", str(run), "--no-gif", "--num-envs", "2"]) == 2
    err = capsys.readouterr().err
    assert "checkpoint.pt" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize(
    "setting, value, words",
    [
        ("hidden", "wide", "'hidden' must be of type int"),
        ("epochs", 2.5, "'epochs' must be of type int"),
        ("entropy", -1.0, "'entropy' must be finite and >= 0"),
    ],
)
def test_a_resume_refuses_recorded_settings_of_the_wrong_type_or_range(ppo_run, tmp_path, setting, value, words):
    run = copy_run(ppo_run, tmp_path / "run")
    rewrite_checkpoint(run, **{f"config.{setting}": value})
    with pytest.raises(ValueError, match=words) as err:
        configure(PPOConfig, "vortex-v0", out=str(run), resume=True, **{**PPO, "frames": 600})
    assert "checkpoint.pt" in str(err.value)


@pytest.mark.parametrize(
    "line", [b"1,2,3\n", b"step,value\n", b"\xff\xfe\x00binary\n", b"-5,1.0\n", b"1.5,1.0\n", b"nan,1.0\n"]
)
def test_a_resume_refuses_a_log_it_did_not_write_and_mends_nothing(ppo_run, tmp_path, line):
    run = copy_run(ppo_run, tmp_path / "run")
    log = run / "ppo" / "scalars" / "reward.csv"
    log.write_bytes(log.read_bytes() + line)
    before = log.read_bytes()
    with pytest.raises(BadRun, match="reward.csv"):
        ppo.main(configure(PPOConfig, "vortex-v0", out=str(run), resume=True, **{**PPO, "frames": 600}))
    assert log.read_bytes() == before
    with pytest.raises(BadRun, match="reward.csv"):
        read_log(log)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    st.lists(
        st.lists(
            st.one_of(st.text(max_size=6), st.integers(-10, 10**6).map(str), st.floats(allow_nan=True).map(str)),
            min_size=0,
            max_size=4,
        ),
        max_size=5,
    )
)
def test_log_lines_are_two_numbers_or_a_clear_error(tmp_path, rows):
    import csv

    file = tmp_path / "x.csv"
    with file.open("w", newline="") as f:
        csv.writer(f).writerows(rows)
    try:
        read = read_log(file)
    except BadRun as err:
        assert str(file) in str(err)
    else:
        assert all(step >= 0 and float(step).is_integer() for step, _ in read)


def valid_state():
    from beacon_torch.training.env import make_env
    from beacon_torch.training.networks import stochastic_actor

    env = make_env("vortex-v0", 1, norm_steps=0)
    return {
        "env": "vortex-v0",
        "algo": "ppo",
        "frames": 400,
        "elapsed": 1.0,
        "seed": 0,
        "config": {"frames": 400, "n_rollout": 200},
        "policy": {"network": "stochastic_actor", "hidden": 8},
        "counters": {},
        "obs_norm": env.transform[0].state_dict(),
        "modules": {"actor": stochastic_actor(env, 8).state_dict()},
    }


JUNK = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**70), 2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
    st.lists(st.integers(), max_size=3),
    st.dictionaries(st.text(max_size=4), st.integers(), max_size=2),
)


@settings(max_examples=150, deadline=None)
@given(
    key=st.sampled_from(
        [
            "env",
            "algo",
            "frames",
            "elapsed",
            "seed",
            "config",
            "policy",
            "counters",
            "obs_norm",
            "modules",
            "policy.hidden",
            "policy.network",
            "config.frames",
        ]
    ),
    value=JUNK,
)
def test_any_forged_checkpoint_field_is_one_clear_error(key, value):
    state = valid_state()
    check_checkpoint(state, "ok.pt")
    *path, last = key.split(".")
    target = state
    for part in path:
        target = target[part]
    target[last] = value
    try:
        check_checkpoint(state, "forged.pt")
    except BadRun as err:
        assert str(err).startswith("forged.pt: not a checkpoint of a run (")


def test_a_tampered_replay_buffer_is_named(tmp_path):
    run = tmp_path / "run"
    td3.main(configure(TD3Config, "vortex-v0", out=str(run), **TD3))
    meta = next(buffer_folder(run).rglob("*.json"))
    meta.write_bytes(b"{" * len(meta.read_bytes()))  # the size it had: only its reading can tell
    with pytest.raises(BadRun, match="unreadable replay buffer"):
        td3.main(configure(TD3Config, "vortex-v0", out=str(run), resume=True, **{**TD3, "frames": 384}))


SUMMARY_KEYS = ["env", "algo", "seeds", "uncontrolled", "frames", "wall_s_per_seed", "train_mean", "test_uncontrolled"]


@settings(max_examples=150, deadline=None)
@given(
    key=st.sampled_from(SUMMARY_KEYS),
    value=st.one_of(
        JUNK,
        st.lists(st.fixed_dictionaries({"eval": JUNK}), max_size=2),
        st.lists(st.fixed_dictionaries({"eval": JUNK, "test": JUNK}), max_size=2),
    ),
    held_out=st.booleans(),
)
def test_any_forged_summary_field_is_one_clear_error(key, value, held_out):
    summary = {**summary_of(train_mean=-1.5, **(TEST_SCORES if held_out else {})), key: value}
    try:
        report.check_summary(summary, "forged.json")
    except ValueError as err:
        assert str(err).startswith("forged.json: not a summary of trained seeds (")
    else:  # what passes is scored without error or NaN, on either set of episodes
        for starts in report.EPISODES:
            row = report.row(summary, starts)
            assert np.isfinite(row["iqm"]) and np.isfinite(row["ci"]).all()


@settings(max_examples=150, deadline=None)
@given(
    curve=st.one_of(
        JUNK,
        st.fixed_dictionaries({"frames": st.lists(JUNK, max_size=3), "score": st.lists(JUNK, max_size=3)}),
        st.fixed_dictionaries(
            {
                "frames": st.lists(st.integers(-5, 10**20), max_size=3),
                "score": st.lists(st.floats(), max_size=3),
                "wall_s": st.lists(st.floats(), max_size=3),
            }
        ),
    )
)
def test_a_seed_s_training_curve_is_three_lists_of_bounded_numbers_or_one_clear_error(curve):
    summary = summary_of(train_mean=-1.5)
    summary["seeds"][0]["curve"] = curve
    try:
        report.check_summary(summary, "forged.json")
    except ValueError as err:
        assert str(err).startswith("forged.json: not a summary of trained seeds (a seed's 'curve' must")
    else:
        frames, score, wall = curve["frames"], curve["score"], curve["wall_s"]
        assert len(frames) == len(score) and len(wall) in (0, len(frames)) and frames == sorted(frames)
        assert all(0 <= f <= report.MAX_COUNT for f in frames) and np.isfinite(score + wall).all()
    good = {"frames": [0, 64, 128], "score": [-2.0, -1.5, -1.0], "wall_s": [0.0, 1.0, 2.5]}
    summary["seeds"][0]["curve"] = good
    assert report.check_summary(summary, "true.json") is summary


# ---------------------------------------------------------------- no NaN as a result
def test_a_diverging_training_stops_and_keeps_its_last_good_checkpoint(tmp_path):
    settings_ = dict(
        frames=640,
        frames_per_batch=64,
        num_envs=4,
        updates_per_batch=16,
        batch_size=32,
        hidden=16,
        progress=False,
        logger="csv",
        checkpoint_every=1,
    )
    run = tmp_path / "run"
    dqn.main(configure(DQNConfig, "lorenz-v0", out=str(run), **{**settings_, "frames": 128}))
    # the run's optimiser at a rate that diverges from here on
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    state["modules"]["optim"]["param_groups"][0]["lr"] = 1e30
    torch.save(state, run / "checkpoint.pt")
    good = (run / "checkpoint.pt").read_bytes()
    with pytest.raises(Diverged, match="diverged after 128 transitions"):
        dqn.main(configure(DQNConfig, "lorenz-v0", out=str(run), resume=True, **settings_))
    assert (run / "checkpoint.pt").read_bytes() == good, "a diverged update reached the checkpoint"
    # from the command line: one line, status 2, and no checkpoint of NaN weights
    done = subprocess.run(
        [
            sys.executable,
            str(ROOT / "recipes" / "dqn.py"),
            "--env",
            "lorenz-v0",
            "--out",
            str(tmp_path / "cli"),
            "--lr",
            "1e30",
            "--frames",
            "640",
            "--num-envs",
            "4",
            "--frames-per-batch",
            "64",
            "--updates-per-batch",
            "16",
            "--num-envs",
            "32",
            "--hidden",
            "16",
            "--checkpoint-every",
            "1",
            "--no-progress",
            "--logger",
            "csv",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 2 and "diverged" in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert not (tmp_path / "cli" / "checkpoint.pt").exists() or load_checkpoint(tmp_path / "cli")["frames"] < 640


def summary_of(**changes):
    summary = {
        "env": "sloshing-v0",
        "algo": "ppo",
        "uncontrolled": -2.1,
        "frames": 200_000,
        "wall_s_per_seed": 120.0,
        "seeds": [{"eval": e} for e in (-1.1, -1.6, -2.1)],
    }
    return {**summary, **changes}


# a summary's scores on the test set's starts, as summarise records them
TEST_SCORES = dict(
    seeds=[{"eval": e, "test": t} for e, t in ((-1.1, -1.9), (-1.6, -2.3), (-2.1, -2.0))], test_uncontrolled=-2.6
)


@pytest.mark.parametrize(
    "change, words",
    [
        (dict(seeds=[]), "at least one seed"),
        (dict(TEST_SCORES, test_uncontrolled=float("nan")), "test-set scores must be finite"),
        (dict(seeds=TEST_SCORES["seeds"]), "test-set scores must be finite"),
        (dict(TEST_SCORES, seeds=[{"eval": -1.1, "test": None}]), "test-set scores must be finite"),
        (dict(TEST_SCORES, test_uncontrolled=-1.1), "test-set uncontrolled score -1.1 is within round-off of the"),
        (dict(seeds=None), "at least one seed"),
        (dict(seeds=[{"eval": float("nan")}]), "finite 'eval'"),
        (dict(seeds=[{"eval": float("inf")}]), "finite 'eval'"),
        (dict(uncontrolled=float("nan")), "'uncontrolled' must be a finite"),
        (dict(uncontrolled=-1.1), "own-start uncontrolled score -1.1 is within round-off of the reference"),
        (dict(env="nowhere-v0"), "unknown env"),
        (dict(frames=-1), "'frames' must be"),
    ],
)
def test_report_refuses_empty_or_non_finite_summaries(tmp_path, change, words, capsys):
    file = tmp_path / "ppo-sloshing-v0.json"
    file.write_text(json.dumps(summary_of(**change)))
    with pytest.raises(ValueError, match=words):
        report.summaries([file])
    assert cli(["report", str(file), "--out", str(tmp_path / "report")]) == 2
    err = capsys.readouterr().err
    assert str(file) in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "report" / "report.md").exists()


def differentiated_grads(env_id: str, n_steps: int, *, scale: float | None = None, shared=None, **params):
    """The gradient of the summed rewards with respect to a policy weight shared by
    every member (and to ``shared``, a parameter shared by them), float64."""
    members = len(next(iter(params.values()))) if params else 2
    env = beacon_torch.make(env_id, members, dtype="float64", differentiable=True, **params)
    env.reset()
    if scale is not None:  # the second member's state scaled out of any range
        env.set_state({k: torch.cat([v[:1], v[1:] * scale]) for k, v in env.state._asdict().items()})
    w = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)
    total = 0.0
    ended = torch.zeros(members, dtype=torch.bool)
    for _ in range(n_steps):
        action = torch.tanh(w * env.observation[:, : env.n_actions]).reshape(members, env.n_actions)
        _, reward, terminated, _ = env.step_members(action)
        ended |= terminated
        total = total + reward.sum()
    leaves = [w] + ([shared] if shared is not None else [])
    return torch.autograd.grad(total, leaves), ended


@pytest.mark.parametrize(
    "env_id, blown, alone",
    [
        ("sloshing-v0", dict(amp=[5.0, 1e6]), dict(amp=[5.0])),
        ("lorenz-continuous-v0", dict(reward_width=[1.0, 1.0], rho=[28.0, 1e6]), dict(reward_width=[1.0], rho=[28.0])),
        ("lorenz-continuous-v0", dict(reward_width=[1.0, 1.0], scale=1e30), dict(reward_width=[1.0])),
        ("sloshing-v0", dict(amp=[5.0, 5.0], scale=1e30), dict(amp=[5.0])),
    ],
)
def test_a_blown_up_member_adds_zero_not_nan_to_shared_gradients(env_id, blown, alone):
    (grad,), ended = differentiated_grads(env_id, 20, **blown)
    assert ended.tolist() == [False, True], "the second member did not blow up"
    (reference,), _ = differentiated_grads(env_id, 20, **alone)
    assert torch.isfinite(grad) and grad != 0
    assert torch.allclose(grad, reference, rtol=1e-10, atol=0), (grad, reference)


def test_a_blown_up_member_adds_zero_to_a_parameter_the_batch_shares_and_to_its_own():
    rho = torch.tensor([28.0, 1e6], dtype=torch.float64, requires_grad=True)
    (_, g_rho), ended = differentiated_grads("lorenz-continuous-v0", 20, shared=rho, reward_width=[1.0, 1.0], rho=rho)
    assert ended.tolist() == [False, True] and torch.isfinite(g_rho).all() and g_rho[1] == 0 and g_rho[0] != 0
    alone = torch.tensor([28.0], dtype=torch.float64, requires_grad=True)
    (_, g_alone), _ = differentiated_grads("lorenz-continuous-v0", 20, shared=alone, reward_width=[1.0], rho=alone)
    assert torch.allclose(g_rho[:1], g_alone, rtol=1e-10, atol=0)


def test_a_blown_up_member_steps_as_without_gradients():
    """The retaken step draws the same noise: with and without a graph, the rewards of
    a batch with a blown-up member are the same."""
    rewards = []
    for differentiable in (True, False):
        env = beacon_torch.make("burgers-v0", 2, dtype="float64", seed=4, differentiable=differentiable)
        env.reset()
        env.set_state({k: torch.cat([v[:1], v[1:] * 1e30]) for k, v in env.state._asdict().items()})
        action = torch.full((2, 1), 0.3, dtype=torch.float64, requires_grad=differentiable)
        rewards.append(torch.stack([env.step_members(action)[1] for _ in range(5)]).detach())
    assert torch.equal(*rewards)


# ---------------------------------------------------------------- one clear error each
def test_cli_bad_inputs_are_one_line_with_status_2(ppo_run, tmp_path, capsys):
    def one_line(argv, words):
        assert cli(argv) == 2
        err = capsys.readouterr().err
        assert words in err and len(err.strip().splitlines()) == 1, err

    one_line(["eval", str(ppo_run), "--device", "meta", "--no-gif"], "meta")
    one_line(["plot", str(tmp_path / "nothing"), "--out", str(tmp_path / "p.png")], "not a run directory")
    run = copy_run(ppo_run, tmp_path / "run")
    (run / "ppo" / "scalars" / "episode_score.csv").write_text("step,value\n")
    one_line(["plot", str(run), "--out", str(tmp_path / "p.png")], "episode_score.csv, line 1")
    with pytest.raises(SystemExit) as exit_:
        reproduce.main(["train", "--envs", "lorenz-v0", "--seeds", "0"])
    assert exit_.value.code == 2 and "--seeds: expects a positive integer" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:
        reproduce.main(["publish", str(tmp_path / "nothing")])
    assert exit_.value.code == 2 and "reproduce: error:" in capsys.readouterr().err


def test_a_replay_buffer_that_cannot_fit_on_the_disk_is_one_clear_error(tmp_path, monkeypatch):
    run = tmp_path / "run"
    monkeypatch.setattr(files, "free_bytes", lambda folder: 1000)
    with pytest.raises(OSError, match="no room to save the replay buffer"):
        td3.main(configure(TD3Config, "vortex-v0", out=str(run), **{**TD3, "checkpoint_every": 1}))
    assert not buffer_folders(run) and not list(run.glob(".*partial"))


@pytest.mark.parametrize(
    "record, words",
    [
        ({"weights": "nan"}, "non-finite"),
        ({"env": "vortex-v0"}, "a policy of vortex-v0, not of lorenz-v0"),
        ({"hidden": 10**5}, "width"),
        ({"network": "builtins.eval"}, "unknown"),
    ],
)
def test_policy_files_are_checked_before_use(tmp_path, record, words):
    shipped = pretrained._read(pretrained.shipped("ppo/lorenz-v0"))[0]
    forged = dict(shipped)
    for key, value in record.items():
        if value == "nan":
            forged["weights"] = {
                k: torch.full_like(v, float("nan")) if v.is_floating_point() else v
                for k, v in shipped["weights"].items()
            }
        else:
            forged[key] = value
    file = tmp_path / "policy.pt"
    torch.save(forged, file)
    with pytest.raises(ValueError, match=words) as err:
        pretrained.load_file(file, "lorenz-v0")
    assert str(file) in str(err.value)


def test_a_tampered_policy_file_is_named_and_a_policy_on_another_env_says_so(tmp_path):
    file = tmp_path / "policy.pt"
    file.write_bytes(pretrained.shipped("ppo/lorenz-v0").read_bytes()[:500])
    with pytest.raises(ValueError, match=f"{file}: not a policy file"):
        pretrained.load_file(file)
    policy = pretrained.load("ppo/lorenz-v0")
    env = beacon_torch.make("vortex-v0", 2)
    with pytest.raises(ValueError, match="trained on lorenz-v0 \\(6 observations\\); it was given 8"):
        policy(env.reset())


def test_a_non_tensor_action_is_a_type_error_not_a_hang():
    env = beacon_torch.make("lorenz-v0", 2)
    td = env.reset()
    td.set_non_tensor("action", [1, 1])
    signal.alarm(30)  # the failure this guards against is a hang
    try:
        with pytest.raises(TypeError, match="the action must be a tensor"):
            env.step(td)
    finally:
        signal.alarm(0)


def test_masks_states_and_devices_of_the_wrong_kind_are_named():
    env = beacon_torch.make("vortex-v0", 2)
    td = env.reset()
    td["action"] = torch.zeros(2, 2)
    with pytest.raises(TypeError, match="'_step' mask must be a bool tensor"):
        env.step(td.set("_step", torch.ones(2, 1)))
    with pytest.raises(ValueError, match="device 'meta'"):
        beacon_torch.make("vortex-v0", 2, device="meta")
    # another device: refused, whether this machine has it or not
    with pytest.raises(ValueError, match="stays on the device it was made on|cannot be used on this machine"):
        env.to("cuda")
    with pytest.raises(ValueError, match="meta"):
        env.to("meta")
    assert env.to("cpu") is env
    state = {k: v.to(torch.int64) for k, v in env.state._asdict().items()}
    obs = env.set_state(state)
    assert obs.dtype == torch.float32 and env.state.ay.dtype == torch.float32
    with pytest.raises(TypeError, match="real numbers"):
        env.set_state({k: v.to(torch.complex64) for k, v in env.state._asdict().items()})
    env.close()
    with pytest.raises(RuntimeError, match="closed env"):
        env.step(td)
    with pytest.raises(RuntimeError, match="closed env"):
        env.reset()


def test_gradients_that_would_be_dropped_warn():
    rho = torch.tensor(28.0, requires_grad=True)
    with pytest.warns(UserWarning, match="parameter\\(s\\) \\['rho'\\] require grad but the env is not differentiable"):
        env = beacon_torch.make("lorenz-v0", 2, rho=rho)
    env.reset()
    with pytest.warns(UserWarning, match="require grad but the env is not differentiable"):
        env.set_state({k: v.clone().requires_grad_() for k, v in env.state._asdict().items()})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        beacon_torch.make("lorenz-v0", 2, rho=rho, differentiable=True)


@settings(max_examples=40, deadline=None)
@given(value=st.floats(min_value=1e-320, max_value=1e-38))
def test_a_parameter_the_precision_takes_out_of_range_is_refused(value):
    try:
        env = beacon_torch.make("vortex-v0", 1, re=value)
    except ValueError as err:
        assert (
            "becomes" in str(err) and "float32" in str(err) and torch.tensor(value, dtype=torch.float32).item() == 0.0
        )
    else:
        assert env.params.re.item() > 0


def test_a_member_at_the_published_gravity_starts_from_the_published_state():
    mixed = beacon_torch.make("sloshing-v0", 2, g=[5.0, 9.81], dtype="float64")
    mixed.reset()
    for g, row in ((9.81, 1), (5.0, 0)):
        alone = beacon_torch.make("sloshing-v0", 1, g=g, dtype="float64")
        alone.reset()
        assert all(torch.equal(m[row], a[0]) for m, a in zip(mixed.state, alone.state, strict=True))


def test_huge_batches_are_refused_before_allocating_and_envs_pickle():
    with pytest.raises(ValueError, match="members need about .* at most about"):
        beacon_torch.make("mixing-v0", 2**24)
    env = beacon_torch.make("burgers-v0", 2, seed=3)
    copy = pickle.loads(pickle.dumps(env))
    rewards = []
    for e in (env, copy):
        e.reset()
        rewards.append(torch.stack([e.step_members(e.null_action())[1] for _ in range(3)]))
    assert torch.equal(*rewards)


def test_state_dict_continues_an_episode_bit_for_bit():
    env = beacon_torch.make("burgers-v0", 3, seed=1)
    env.reset()
    for _ in range(5):
        env.step_members(env.null_action())
    saved = env.state_dict()
    assert {"count", "rng", "state.u"} <= set(saved)
    other = beacon_torch.make("burgers-v0", 3, seed=99)
    other.load_state_dict(saved)
    assert torch.equal(other.step_count, env.step_count)
    for _ in range(5):
        assert torch.equal(env.step_members(env.null_action())[1], other.step_members(other.null_action())[1])
    with pytest.raises(KeyError, match="unknown entries"):
        other.load_state_dict({**saved, "extra": torch.zeros(1)})


def test_adapters_refuse_what_they_cannot_honour():
    import gymnasium

    import beacon_torch.gym  # noqa: F401
    from beacon_torch.sb3 import BeaconVecEnv

    with pytest.raises(ValueError, match="cannot change it"):
        gymnasium.make("beacon/burgers-v0", env_id="lorenz-v0")
    venv = gymnasium.make_vec("beacon/lorenz-v0", num_envs=2)
    venv.reset(seed=[3, 4])
    with pytest.raises(ValueError, match="share one random stream"):
        venv.reset(seed=[0, 99])
    sb3 = BeaconVecEnv("sloshing-v0", n_envs=2)
    for name, value in (("n_envs", 3), ("amp", 1e9), ("dtype", torch.float16)):
        with pytest.raises(AttributeError, match="not settable|a parameter of the env"):
            sb3.set_attr(name, value)
    with pytest.raises(TypeError, match="True or False"):
        sb3.set_attr("check_actions", "no")
    sb3.set_attr("render_index", 1)
    for seed in ("a", 1.5, -1):
        with pytest.raises((TypeError, ValueError), match="seed must be an integer"):
            sb3.seed(seed)


def test_the_cache_ignores_an_empty_path_and_leaves_no_temporary_file(tmp_path, monkeypatch):
    from beacon_torch import cache

    monkeypatch.setenv("BEACON_TORCH_CACHE", "")
    assert cache.cache_dir() == Path.home() / ".cache" / "beacon-torch"
    blocked = tmp_path / "blocked"
    (blocked / "x.pt").mkdir(parents=True)  # a folder where the file should go
    with pytest.raises(OSError):
        cache.save(shkadov.Film(h=torch.zeros(2), q=torch.zeros(2)), blocked / "x.pt")
    assert sorted(p.name for p in blocked.iterdir()) == ["x.pt"]
    np.testing.assert_equal(len(list(blocked.rglob("*"))), 1)


# ---------------------------------------------------------------- resume, casts, one line each
@pytest.mark.parametrize("planted", ["missing", "directory"])
def test_a_resume_without_a_checkpoint_is_refused_and_truncates_nothing(ppo_run, tmp_path, planted):
    run = copy_run(ppo_run, tmp_path / "run")
    (run / "checkpoint.pt").unlink()
    if planted == "directory":
        (run / "checkpoint.pt").mkdir()
    logs = snapshot(run)
    words = "no checkpoint to resume \\(" + ("a directory" if planted == "directory" else "missing") + "\\)"
    with pytest.raises(BadRun, match=f"{words}; a fresh run needs a new --out"):
        ppo.main(configure(PPOConfig, "vortex-v0", out=str(run), resume=True, seed=7, **{**PPO, "frames": 600}))
    assert snapshot(run) == logs
    nowhere = tmp_path / "nowhere"
    with pytest.raises(BadRun, match="no checkpoint to resume \\(missing\\)"):
        ppo.main(configure(PPOConfig, "vortex-v0", out=str(nowhere), resume=True, **PPO))
    assert not nowhere.exists(), "a refused run created its directory"


STATE_KEYS = ["state.u", "state.u_prev", "state.a", "count", "rng", "action_rng", "params", "extra"]


@settings(max_examples=120, deadline=None)
@given(
    key=st.sampled_from(STATE_KEYS),
    value=st.one_of(
        JUNK,
        st.sampled_from([1e300, -1e39, float("nan"), 3.0]).map(lambda v: torch.full((2, 500), v, dtype=torch.float64)),
        st.lists(st.integers(1, 600), min_size=1, max_size=3).map(lambda shape: torch.zeros(shape)),
        st.integers(-3, 300).map(lambda n: torch.full((2,), n)),
        st.fixed_dictionaries({"amp": st.floats(allow_nan=True)}),
    ),
    strict=st.booleans(),
)
def test_any_forged_state_dict_entry_is_one_clear_error_or_a_sound_env(key, value, strict):
    env = beacon_torch.make("burgers-v0", 2, seed=1)
    env.reset()
    saved = env.state_dict()
    saved[key] = value
    fresh = beacon_torch.make("burgers-v0", 2, seed=1)
    try:
        fresh.load_state_dict(saved, strict=strict)
    except (ValueError, TypeError, KeyError) as err:
        assert "burgers-v0" in str(err) and "\n" not in str(err)
    else:
        fresh.reset() if fresh._state is None else None
        obs, reward, _, _ = fresh.step_members(fresh.null_action())
        assert torch.isfinite(obs).all() and torch.isfinite(reward).all()


def test_a_run_whose_output_appears_while_it_runs_replaces_nothing(tmp_path, monkeypatch, capsys):
    """Two runs into one --out: the second, refused at the end because the first wrote
    there meanwhile, leaves the first's files as they were."""
    from beacon_torch import episodes

    monkeypatch.chdir(tmp_path)
    real = episodes.episode

    def meanwhile(env, policy, **kwargs):
        out = tmp_path / "out"
        if not (out / "run.png").exists():
            (out / "run.png").write_text("the first run's")
            (out / "scores.json").write_text("the first run's")
        return real(env, policy, **kwargs)

    monkeypatch.setattr(episodes, "episode", meanwhile)
    assert cli(["run", "vortex-v0", "--num-envs", "2", "--out", "out"]) == 2
    assert "exists and is not overwritten" in capsys.readouterr().err
    assert (tmp_path / "out" / "run.png").read_text() == "the first run's"
    assert (tmp_path / "out" / "scores.json").read_text() == "the first run's"


def test_values_are_checked_after_their_cast_to_the_envs_dtype():
    env = beacon_torch.make("burgers-v0", 2)  # float32
    env.reset()
    saved = env.state_dict()
    big = {**saved, "state.u": saved["state.u"].double().fill_(1e300)}
    with pytest.raises(ValueError, match="state.u has values that are not finite in torch.float32"):
        env.load_state_dict(big)
    with pytest.raises(ValueError, match="not finite in torch.float32"):
        env.set_state({k: v.double().fill_(1e39) for k, v in env.state._asdict().items()})
    assert torch.isfinite(env.observation).all()
    with pytest.raises(
        ValueError, match="keeps the dtype it was made with \\(torch.float32\\); make\\(..., dtype='float64'"
    ):
        env.to(torch.float64)
    assert env.to(torch.float32) is env and env.to("cpu", torch.float32) is env


def test_state_dicts_and_states_are_checked_for_what_they_claim():
    env = beacon_torch.make("burgers-v0", 2, seed=1)
    # never reset: the shapes come from the start it would take, its generator untouched
    rng = env.rng.get_state()
    with pytest.raises(ValueError, match="state.u must have shape \\(2, 500\\)"):
        env.set_state({k: torch.zeros(2, 3) for k in env.physics.state_type._fields})
    assert torch.equal(env.rng.get_state(), rng)
    with pytest.raises(
        KeyError, match="lacks \\['state.u', 'state.u_prev', 'state.a', 'rng', 'action_rng', 'params'\\]"
    ):
        env.load_state_dict({}, strict=True)
    env.load_state_dict({}, strict=False)  # nothing to load, said so by strict=False
    env.reset()
    saved = env.state_dict()
    other = beacon_torch.make("burgers-v0", 2, amp=0.2)
    with pytest.raises(ValueError, match="saved by an env with other parameters \\(amp = "):
        other.load_state_dict(saved)
    same = beacon_torch.make("burgers-v0", 2, seed=9)
    same.load_state_dict(saved)
    assert torch.equal(same.observation, env.observation)


def test_an_env_whose_observe_disagrees_with_its_sizes_is_named(tmp_path):
    from beacon_torch.envs.lorenz import CARD, LorenzPhysics
    from beacon_torch.testing import ConformanceError, check_flow_env

    class NarrowPhysics(LorenzPhysics):
        def observe(self, p, state):
            return super().observe(p, state)[:, :3]

    beacon_torch.register("narrow-lorenz-v0", NarrowPhysics, CARD)
    try:
        with pytest.raises(
            ValueError, match="observe\\(\\) returned shape \\(2, 3\\), the observation spec says \\(2, 6\\)"
        ):
            beacon_torch.make("narrow-lorenz-v0", 2).reset()
        with pytest.raises(
            ConformanceError, match="narrow-lorenz-v0: specs: the env raised ValueError: narrow-lorenz-v0"
        ):
            check_flow_env("narrow-lorenz-v0", checks=["specs"])
        with pytest.raises(ValueError, match="its default parameters: .*'rho'"):
            beacon_torch.register("bad-lorenz-v0", LorenzPhysics, rho=-5.0)
        with pytest.raises(TypeError, match="default differentiable must be True or False"):
            beacon_torch.register("bad-lorenz-v1", LorenzPhysics, differentiable="yes")
        assert "bad-lorenz-v0" not in beacon_torch.registry.ENVS
    finally:
        beacon_torch.registry.ENVS.pop("narrow-lorenz-v0", None)


def test_small_misuses_are_clear_errors():
    import gymnasium

    import beacon_torch.gym
    from beacon_torch.sb3 import BeaconVecEnv

    env = beacon_torch.make("lorenz-v0", 2)
    with pytest.raises(ValueError, match="rollout needs a positive number of steps, got 0"):
        env.rollout(0)
    venv = gymnasium.make_vec("beacon/lorenz-v0", num_envs=3)
    venv.reset()
    for mask, words in (([True, False], "2 values of dtype bool"), ([0, 5, 1], "3 values of dtype int64")):
        with pytest.raises(ValueError, match=f"one bool per copy \\(3\\), got {words}"):
            venv.reset(options={"reset_mask": mask})
    sb3 = BeaconVecEnv("lorenz-v0", n_envs=2)
    sb3.reset()
    sb3.close()
    with pytest.raises(RuntimeError, match="closed env"):
        sb3.step(np.zeros(2, dtype=np.int64))
    with pytest.raises(ValueError, match="members need about .* at most about"):
        beacon_torch.make("sloshing-v0", 2**24)
    # a float32 policy given float64 observations
    policy = pretrained.load("ppo/lorenz-v0")
    with pytest.raises(TypeError, match="computes in torch.float32 and was given torch.float64 observations"):
        policy(beacon_torch.make("lorenz-v0", 2, dtype="float64").reset())


def test_a_differentiable_batch_whose_every_member_blows_up_still_backpropagates():
    env = beacon_torch.make("sloshing-v0", 2, dtype="float64", differentiable=True, amp=[1e6, 1e6])
    env.reset()
    w = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)
    total = 0.0
    for _ in range(5):
        _, reward, terminated, _ = env.step_members(torch.tanh(w * env.observation[:, :1]))
        total = total + reward.sum()
    assert terminated.all()
    (g,) = torch.autograd.grad(total, w)
    assert torch.isfinite(g)


def test_files_written_through_a_temporary_name_keep_the_umasks_permissions(tmp_path):
    old = os.umask(0o022)
    try:
        files.write_text(tmp_path / "a.txt", "x")
        files.create_file(tmp_path / "b.txt", lambda tmp: tmp.write_text("x"))
        assert (tmp_path / "a.txt").stat().st_mode & 0o777 == 0o644
        assert (tmp_path / "b.txt").stat().st_mode & 0o777 == 0o644
        # a name as long as a file system allows still has room for its temporary name
        long = tmp_path / ("n" * 250)
        files.write_text(long, "x")
        assert long.read_text() == "x"
    finally:
        os.umask(old)


def test_commands_refuse_bad_outputs_and_misuses_in_one_line(ppo_run, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)

    def one_line(argv, words, progress=False):
        assert cli(argv) == 2, argv
        err = capsys.readouterr().err
        lines = err.strip().splitlines()[-1:] if progress else err.strip().splitlines()
        assert words in lines[-1] and len(lines) == 1 and "Traceback" not in err, err

    one_line(["run", "vortex-v0", "--gif", "x.txt"], "an animation is a GIF file")
    one_line(["run", "vortex-v0", "--gif", "x.gif", "--gif-every", "-5"], "--gif-every must be a positive")
    assert not (tmp_path / "x.txt").exists() and not (tmp_path / "runs").exists()
    one_line(["bench", "--envs", "lorenz-v0", "--device", "meta", "--out", "b"], "device 'meta'")
    one_line(
        ["bench", "--envs", "lorenz-v0", "--num-envs", str(2**25), "--mode", "eager", "--out", "b2"],
        f"measuring lorenz-v0 at {2**25} members failed: ValueError: batch_size",
        progress=True,  # the line of the measurement started, then the error
    )
    run = copy_run(ppo_run, tmp_path / "run")
    log = run / "ppo" / "scalars" / "reward.csv"
    log.write_text(log.read_text() + "600,1e400\n")
    one_line(["plot", str(run), "--scalar", "reward", "--out", "p.png"], "a step and a finite value")
    for k, (change, words) in enumerate(
        (
            (dict(seeds=[{"eval": 10**400}]), "each with a finite 'eval' score"),
            (
                dict(uncontrolled=10**400),
                "'uncontrolled' must be a finite number of at most 1e+09, got an integer of 401",
            ),
            (dict(seeds=[{"eval": 1e308}] * 3), "each with a finite 'eval' score of at most 1e+09"),
        )
    ):
        file = tmp_path / f"summary-{k}.json"
        file.write_text(json.dumps(summary_of(**change)))
        one_line(["report", str(file), "--out", f"rep-{k}"], words)
    with pytest.raises(SystemExit) as exit_:
        reproduce.main(["train", "--envs", "lorenz-v0", "--set", "seed=5"])
    assert exit_.value.code == 2 and "--set seed: the driver sets it" in capsys.readouterr().err


@pytest.mark.parametrize(
    "change, words",
    [
        (dict(env="burgers-v0"), "observation statistics must have burgers-v0's"),
        ({"modules.actor": "wrong"}, "the actor's weights do not fit a stochastic_actor of width 64 on vortex-v0"),
        ({"obs_norm.loc": torch.zeros(3)}, "observation statistics must have vortex-v0's 8 observations"),
    ],
)
def test_eval_of_a_relabelled_or_reshaped_checkpoint_is_one_line(ppo_run, tmp_path, change, words, capsys):
    run = copy_run(ppo_run, tmp_path / "run")
    if change.get("modules.actor") == "wrong":
        state = torch.load(run / "checkpoint.pt", weights_only=True)
        key = next(k for k in state["modules"]["actor"] if k.endswith("weight"))
        state["modules"]["actor"][key] = torch.zeros(3, 3)
        torch.save(state, run / "checkpoint.pt")
    else:
        rewrite_checkpoint(run, **change)
    assert cli(["eval", str(run), "--no-gif", "--num-envs", "1"]) == 2
    err = capsys.readouterr().err
    assert words in err and "checkpoint.pt" in err and len(err.strip().splitlines()) == 1, err


def test_run_writes_its_scores_when_every_member_blows_up(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert cli(["run", "burgers-v0", "--num-envs", "2", "--param", "amp=100", "--out", "out"]) == 0
    scores = json.loads((tmp_path / "out" / "scores.json").read_text())
    assert scores["random"]["num_envs"] == 2 and (tmp_path / "out" / "run.png").stat().st_size > 1000


def test_a_full_disk_while_a_checkpoint_is_written_is_one_line_and_keeps_the_last(ppo_run, tmp_path):
    """A file-size limit stands for the full disk: torch's failed write is one line,
    status 2, and the checkpoint of before stays as it was."""
    run = copy_run(ppo_run, tmp_path / "run")
    before = (run / "checkpoint.pt").read_bytes()
    limited = (
        "import resource, runpy, signal, sys\n"
        "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000))\n"
        "sys.argv = ['ppo.py'] + sys.argv[1:]\n"
        f"runpy.run_path({str(ROOT / 'recipes' / 'ppo.py')!r}, run_name='__main__')\n"
    )
    args = ["--env", "vortex-v0", "--out", str(run), "--resume", "--frames", "600", "--n-rollout", "200"]
    args += ["--num-envs", "4", "--epochs", "1", "--no-progress", "--logger", "csv", "--no-compile"]
    done = subprocess.run([sys.executable, "-c", limited, *args], capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr
    assert "checkpoint.pt: could not be written" in done.stderr and "the previous file is kept" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert (run / "checkpoint.pt").read_bytes() == before


def test_list_into_a_closed_pipe_is_quiet():
    reader = subprocess.Popen(
        [sys.executable, "-m", "beacon_torch", "list"], stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    reader.stdout.readline()
    reader.stdout.close()
    err = reader.stderr.read().decode()
    assert reader.wait(timeout=120) == 0 and "Broken pipe" not in err and "Traceback" not in err, err
