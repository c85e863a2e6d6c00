import contextlib
import os
from pathlib import Path

import pytest
import torch

import beacon_torch

# the adapters compile by default; the behaviour tests run them eagerly (compiled and
# eager steps are compared per env in test_compile.py, and the default is tested there)
os.environ["BEACON_TORCH_COMPILE"] = "0"

if os.environ.get("PYTEST_XDIST_WORKER"):
    # one intra-op thread per worker: two workers with two threads each on two cores
    # slow the matrix-heavy 2-D solvers down several times
    torch.set_num_threads(1)
    # and the recipes and commands, which would take the measured default
    os.environ["BEACON_TORCH_THREADS"] = "1"

ENVS = beacon_torch.registry.ENVS
# FluidGym's medium and hard levels are the easy level's code at other Rayleigh numbers
# and time steps: the behaviour tests run on the easy ones, test_rbc2d.py steps them all
ALL_ENVS = [e for e in beacon_torch.list_envs() if not e.startswith(("rbc2d-medium-", "rbc2d-hard-"))]
CONTINUOUS_ENVS = [e for e in ALL_ENVS if not ENVS[e].physics.discrete]
DISCRETE_ENVS = [e for e in ALL_ENVS if ENVS[e].physics.discrete]
DETERMINISTIC_ENVS = [e for e in ALL_ENVS if ENVS[e].physics.deterministic]
# the 2-D cavities take tens of seconds an episode: their whole episodes are run by
# test_scores.py, the behaviour tests that need whole episodes run on the others
EXPENSIVE_ENVS = {e for e in ALL_ENVS if ENVS[e].card.costly}
CHEAP_ENVS = [e for e in ALL_ENVS if e not in EXPENSIVE_ENVS]
# the cheaper settings each env declares for the behaviour tests run on every env (the
# published numbers are checked with the defaults in test_scores.py)
FAST = {e: ENVS[e].card.test_settings for e in ALL_ENVS}


ROOT = Path(__file__).resolve().parents[1]


def make(env_id, num_envs=1, **kwargs):
    return beacon_torch.make(env_id, num_envs, **{**FAST[env_id], **kwargs})


@pytest.fixture(params=ALL_ENVS)
def env_id(request):
    return request.param


@pytest.fixture(params=CHEAP_ENVS)
def cheap_env_id(request):
    return request.param


def run_actions(env, actions):
    """Step ``env`` from a reset through ``actions`` (a list of action batches);
    return the stacked observations and rewards."""
    td = env.reset()
    obs, rew = [], []
    for a in actions:
        td[env.action_key] = a
        td = env.step(td)["next"]
        obs.append(td[env.observation_key].clone())
        rew.append(td[env.reward_key].clone())
    return torch.stack(obs, 1), torch.stack(rew, 1)


def seconds(item) -> float:
    """The time a test is marked to take (``@pytest.mark.slow(seconds=...)``, measured
    on one core of this project's machines); 0 for the unmarked ones."""
    mark = item.get_closest_marker("slow")
    return mark.kwargs.get("seconds", 1.0) if mark is not None else 0.0


def pytest_collection_modifyitems(items):
    # The longest tests start first, so that no episode of minutes runs alone at the end
    # while the other worker idles: xdist hands the first tests out in turn, and the
    # longest one (the mixing episode) holds one worker while the other runs the next
    items.sort(key=seconds, reverse=True)


# a run of each kind in seconds, for the tests of run directories
PPO = dict(frames=400, n_rollout=200, num_envs=4, epochs=1, progress=False, logger="csv")
TD3 = dict(
    frames=256,
    frames_per_batch=64,
    num_envs=4,
    updates_per_batch=4,
    init_random_frames=64,
    batch_size=32,
    hidden=32,
    progress=False,
    logger="csv",
)


@pytest.fixture(scope="module")
def ppo_run(tmp_path_factory):
    """A PPO run directory on vortex-v0 (no episode ends in it), for a module's tests
    to copy."""
    from beacon_torch.training.config import PPOConfig, configure

    run = tmp_path_factory.mktemp("ppo") / "run"
    from recipes import ppo

    ppo.main(configure(PPOConfig, "vortex-v0", out=str(run), **PPO))
    return run


@pytest.fixture(scope="module")
def td3_run(tmp_path_factory):
    """A TD3 run directory on vortex-v0 with its replay buffer."""
    from beacon_torch.training.config import TD3Config, configure

    run = tmp_path_factory.mktemp("td3") / "run"
    from recipes import td3

    td3.main(configure(TD3Config, "vortex-v0", out=str(run), **TD3))
    return run


def copy_run(run: Path, to: Path) -> Path:
    import shutil

    shutil.copytree(run, to)
    return to


@pytest.fixture(scope="module")
def short_lorenz():
    """``short-lorenz-v0``, registered while a module's tests run: lorenz-v0 with
    episodes of 25 actions, so that the runs of tests that summarise, evaluate and
    publish see episodes end in a fraction of a second."""
    import gymnasium

    from beacon_torch import registry
    from beacon_torch.envs.lorenz import CARD, LorenzPhysics

    class ShortLorenz(LorenzPhysics):
        episode_length = 25

    beacon_torch.register("short-lorenz-v0", ShortLorenz, CARD, base="lorenz-v0")
    yield "short-lorenz-v0"
    for table in (registry.ENVS, registry.ORIGIN):
        table.pop("short-lorenz-v0", None)
    gymnasium.registry.pop("beacon/short-lorenz-v0", None)


def random_policy_file(path: Path, env_id: str, params: dict, hidden: int = 16) -> Path:
    """A policy file (``pretrained.export``'s format) of a deterministic actor of
    ``env_id`` with ``params``, its weights drawn at random but reproducibly, large
    enough that its actions move."""
    from beacon_torch import training
    from beacon_torch.training import networks

    env = training.env.make_env(env_id, 1, norm_steps=0, params=params)
    policy = networks.policy(env, "deterministic_actor", hidden)
    with torch.no_grad():
        for p in policy.parameters():
            p.normal_(0.0, 0.3, generator=torch.Generator().manual_seed(p.numel()))
    record = {"env": env_id, "algo": "td3", "network": "deterministic_actor", "hidden": hidden}
    torch.save({**record, "params": params, "weights": policy.state_dict()}, path)
    return path


@contextlib.contextmanager
def lock_held_elsewhere(folder: Path):
    """``folder``'s lock held by another process while the block runs (a run or a
    planner writing there); the holder is killed after, which drops its lock."""
    import subprocess
    import sys

    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            f"from beacon_torch.files import Lock; import time; lock = Lock({str(folder)!r}); "
            f"print('held', flush=True); time.sleep(60)",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        yield
    finally:
        holder.kill()
        holder.wait()
