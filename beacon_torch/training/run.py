"""A training run's directory: ``checkpoint.pt``, the CSV logs
``<algo>/scalars/<name>.csv`` (``step,value`` lines, the step being transitions
collected; what ``beacon-torch plot`` and ``eval`` read), TensorBoard event files in
``<algo>/`` when asked for, the replay buffer of off-policy runs (``buffer/``) and the
progress bar.

A checkpoint holds, next to the state of every module and optimiser of the run, the env
id, the algorithm, the settings, the observation normalisation and, by name and width,
the network of its policy: evaluation rebuilds the policy from the checkpoint alone.

A run killed at any moment (``kill -9``) loses at most the work since its last
checkpoint: the replay buffer is written to a new folder and swapped in, then the
checkpoint, which records how many transitions the buffer held, replaces the old one in
one step; a resume takes that many transitions from the buffer (an interrupted swap
leaves the previous folder, which is used) and drops the log lines written after the
checkpoint.
"""

from __future__ import annotations

import csv
import dataclasses
import os
import shutil
import time
from importlib.util import find_spec
from pathlib import Path
from typing import Any

import torch
from torchrl.record.loggers import CSVLogger

from beacon_torch.training.env import sibling

CHECKPOINT = "checkpoint.pt"


def load_checkpoint(run: str | Path) -> dict:
    """The checkpoint of a run folder, with a clear error for a bad file. It holds
    tensors, numbers, strings and containers of them only, read as such: a file whose
    pickle would run code is refused."""
    path = Path(run) / CHECKPOINT
    try:
        return torch.load(path, weights_only=True, map_location="cpu")
    except Exception as err:  # a missing, truncated or foreign file
        raise FileNotFoundError(f"{path}: unreadable checkpoint ({err})") from None


def seed_dirs(run: str | Path) -> list[Path]:
    """The per-seed folders of a run directory (the directory itself for one seed)."""
    run = Path(run)
    if (run / CHECKPOINT).is_file():
        return [run]
    found = sorted(p for p in run.glob("seed*") if (p / CHECKPOINT).is_file())
    if not found:
        raise FileNotFoundError(f"{run}: not a run directory (no {CHECKPOINT} in it or in seed* folders)")
    return found


def tensorboard_installed() -> bool:
    return find_spec("tensorboard") is not None


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


