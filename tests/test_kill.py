"""``kill -9`` at any moment of a training loses at most the work since the last
checkpoint and never corrupts the run: killed in a subprocess at several points, then
resumed, the run reaches its total with whole logs and a whole replay buffer."""

import csv
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from beacon_torch.training.config import PPOConfig, TD3Config, configure
from beacon_torch.training.run import load_checkpoint

from conftest import recipe

ROOT = Path(__file__).resolve().parents[1]

# the subprocess: a short training that kills itself at the n-th time it passes `point`
DRIVER = textwrap.dedent(
    """
    import importlib.util, os, signal, sys
    import torch
    from torchrl.data import ReplayBuffer
    from beacon_torch.training import config

    def load(algo):
        spec = importlib.util.spec_from_file_location("recipe_" + algo, {recipes!r} + "/" + algo + ".py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    ppo, td3 = load("ppo"), load("td3")
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
    elif point == "buffer-written":  # the new buffer folder written, not swapped in
        wrap(ReplayBuffer, "dumps", after=True)
    elif point == "between-renames":  # the old buffer moved aside, the new one not in place
        wrap(os, "replace", when=lambda src, dst: str(src).endswith("buffer.partial"))
    elif point == "before-checkpoint":  # the buffer swapped, the checkpoint not yet replaced
        wrap(os, "replace", when=lambda src, dst: str(src).endswith(".pt.partial"))
    settings = dict({settings})
    cls, recipe = (config.PPOConfig, ppo) if algo == "ppo" else (config.TD3Config, td3)
    cfg = config.configure(cls, "vortex-v0", out=out, progress=False, logger="csv", checkpoint_every=1, **settings)
    recipe.main(cfg)
    """
)
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
        ("td3", "between-renames", 2),
        ("td3", "before-checkpoint", 3),
    ],
)
def test_a_killed_training_resumes_whole(algo, point, nth, tmp_path):
    settings = PPO if algo == "ppo" else TD3
    driver = tmp_path / "driver.py"
    driver.write_text(DRIVER.format(recipes=str(ROOT / "recipes"), settings=settings))
    run = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, str(driver), algo, point, str(nth), str(run)], cwd=ROOT, capture_output=True, text=True
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    saved = load_checkpoint(run)
    assert 0 < saved["frames"] < settings["frames"]
    # the resume: from the checkpoint to the total, logs continued, the buffer whole
    cls, script = (PPOConfig, recipe("ppo")) if algo == "ppo" else (TD3Config, recipe("td3"))
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
        buffer.loads(run / "buffer")
        assert len(buffer) == settings["frames"] == load_checkpoint(run)["counters"]["buffer_len"]
        obs = buffer[: len(buffer)]["observation"]
        assert torch.isfinite(obs).all() and (obs.abs().sum(-1) > 0).all(), "zeroed transitions in the buffer"
        assert not (run / "buffer.old").exists() and not list(run.glob("*partial*")), (
            "a stop left a partial write behind"
        )


def test_a_truncated_replay_buffer_is_reported_not_trained_on(tmp_path):
    td3 = recipe("td3")

    cfg = dict(TD3, frames=128)
    td3.main(configure(TD3Config, "vortex-v0", out=str(tmp_path), progress=False, logger="csv", **cfg))
    memmap = tmp_path / "buffer" / "storage" / "observation.memmap"
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
