"""What the recipes share: the training env with its transforms, network initialisation,
and the run directory (checkpoint, logger, progress bar)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import nn
from torchrl.envs import Compose, ObservationNorm, RewardSum, TransformedEnv
from torchrl.record.loggers import CSVLogger

import beacon_torch

NORM_STEPS = 16  # random steps that set the observation normalisation


def make_env(env_id: str, num_envs: int, *, device="cpu", seed: int = 0, norm: dict | None = None, **env_kwargs) -> TransformedEnv:
    """The batched env with observation normalisation and episode returns; ``norm`` (a
    saved ``ObservationNorm`` state) instead of statistics from a random rollout."""
    base = beacon_torch.make(env_id, num_envs, device=device, seed=seed, **env_kwargs)
    if isinstance(base.observation_key, tuple):
        raise ValueError(f"{env_id}: the recipes handle single-agent envs; multi-agent layouts are not supported yet")
    loc, scale = (norm["loc"], norm["scale"]) if norm is not None else (None, None)
    env = TransformedEnv(base, Compose(ObservationNorm(loc=loc, scale=scale, in_keys=["observation"], standard_normal=True), RewardSum()))
    if norm is None:
        env.transform[0].init_stats(num_iter=NORM_STEPS, reduce_dim=(0, 1), cat_dim=1)
    return env


def orthogonal(module: nn.Module, gain: float = 2**0.5) -> nn.Module:
    for layer in module.modules():
        if isinstance(layer, nn.Linear):
            nn.init.orthogonal_(layer.weight, gain)
            nn.init.zeros_(layer.bias)
    return module


def check_action_space(env_id: str, algo: str) -> None:
    """TD3 needs continuous actions, DQN discrete ones: a clear error otherwise."""
    discrete = beacon_torch.registry.ENVS[env_id].discrete
    if algo == "td3" and discrete:
        raise ValueError(f"td3 needs continuous actions; {env_id} has discrete ones (use ppo or dqn)")
    if algo == "dqn" and not discrete:
        raise ValueError(f"dqn needs discrete actions; {env_id} has continuous ones (use ppo or td3)")


def load_checkpoint(run: str | Path) -> dict:
    """The ``checkpoint.pt`` of a run folder, with a clear error for a bad file."""
    path = Path(run) / "checkpoint.pt"
    try:
        return torch.load(path, weights_only=False, map_location="cpu")
    except Exception as err:  # a missing, truncated or foreign file
        raise FileNotFoundError(f"{path}: unreadable checkpoint ({err})") from None


class Run:
    """A run directory: ``checkpoint.pt``, the CSV logs ``<algo>/scalars/*.csv`` and
    the progress bar. ``state`` is the loaded checkpoint when resuming, else None."""

    def __init__(self, out: str | Path, env_id: str, algo: str, total: int, *, resume: bool, progress: bool) -> None:
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
        self.logger = CSVLogger(exp_name=algo, log_dir=str(self.out))
        self.last: dict[str, Any] = {"frames": self.frames}
        self.bar = None
        if progress and total > self.frames:
            from tqdm.auto import tqdm

            self.bar = tqdm(total=total, initial=self.frames, unit="frames", desc=f"{algo} {env_id}")

    def log(self, collected: int, values: dict[str, float]) -> None:
        self.frames += collected
        self.last = {"frames": self.frames, **values}
        for name, value in values.items():
            self.logger.log_scalar(name, value, step=self.frames)
        if self.bar is not None:
            self.bar.update(collected)
            self.bar.set_postfix({k: f"{v:.4g}" for k, v in values.items()})

    def save(self, **state: Any) -> None:
        torch.save({"env": self.env_id, "algo": self.algo, "frames": self.frames, **state}, self.path)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def start(env_id: str, algo: str, cfg, out, *, seed: int, device, resume: bool, progress: bool) -> tuple[Run, TransformedEnv]:
    """The run directory (resumed or new) and the seeded training env of a recipe."""
    check_action_space(env_id, algo)
    run = Run(out, env_id, algo, cfg.frames, resume=resume, progress=progress)
    torch.manual_seed(seed)
    norm = run.state["obs_norm"] if run.state else None
    return run, make_env(env_id, cfg.num_envs, device=device, seed=seed, norm=norm)


def episode_values(data, reward_key=("next", "reward")) -> dict[str, float]:
    """The mean reward of a collected batch and the mean score of the episodes that
    ended in it (``RewardSum``'s ``episode_reward``)."""
    done = data["next", "done"][..., 0]
    values = {"reward": data[reward_key].float().mean().item()}
    if done.any():
        values["episode_score"] = data["next", "episode_reward"][..., 0][done].float().mean().item()
    return values


def off_policy_train(run: Run, env, policy, cfg, update, save, *, device="cpu", checkpoint_every: int = 10, on_batch=None) -> dict:
    """The loop TD3 and DQN share: a ``Collector`` with ``policy`` (exploration
    included) fills a ``ReplayBuffer`` (saved with the checkpoint, so that a resumed run
    keeps what it collected); after each batch ``update(sample)`` runs
    ``cfg.updates_per_batch`` times and returns the logged loss. ``on_batch(frames)``
    anneals the exploration."""
    from torchrl.collectors import Collector
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
    collector = Collector(
        env,
        policy,
        frames_per_batch=cfg.frames_per_batch,
        total_frames=remaining,
        init_random_frames=init_random,
        device=device,
        auto_register_policy_transforms=False,
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
