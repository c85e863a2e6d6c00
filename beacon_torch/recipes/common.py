"""What the recipes share: the training env with its transforms, network initialisation,
and the run directory (checkpoint, logger, progress bar)."""

from __future__ import annotations

import time
from functools import partial
from importlib.util import find_spec
from pathlib import Path
from typing import Any

import torch
from torch import nn
from torchrl.envs import ClipTransform, Compose, ObservationNorm, RewardSum, TransformedEnv
from torchrl.record.loggers import CSVLogger

import beacon_torch
from beacon_torch.recipes.config import NORM_STEPS



def sibling(key: str | tuple[str, ...], name: str) -> str | tuple[str, ...]:
    """The entry ``name`` next to ``key``: ``("agents", "reward")`` -> ``("agents", name)``."""
    return (*key[:-1], name) if isinstance(key, tuple) else name


def make_env(env_id: str, num_envs: int, *, device="cpu", seed: int = 0, norm: dict | None = None, norm_steps: int = NORM_STEPS, **env_kwargs) -> TransformedEnv:
    """The batched env with observation normalisation and episode returns; the
    statistics come from ``norm`` (a saved ``ObservationNorm`` state) or else from a
    rollout of ``norm_steps`` random actions. In a multi-agent layout
    (shkadov-separable-v0) the statistics are shared by the agents, as the policy is,
    and the episode returns are per agent, next to their rewards. Continuous actions
    reach the env clipped to its box."""
    base = beacon_torch.make(env_id, num_envs, device=device, seed=seed, **env_kwargs)
    obs, reward = base.observation_key, base.reward_key
    loc, scale = (norm["loc"], norm["scale"]) if norm is not None else (None, None)
    transforms = [ObservationNorm(loc=loc, scale=scale, in_keys=[obs], standard_normal=True), RewardSum(in_keys=[reward], out_keys=[sibling(reward, "episode_reward")])]
    if not base.discrete:
        # a policy's sample may leave the box: the env gets it clipped, the data keeps it
        low, high = base.full_action_spec[base.action_key].space.low.unique(), base.full_action_spec[base.action_key].space.high.unique()
        transforms.append(ClipTransform(in_keys_inv=[base.action_key], low=low.item(), high=high.item()))
    env = TransformedEnv(base, Compose(*transforms))
    if norm is None:
        agent_dims = base.observation_spec[obs].ndim - base.batch_dims - 1
        env.transform[0].init_stats(num_iter=norm_steps, reduce_dim=tuple(range(2 + agent_dims)), cat_dim=1)
    return env


def make_collector(
    env_id: str, env: TransformedEnv, policy, *, frames_per_batch: int, total_frames: int, collectors: int = 1, ray: str | None = None, seed: int = 0, device="cpu", init_random_frames: int = 0
):
    """A TorchRL collector over the batched ``env``: a ``Collector`` in this process;
    with ``collectors`` > 1 a ``MultiSyncCollector`` of that many processes; with
    ``ray`` (a Ray cluster address, or "local" for a Ray instance on this machine) a
    synchronous ``RayCollector`` of ``collectors`` Ray actors. Each remote collector
    steps its own batched env of the same size (seeded apart, with ``env``'s observation
    normalisation), and their batches are stacked into one ``[collectors, members,
    time]`` batch."""
    from torchrl.collectors import Collector, MultiSyncCollector

    if collectors < 1:
        raise ValueError(f"collectors must be a positive integer, got {collectors}")
    kwargs = dict(frames_per_batch=frames_per_batch, total_frames=total_frames, init_random_frames=init_random_frames)
    local = dict(device=device, auto_register_policy_transforms=False)
    if collectors == 1 and ray is None:
        return Collector(env, policy, **kwargs, **local)
    members = env.batch_size.numel()
    if frames_per_batch % (collectors * members):
        raise ValueError(f"the collected batch ({frames_per_batch}) must be a multiple of collectors x members ({collectors} x {members})")
    base = env.base_env
    makers = [
        partial(make_env, env_id, members, device=device, seed=seed + 7919 * (k + 1), norm=env.transform[0].state_dict(), dtype=base.dtype, compile=base.compile_options or False)
        for k in range(collectors)
    ]
    if ray is None:
        return MultiSyncCollector(makers, policy, cat_results="stack", **kwargs, **local)
    if find_spec("ray") is None:
        raise ValueError("collection on Ray needs the ray package (pip install 'beacon-torch[ray]')")
    from torchrl.collectors.distributed import RayCollector

    init = {"address": None if ray == "local" else ray, "ignore_reinit_error": True, "log_to_driver": False}
    if ray == "local":
        init["num_cpus"] = collectors
    return RayCollector(
        makers,
        policy,
        **kwargs,
        num_collectors=collectors,
        sync=True,
        ray_init_config=init,
        remote_configs={"num_cpus": 1, "memory": 2 * 1024**3},
        collector_kwargs=local,
        update_after_each_batch=True,
    )


