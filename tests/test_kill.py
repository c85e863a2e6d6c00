"""``kill -9`` at any moment of a training loses at most the work since the last
checkpoint and never corrupts the run: killed in a subprocess at several points, then
resumed, the run reaches its total with whole logs and a whole replay buffer."""

import csv
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from beacon_torch.training.config import PPOConfig, TD3Config, configure
from beacon_torch.training.run import buffer_folder, buffer_folders, load_checkpoint
from recipes import ppo, td3

ROOT = Path(__file__).resolve().parents[1]

# the driver imports the recipes as the tests do, from the repository's root
REPOSITORY = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}

# the subprocess: a short training that kills itself at the n-th time it passes `point`
DRIVER = textwrap.dedent(
    """
    import json, os, signal, sys
    import torch
    from torchrl.data import ReplayBuffer
    from beacon_torch.training import config
    from recipes import ppo, td3
    algo, point, nth, out = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
    seen = [0]

    def wrap(owner, name, when=lambda *a, **k: True, after=False):
        original = getattr(owner, name)

        def patched(*args, **kwargs):
            if when(*args, **kwargs):
                seen[0] += 1
                if seen[0] == nth and not after:
                    os.kill(os.getpid(), signal.SIGKILL)
                result = original(*args, **kwargs)
                if seen[0] == nth and after:
                    os.kill(os.getpid(), signal.SIGKILL)
                return result
            return original(*args, **kwargs)

        setattr(owner, name, patched)

    if point == "update":  # in the middle of a round of gradient steps
        wrap(torch.optim.Adam, "step")
    elif point == "buffer-written":  # the new buffer folder written under its temporary name
        wrap(ReplayBuffer, "dumps", after=True)
    elif point == "buffer-named":  # the new buffer folder under its name, no checkpoint naming it
        wrap(os, "replace", when=lambda src, dst: str(src).endswith("buffer.partial"), after=True)
    elif point == "checkpoint-written":  # the new checkpoint written, not yet in place
        wrap(os, "replace", when=lambda src, dst: str(src).endswith(".pt.partial"))
    elif point == "checkpoint-replaced":  # the new checkpoint in place, the old buffer not yet removed
        wrap(os, "replace", when=lambda src, dst: str(src).endswith(".pt.partial"), after=True)
    settings = dict({settings}, **{{k: json.loads(v) for k, v in (a.split("=") for a in sys.argv[5:])}})
    cls, recipe = (config.PPOConfig, ppo) if algo == "ppo" else (config.TD3Config, td3)
    cfg = config.configure(cls, "vortex-v0", out=out, progress=False, logger="csv", checkpoint_every=1, **settings)
    recipe.main(cfg)
    """
)
# a moment of a checkpoint's commit at which a stop is tested: (point, passes of the
# point before the stop)
MOMENTS = ["buffer-written", "buffer-named", "checkpoint-written", "checkpoint-replaced"]
PPO = dict(frames=800, n_rollout=200, num_envs=4, epochs=1, minibatches=2)
TD3 = dict(
    frames=384, frames_per_batch=64, num_envs=4, updates_per_batch=4, init_random_frames=64, batch_size=32, hidden=32
)


def steps(run: Path, algo: str) -> list[float]:
    with (run / algo / "scalars" / "reward.csv").open() as f:
        return [float(row[0]) for row in csv.reader(f)]


@pytest.mark.slow(seconds=40)
@pytest.mark.parametrize(
    "algo, point, nth",
    [
        ("ppo", "update", 5),  # the third round's update, after two checkpoints
        ("td3", "update", 9),
        ("td3", "buffer-written", 3),
        ("td3", "buffer-named", 2),
        ("td3", "checkpoint-written", 3),
        ("td3", "checkpoint-replaced", 2),
    ],
)
def test_a_killed_training_resumes_whole(algo, point, nth, tmp_path):
    settings = PPO if algo == "ppo" else TD3
    driver = tmp_path / "driver.py"
    driver.write_text(DRIVER.format(settings=settings))
    run = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, str(driver), algo, point, str(nth), str(run)],
        cwd=ROOT,
        env=REPOSITORY,
        capture_output=True,
        text=True,
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    saved = load_checkpoint(run)
    assert 0 < saved["frames"] < settings["frames"]
    # the resume: from the checkpoint to the total, logs continued, the buffer whole
    cls, script = (PPOConfig, ppo) if algo == "ppo" else (TD3Config, td3)
    last = script.main(
        configure(
            cls, "vortex-v0", out=str(run), resume=True, progress=False, logger="csv", checkpoint_every=1, **settings
        )
    )
    assert last["frames"] == settings["frames"] == load_checkpoint(run)["frames"]
    logged = steps(run, algo)
    assert logged == sorted(set(logged)) and logged[-1] == settings["frames"], logged
    if algo == "td3":
        from torchrl.data import LazyTensorStorage, ReplayBuffer

        buffer = ReplayBuffer(storage=LazyTensorStorage(settings["frames"]))
        buffer.loads(buffer_folder(run))
        assert len(buffer) == settings["frames"] == load_checkpoint(run)["counters"]["buffer_len"]
        obs = buffer[: len(buffer)]["observation"]
        assert torch.isfinite(obs).all() and (obs.abs().sum(-1) > 0).all(), "zeroed transitions in the buffer"
        assert buffer_folders(run) == [buffer_folder(run)] and not list(run.glob("*partial*")), (
            "a stop left a partial write behind"
        )