class Run:
    """The directory ``out`` of one training of ``algo`` on ``env_id`` towards ``total``
    transitions, new or (``resume``) continued from its checkpoint. ``tensorboard``:
    True, False, or None for "when the package is installed". ``settings`` (a dict) is
    recorded with every checkpoint, which :meth:`log` writes every ``checkpoint_every``
    rounds and :meth:`close` at the end."""

    def __init__(
        self,
        out: str | Path,
        env_id: str,
        algo: str,
        total: int,
        *,
        seed: int = 0,
        settings: dict | None = None,
        resume: bool = False,
        progress: bool = True,
        tensorboard: bool | None = None,
        checkpoint_every: int = 10,
    ) -> None:
        self.out = Path(out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.path = self.out / CHECKPOINT
        self.env_id, self.algo, self.total, self.seed = env_id, algo, total, seed
        self.settings = settings or {}
        self.checkpoint_every, self.rounds = checkpoint_every, 0
        self.state: dict | None = None
        if resume:
            if not self.path.is_file():
                raise FileNotFoundError(f"no checkpoint to resume in {self.out}")
            self.state = load_checkpoint(self.out)
            if self.state["env"] != env_id or self.state["algo"] != algo:
                raise ValueError(f"{self.out} holds a {self.state['algo']} run on {self.state['env']}, not {algo} on {env_id}")
        self.frames = self.state["frames"] if self.state else 0
        if self.state is not None:
            self._trim_logs()
        # what a recipe keeps over resumes (updates dropped, the buffer's size and files),
        # saved as it is
        self.counters: dict[str, Any] = dict(self.state.get("counters", {})) if self.state else {}
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

    def _trim_logs(self) -> None:
        """Drop the log lines of steps after the checkpoint (written before a stop), so
        that the resumed run's lines follow on without repeated or backward steps."""
        for file in (self.out / self.algo / "scalars").glob("*.csv"):
            with file.open() as f:
                rows = [row for row in csv.reader(f) if len(row) == 2 and float(row[0]) <= self.frames]
            with file.open("w", newline="") as f:
                csv.writer(f).writerows(rows)

    @classmethod
    def of(cls, settings) -> Run:
        """The run of a recipe's settings: a dataclass with ``out``, ``env``, ``algo``,
        ``frames``, ``seed``, ``resume``, ``progress``, ``tensorboard`` and
        ``checkpoint_every``, recorded whole with the checkpoints."""
        s = settings
        return cls(
            s.out, s.env, s.algo, s.frames, seed=s.seed, settings=dataclasses.asdict(s), resume=s.resume, progress=s.progress, tensorboard=s.tensorboard, checkpoint_every=s.checkpoint_every
        )

    @property
    def remaining(self) -> int:
        return self.total - self.frames

    @property
    def obs_norm(self) -> dict | None:
        """The saved observation statistics of a resumed run (None for a new one)."""
        return self.state["obs_norm"] if self.state else None

    def restore(self, buffer=None, **modules) -> None:
        """Load the saved state into ``modules`` (networks, losses, optimisers, by the
        names they were saved under) and ``buffer``; nothing for a new run."""
        if self.state is None:
            return
        for name, module in modules.items():
            module.load_state_dict(self.state["modules"][name])
        if buffer is None or "buffer_len" not in self.counters:
            return
        folder = self.out / "buffer"
        if not folder.exists() and (self.out / "buffer.old").exists():
            folder = self.out / "buffer.old"  # a stop between the two renames of a swap
        if not folder.exists():
            raise FileNotFoundError(f"{self.out}: the checkpoint refers to a replay buffer of {self.counters['buffer_len']} transitions, and there is none")
        for name, size in self.counters.get("buffer_files", {}).items():
            file = folder / name
            if not file.is_file() or file.stat().st_size != size:
                found = file.stat().st_size if file.is_file() else "no"
                raise ValueError(f"{folder}: the replay buffer is damaged ({name}: {found} bytes, {size} when saved); resume from a copy of the run or start it again")
        if any(folder.rglob("*.pkl")):
            # TorchRL unpickles these when it loads a buffer: code could run
            raise ValueError(f"{folder}: a replay buffer folder with pickle files is refused (loading it could run code); ours hold tensors and JSON only")
        # the transitions the checkpoint counted, oldest first (the buffer may hold more:
        # a stop between its save and the checkpoint's), into a buffer of the resumed size
        saved = type(buffer)(storage=type(buffer.storage)(self.counters["buffer_capacity"], device=buffer.storage.device))
        saved.loads(folder)
        n = self.counters["buffer_len"]
        if len(saved) < n:
            raise ValueError(f"{folder}: the replay buffer holds {len(saved)} transitions, the checkpoint counted {n}: it is damaged")
        if n:
            buffer.extend(saved[max(0, n - buffer.storage.max_size) : n])

    def seconds(self) -> float:
        return self.elapsed + time.perf_counter() - self._since

    def log(self, collected: int, values: dict[str, float], save=None) -> None:
        """Count and log one round of ``collected`` transitions; ``save()`` writes the
        checkpoint, called every ``checkpoint_every`` rounds."""
        self.frames += collected
        self.rounds += 1
        self.last = {"frames": self.frames, **values}
        for name, value in {**values, "wall_time": self.seconds()}.items():
            for logger in self.loggers:
                logger.log_scalar(name, value, step=self.frames)
        if self.bar is not None:
            self.bar.update(collected)
            self.bar.set_postfix({k: f"{v:.4g}" for k, v in values.items()})
        if save is not None and self.rounds % self.checkpoint_every == 0:
            save()

    def save(self, env, policy: tuple[str, int, torch.nn.Module], buffer=None, **modules) -> None:
        """Write the checkpoint: ``policy`` as (network name, width, module), the other
        ``modules`` by name, the observation normalisation of the training ``env`` and,
        for off-policy runs, the ``buffer``. The file is replaced in one step, so a run
        stopped while saving keeps its previous checkpoint."""
        network, hidden, actor = policy
        if buffer is not None:
            self._save_buffer(buffer)
        state = {
            "env": self.env_id,
            "algo": self.algo,
            "frames": self.frames,
            "elapsed": self.seconds(),
            "seed": self.seed,
            "config": self.settings,
            "policy": {"network": network, "hidden": hidden},
            "counters": self.counters,
            "obs_norm": env.transform[0].state_dict(),
            "modules": {"actor": actor.state_dict(), **{name: m.state_dict() for name, m in modules.items()}},
        }
        partial = self.path.with_suffix(".pt.partial")
        torch.save(state, partial)
        os.replace(partial, self.path)
        shutil.rmtree(self.out / "buffer.old", ignore_errors=True)

    def _save_buffer(self, buffer) -> None:
        """The buffer into a new folder, swapped for the previous one; the checkpoint
        written next records its size."""
        new, current, old = self.out / "buffer.partial", self.out / "buffer", self.out / "buffer.old"
        shutil.rmtree(new, ignore_errors=True)
        buffer.dumps(new)
        # the state of TorchRL's prefetching, unused here, is its one pickle: not kept, so
        # that loading a buffer never unpickles
        for file in new.rglob("*.pkl"):
            file.unlink()
        # the size of every file, which a resume checks (a truncated file is never read
        # as zeros); a buffer's files have the size of its capacity, however full
        self.counters["buffer_files"] = {str(f.relative_to(new)): f.stat().st_size for f in sorted(new.rglob("*")) if f.is_file()}
        if current.exists():
            shutil.rmtree(old, ignore_errors=True)
            os.replace(current, old)
        os.replace(new, current)
        self.counters["buffer_capacity"] = buffer.storage.max_size
        self.counters["buffer_len"] = len(buffer)

    def close(self, save) -> dict[str, Any]:
        """End the run: the last checkpoint (``save()``), the loggers flushed and, with
        a progress bar, the learning curve drawn into ``learning_curve.png``. Returns
        the last logged values and the transitions collected."""
        save()
        for logger in self.loggers[1:]:
            logger.experiment.flush()
        if self.bar is not None:
            from beacon_torch.training.evaluation import learning_curve

            self.bar.close()
            print(f"{self.algo} {self.env_id} seed {self.seed}: {self.last} -> {self.out}")
            print(learning_curve(self.out))
        return self.last