def orthogonal(module: nn.Module, gain: float = 2**0.5) -> nn.Module:
    for layer in module.modules():
        if isinstance(layer, nn.Linear):
            nn.init.orthogonal_(layer.weight, gain)
            nn.init.zeros_(layer.bias)
    return module


def check_action_space(env_id: str, algo: str) -> None:
    """TD3 and gradient-based control need continuous actions, DQN discrete ones: a
    clear error otherwise."""
    discrete = beacon_torch.registry.ENVS[env_id].discrete
    if algo in ("td3", "grad") and discrete:
        raise ValueError(f"{algo} needs continuous actions; {env_id} has discrete ones (use ppo or dqn)")
    if algo == "dqn" and not discrete:
        raise ValueError(f"dqn needs discrete actions; {env_id} has continuous ones (use ppo or td3)")


def load_checkpoint(run: str | Path) -> dict:
    """The ``checkpoint.pt`` of a run folder, with a clear error for a bad file."""
    path = Path(run) / "checkpoint.pt"
    try:
        return torch.load(path, weights_only=False, map_location="cpu")
    except Exception as err:  # a missing, truncated or foreign file
        raise FileNotFoundError(f"{path}: unreadable checkpoint ({err})") from None


def tensorboard_installed() -> bool:
    return find_spec("tensorboard") is not None