def resume_whole(run: Path, frames: int) -> None:
    """Resume the TD3 run in ``run`` to ``frames`` and check it ended whole: every
    transition in the buffer its checkpoint names, no other buffer folder left."""
    from torchrl.data import LazyTensorStorage, ReplayBuffer

    settings = {**TD3, "frames": frames}
    last = td3.main(
        configure(TD3Config, "vortex-v0", out=str(run), resume=True, progress=False, logger="csv", **settings)
    )
    saved = load_checkpoint(run)
    assert last["frames"] == frames == saved["frames"] == saved["counters"]["buffer_len"]
    buffer = ReplayBuffer(storage=LazyTensorStorage(frames))
    buffer.loads(buffer_folder(run))
    obs = buffer[: len(buffer)]["observation"]
    assert len(buffer) == frames and torch.isfinite(obs).all() and (obs.abs().sum(-1) > 0).all()
    assert buffer_folders(run) == [buffer_folder(run)], buffer_folders(run)


@pytest.fixture(scope="module")
def td3_256(tmp_path_factory):
    """A finished TD3 run of 256 transitions, checkpointed each round."""
    run = tmp_path_factory.mktemp("td3") / "run"
    settings = {**TD3, "frames": 256}
    td3.main(
        configure(TD3Config, "vortex-v0", out=str(run), progress=False, logger="csv", checkpoint_every=1, **settings)
    )
    return run


@pytest.mark.slow(seconds=30)
@pytest.mark.parametrize("point", MOMENTS)
def test_a_resume_to_more_frames_killed_at_any_moment_of_its_commit_stays_resumable(td3_256, point, tmp_path):
    """The resume grows the replay buffer (its capacity is the run's total), so its
    first save writes a buffer of another size than the checkpoint's: a stop at each
    moment of that save leaves a checkpoint and the buffer it names."""
    import shutil

    run = tmp_path / "run"
    shutil.copytree(td3_256, run)
    driver = tmp_path / "driver.py"
    driver.write_text(DRIVER.format(settings=TD3))
    args = [sys.executable, str(driver), "td3", point, "1", str(run), "frames=384", "resume=true"]
    proc = subprocess.run(args, cwd=ROOT, env=REPOSITORY, capture_output=True, text=True)
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    resume_whole(run, 384)


def test_a_resume_to_more_frames_on_a_full_disk_stays_resumable(td3_256, tmp_path):
    """A file-size limit stands for the full disk: the grown buffer's files fit under it
    and the checkpoint does not. The run stops in one line, and once there is room a
    resume goes on from the checkpoint of before and the buffer it names."""
    import shutil

    run = tmp_path / "run"
    shutil.copytree(td3_256, run)
    before = (run / "checkpoint.pt").read_bytes()
    limited = (
        "import resource, runpy, signal, sys\n"
        "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (30_000, 30_000))\n"
        "sys.argv = ['td3.py'] + sys.argv[1:]\n"
        f"runpy.run_path({str(ROOT / 'recipes' / 'td3.py')!r}, run_name='__main__')\n"
    )
    args = ["--env", "vortex-v0", "--out", str(run), "--resume", "--frames", "384", "--no-progress"]
    args += ["--logger", "csv", "--no-compile", "--checkpoint-every", "1"]
    for name, value in TD3.items():
        if name != "frames":
            args += [f"--{name.replace('_', '-')}", str(value)]
    done = subprocess.run([sys.executable, "-c", limited, *args], cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 2, done.stderr[-2000:]
    assert "checkpoint.pt: could not be written" in done.stderr and len(done.stderr.strip().splitlines()) == 1
    assert (run / "checkpoint.pt").read_bytes() == before
    resume_whole(run, 384)


def test_a_truncated_replay_buffer_is_reported_not_trained_on(tmp_path):
    from recipes import td3

    cfg = dict(TD3, frames=128)
    td3.main(configure(TD3Config, "vortex-v0", out=str(tmp_path), progress=False, logger="csv", **cfg))
    memmap = buffer_folder(tmp_path) / "storage" / "observation.memmap"
    memmap.write_bytes(memmap.read_bytes()[: memmap.stat().st_size // 2])
    with pytest.raises(ValueError, match="replay buffer is damaged \\(storage/observation.memmap"):
        td3.main(
            configure(
                TD3Config,
                "vortex-v0",
                out=str(tmp_path),
                resume=True,
                progress=False,
                logger="csv",
                **{**cfg, "frames": 192},
            )
        )