class Run:
    """A run directory: ``checkpoint.pt``, the CSV logs ``<algo>/scalars/*.csv`` (what
    ``plot`` and ``eval`` read), TensorBoard event files in ``<algo>/`` (``tensorboard``:
    True, or None for "when the package is installed") and the progress bar. ``state``
    is the loaded checkpoint when resuming, else None."""

    def __init__(self, out: str | Path, env_id: str, algo: str, total: int, *, resume: bool, progress: bool, tensorboard: bool | None = None) -> None:
        self.out = Path(out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.path = self.out / "checkpoint.pt"
        self.env_id, self.algo = env_id, algo
        self.state: dict | None = None
        if resume:
            if not self.path.is_file():
                raise FileNotFoundError(f"no checkpoint to resume in {self.out}")
            self.state = load_checkpoint(self.out)
            if self.state["env"] != env_id or self.state["algo"] != algo:
                raise ValueError(f"{self.out} holds a {self.state['algo']} run on {self.state['env']}, not {algo} on {env_id}")
        self.frames = self.state["frames"] if self.state else 0
        # training wall time, carried over resumes, so that results can state it
        self.elapsed = self.state.get("elapsed", 0.0) if self.state else 0.0
        self._since = time.perf_counter()
        self.loggers = [CSVLogger(exp_name=algo, log_dir=str(self.out))]
        if tensorboard is None:
            tensorboard = tensorboard_installed()
        if tensorboard:
            if not tensorboard_installed():
                raise ValueError("TensorBoard logging needs the tensorboard package (pip install tensorboard)")
            from torchrl.record.loggers import TensorboardLogger

            self.loggers.append(TensorboardLogger(exp_name=algo, log_dir=str(self.out)))
        self.last: dict[str, Any] = {"frames": self.frames}
        self.bar = None
        if progress and total > self.frames:
            from tqdm.auto import tqdm

            self.bar = tqdm(total=total, initial=self.frames, unit="frames", desc=f"{algo} {env_id}")

    def seconds(self) -> float:
        return self.elapsed + time.perf_counter() - self._since

    def log(self, collected: int, values: dict[str, float]) -> None:
        self.frames += collected
        self.last = {"frames": self.frames, **values}
        for name, value in {**values, "wall_time": self.seconds()}.items():
            for logger in self.loggers:
                logger.log_scalar(name, value, step=self.frames)
        if self.bar is not None:
            self.bar.update(collected)
            self.bar.set_postfix({k: f"{v:.4g}" for k, v in values.items()})

    def save(self, **state: Any) -> None:
        torch.save({"env": self.env_id, "algo": self.algo, "frames": self.frames, "elapsed": self.seconds(), **state}, self.path)

    def close(self) -> None:
        for logger in self.loggers[1:]:
            logger.experiment.flush()
        if self.bar is not None:
            self.bar.close()


def start(env_id: str, algo: str, cfg, out, *, seed: int, device, resume: bool, progress: bool, tensorboard: bool | None = None, **env_kwargs) -> tuple[Run, TransformedEnv]:
    """The run directory (resumed or new) and the seeded training env of a recipe
    (``env_kwargs`` go to the env, e.g. ``differentiable=True``)."""
    check_action_space(env_id, algo)
    if algo != "ppo" and isinstance(beacon_torch.registry.ENVS[env_id].observation_key, tuple):
        raise ValueError(f"{algo} trains single-agent layouts; {env_id} has one agent per jet (use ppo, or {env_id.replace('-separable', '')} for {algo})")
    run = Run(out, env_id, algo, cfg.frames, resume=resume, progress=progress, tensorboard=tensorboard)
    torch.manual_seed(seed)
    norm = run.state["obs_norm"] if run.state else None
    return run, make_env(env_id, cfg.num_envs, device=device, seed=seed, norm=norm, norm_steps=cfg.norm_steps, compile=cfg.compile, **env_kwargs)


def episode_values(data, reward_key: str | tuple[str, ...] = "reward") -> dict[str, float]:
    """The mean reward of a collected batch and the mean score of the episodes that
    ended in it (``RewardSum``'s ``episode_reward``); over the agents too where there
    are several (the team's score, as ``evaluate.scores`` counts it)."""
    done = data["next", "done"][..., 0]
    reward, score = data["next", reward_key], data["next", sibling(reward_key, "episode_reward")]
    values = {"reward": reward.float().mean().item()}
    if done.any():
        score = score.float().reshape(*done.shape, -1).mean(-1)  # the team's score
        values["episode_score"] = score[done].mean().item()
    return values


def off_policy_train(run: Run, env, policy, cfg, update, save, *, device="cpu", checkpoint_every: int = 10, on_batch=None, seed: int = 0, collectors: int = 1, ray: str | None = None) -> dict:
    """The loop TD3 and DQN share: a ``Collector`` with ``policy`` (exploration
    included) fills a ``ReplayBuffer`` (saved with the checkpoint, so that a resumed run
    keeps what it collected); after each batch ``update(sample)`` runs
    ``cfg.updates_per_batch`` times and returns the logged loss. ``on_batch(frames)``
    anneals the exploration."""
    from torchrl.data import LazyTensorStorage, ReplayBuffer

    buffer = ReplayBuffer(storage=LazyTensorStorage(cfg.buffer_size, device=device), batch_size=cfg.batch_size)
    buffer_dir = run.out / "buffer"
    if run.state is not None and buffer_dir.exists():
        buffer.loads(buffer_dir)
    remaining = cfg.frames - run.frames
    if remaining <= 0:
        return run.last

    def checkpoint() -> None:
        save()
        buffer.dumps(buffer_dir)

    init_random = max(0, cfg.init_random_frames - run.frames)
    collector = make_collector(
        run.env_id, env, policy, frames_per_batch=cfg.frames_per_batch, total_frames=remaining, init_random_frames=init_random, collectors=collectors, ray=ray, seed=seed, device=device
    )
    for batch, data in enumerate(collector):
        buffer.extend(data.reshape(-1))
        values = episode_values(data)
        if run.frames + data.numel() > cfg.init_random_frames or run.state is not None:
            for _ in range(cfg.updates_per_batch):
                values["loss"] = update(buffer.sample())
            collector.update_policy_weights_()
        run.log(data.numel(), values)
        if on_batch is not None:
            on_batch(data.numel())
        if (batch + 1) % checkpoint_every == 0:
            checkpoint()
    collector.shutdown()
    run.close()
    checkpoint()
    return run.last
