"""A training run's directory: ``checkpoint.pt``, the CSV logs
``<algo>/scalars/<name>.csv`` (``step,value`` lines, the step being transitions
collected; what ``beacon-torch plot`` and ``eval`` read), TensorBoard event files in
``<algo>/`` when asked for, the replay buffer of off-policy runs (``buffer-N/``) and
the progress bar.

A checkpoint holds, next to the state of every module and optimiser of the run, the env
id, the algorithm, the settings, the observation normalisation and, by name and width,
the network of its policy: evaluation rebuilds the policy from the checkpoint alone.

A run killed at any moment (``kill -9``), or stopped by a full disk, loses at most the
work since its last checkpoint: the replay buffer is written to a new folder of its own
(``buffer-N``, N counting the saves), then the checkpoint, which names that folder and
records how many transitions it holds and the size of each of its files, replaces the
old one in one step. The buffer and the checkpoint are thus committed together: until
the new checkpoint is in place the previous one names the previous folder, which is
left as it was; only then are the folders no checkpoint names removed. A resume reads
the folder its checkpoint names and drops the log lines written after the checkpoint.

A run directory may come from someone else, so everything in it is read as data and
checked: the checkpoint holds tensors and plain values only, each of the type and range
a run writes, and every log line is two numbers; anything else stops the command with
one line naming the file. A directory holding a symbolic link is refused, a fresh run
refuses a directory that holds a run, and a lock keeps a second process out of a
directory while a run writes to it. A non-finite loss or weight stops the run before
its checkpoint is written, so the last checkpoint stays the last good one.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import os
import re
import shutil
import time
from importlib.util import find_spec
from pathlib import Path
from typing import Any

import torch
from torchrl.record.loggers import CSVLogger

from beacon_torch import files, received, threads
from beacon_torch.core.checks import available_bytes
from beacon_torch.registry import ENVS
from beacon_torch.training.env import sibling
from beacon_torch.training.networks import NETWORKS

CHECKPOINT = "checkpoint.pt"
# the algorithms whose runs a checkpoint may record (the recipes' names)
ALGORITHMS = ("ppo", "td3", "sac", "dqn", "grad", "shac")
# the widest hidden layer a checkpoint may ask evaluation to build (the recipes use 32
# to 128): a forged width cannot make it allocate gigabytes
MAX_HIDDEN = 4096


class BadRun(ValueError):
    """A run directory's file that is not what a run writes: one line naming the file
    and what is wrong."""


def load_checkpoint(run: str | Path) -> dict:
    """The checkpoint of a run folder, checked (:func:`check_checkpoint`) while its
    tensors are still mapped from the file, then read into memory. It holds tensors,
    numbers, strings and containers of them only, read as such and within bounds
    (``beacon_torch.received``): a file whose pickle would run code is refused."""
    path = Path(run) / CHECKPOINT
    if path.is_symlink():
        raise files.UnsafeFile(f"{path}: a symbolic link is refused as a checkpoint")
    if not path.exists():
        raise FileNotFoundError(f"{path}: no checkpoint")
    return received.torch_file(path, "checkpoint", lambda state: check_checkpoint(state, path))


def _number(value, low: float = 0.0, high: float = math.inf, integer: bool = True) -> bool:
    kinds = (int,) if integer else (int, float)
    return isinstance(value, kinds) and received.finite_number(value) and low <= value <= high


# Network copies a checkpoint may hold, each with the recorded width: the actor, the
# critics (TD3's two and their targets), the target actor, and the two moments of
# every optimised network (TD3 holds 13 of them)
NETWORK_COPIES = 32


def checkpoint_bytes(env_id: str, params: dict, hidden: int) -> int:
    """The most bytes of tensors a checkpoint of a run on ``env_id`` whose networks are
    ``hidden`` wide can hold: :data:`NETWORK_COPIES` networks of three hidden layers
    fed an observation and an action, in float64, and the observation statistics."""
    n_obs, n_actions = ENVS[env_id].sizes(params)
    network = hidden * (n_obs + n_actions + 3 * hidden + 2 * n_actions + 8) + 2 * n_actions + 1
    return 8 * (NETWORK_COPIES * network + 2 * n_obs) + 2**16


def _finite_tensors(tree) -> bool:
    """Whether every tensor in a state dict (nested dicts and lists of them) is finite."""
    if isinstance(tree, torch.Tensor):
        return not (tree.is_floating_point() or tree.is_complex()) or bool(torch.isfinite(tree).all())
    if isinstance(tree, dict):
        return all(_finite_tensors(v) for v in tree.values())
    if isinstance(tree, (list, tuple)):
        return all(_finite_tensors(v) for v in tree)
    return True


def check_checkpoint(state, path: str | Path) -> None:
    """Refuse a checkpoint that is not what :meth:`Run.save` writes: known env,
    algorithm and policy network, counts and sizes of the right type and range, the
    observation statistics and module states as tensors, every weight finite."""

    def bad(what: str):
        return BadRun(f"{path}: not a checkpoint of a run ({what})")

    if not isinstance(state, dict):
        raise bad(f"a {type(state).__name__}, not a dict")
    for key in ("env", "algo", "frames", "config", "policy", "obs_norm", "modules"):
        if key not in state:
            raise bad(f"no {key!r}")
    if not isinstance(state["env"], str) or state["env"] not in ENVS:
        hint = ""
        if isinstance(state["env"], str) and len(state["env"]) < 100:
            hint = "; an env registered by a module of your own needs it imported first: beacon-torch --import MODULE"
        raise bad(f"unknown env {str(state['env'])[:100]!r}{hint}")
    if not isinstance(state["algo"], str) or state["algo"] not in ALGORITHMS:
        raise bad(f"unknown algorithm {state['algo']!r}; known: {', '.join(ALGORITHMS)}")
    if not _number(state["frames"]):
        raise bad(f"'frames' must be a non-negative integer, got {state['frames']!r}")
    if not _number(state.get("elapsed", 0.0), integer=False) or not _number(state.get("seed", 0), high=2**64):
        raise bad("'elapsed' and 'seed' must be non-negative numbers")
    if not isinstance(state["config"], dict) or not all(isinstance(k, str) for k in state["config"]):
        raise bad("'config' must be a dict of settings")
    try:
        ENVS[state["env"]].check(state["config"].get("params", {}))
    except (TypeError, ValueError) as err:
        raise bad(f"its env parameters: {err}") from None
    policy = state["policy"]
    if (
        not isinstance(policy, dict)
        or not isinstance(policy.get("network"), str)
        or policy["network"] not in NETWORKS
        or not _number(policy.get("hidden"), 1, MAX_HIDDEN)
    ):
        raise bad(
            f"'policy' must name a network of {sorted(NETWORKS)} and a width in [1, {MAX_HIDDEN}], got {policy!r}"
        )
    spec = ENVS[state["env"]]
    n_obs, n_actions = spec.sizes(state["config"].get("params", {}))
    if spec.agents is not None:
        # a multi-agent layout (one action per agent) normalises each agent's share
        n_obs //= n_actions
    stored = sum(t.numel() * t.element_size() for t in received.tensors_in(state))
    most = checkpoint_bytes(state["env"], state["config"].get("params", {}), policy["hidden"])
    if stored > most:
        raise bad(
            f"it holds {stored / 2**20:,.1f} MiB of tensors, more than a run of networks {policy['hidden']} wide "
            f"on {state['env']} can ({most / 2**20:,.1f} MiB)"
        )
    norm = state["obs_norm"]
    if not isinstance(norm, dict) or not all(isinstance(norm.get(k), torch.Tensor) for k in ("loc", "scale")):
        raise bad("'obs_norm' must hold the tensors 'loc' and 'scale'")
    if any(norm[k].shape != (n_obs,) for k in ("loc", "scale")):
        shapes = {k: tuple(norm[k].shape) for k in ("loc", "scale")}
        raise bad(f"the observation statistics must have {state['env']}'s {n_obs} observations, got shapes {shapes}")
    if norm["loc"].is_complex() or not norm["loc"].is_floating_point() or not norm["scale"].is_floating_point():
        raise bad("the observation statistics must be real numbers")
    if not _finite_tensors(norm) or not bool((norm["scale"] > 0).all()):
        raise bad("the observation statistics must be finite with a positive scale")
    modules = state["modules"]
    if (
        not isinstance(modules, dict)
        or not isinstance(modules.get("actor"), dict)
        or not all(isinstance(m, dict) for m in modules.values())
    ):
        raise bad("'modules' must hold the state of each module, 'actor' among them")
    if not _finite_tensors(modules):
        raise bad("non-finite weights")
    config = state["config"]
    total = config.get("frames")
    if _number(total):
        # a run stops at its total, past it by less than one collected batch
        horizon = (
            config.get("horizon", 0) * config.get("num_envs", 0)
            if _number(config.get("horizon")) and _number(config.get("num_envs"))
            else 0
        )
        sizes = [config.get("n_rollout"), config.get("frames_per_batch"), horizon]
        slack = max(v for v in sizes if _number(v)) if any(_number(v) for v in sizes) else 0
        if state["frames"] > total + slack:
            raise bad(f"it records {state['frames']:,} transitions, past its run's total of {total:,}")
    counters = state.get("counters", {})
    if not isinstance(counters, dict):
        raise bad("'counters' must be a dict")
    for name in ("updates", "target_counter", "skipped", "buffer_len"):
        if name in counters and not _number(counters[name]):
            raise bad(f"counter {name!r} must be a non-negative integer, got {counters[name]!r}")
    if "buffer_len" in counters:
        files_ = counters.get("buffer_files")
        if not _number(counters.get("buffer_capacity"), 1) or counters["buffer_len"] > counters["buffer_capacity"]:
            raise bad("the replay buffer's capacity must be a positive integer of at least its length")
        if not isinstance(files_, dict) or not all(
            isinstance(k, str) and ".." not in Path(k).parts and not Path(k).is_absolute() and _number(v)
            for k, v in files_.items()
        ):
            raise bad("'buffer_files' must map file names inside the buffer to their sizes")
        folder = counters.get("buffer_dir", LEGACY_BUFFER)
        if not isinstance(folder, str) or not BUFFER_NAME.fullmatch(folder):
            raise bad(f"'buffer_dir' must name a folder buffer-N of the run, got {folder!r}")


def seed_dirs(run: str | Path) -> list[Path]:
    """The per-seed folders of a run directory (the directory itself for one seed)."""
    run = Path(run)
    files.refuse_links(run)  # what is read from it, and written into it (an animation)
    if (run / CHECKPOINT).is_file():
        return [run]
    found = sorted(p for p in run.glob("seed*") if (p / CHECKPOINT).is_file())
    if not found:
        raise FileNotFoundError(f"{run}: not a run directory (no {CHECKPOINT} in it or in seed* folders)")
    return found


# the folder of a replay buffer saved with a checkpoint: ``buffer-N`` for the N-th save
# (``buffer``, named by none, in runs of earlier versions)
BUFFER_NAME = re.compile(r"buffer(-[0-9]{1,12})?")
LEGACY_BUFFER = "buffer"


def buffer_folders(run: str | Path) -> list[Path]:
    """The replay buffer folders in a run directory, whichever checkpoint names them
    (an earlier version's swap left ``buffer.old`` too)."""
    run = Path(run)
    found = [p for p in run.glob("buffer*") if BUFFER_NAME.fullmatch(p.name) or p.name == "buffer.old"]
    return sorted(found, key=lambda p: (len(p.name), p.name))


def buffer_folder(run: str | Path, counters: dict | None = None) -> Path:
    """The replay buffer folder that the run's checkpoint (or ``counters``, a
    checkpoint's) names: the one saved with it."""
    if counters is None:
        counters = load_checkpoint(run).get("counters", {})
    return Path(run) / counters.get("buffer_dir", LEGACY_BUFFER)


def holds_run(folder: str | Path, algo: str) -> str:
    """What in ``folder`` belongs to a run ("" when nothing does): its checkpoint,
    its logs, its replay buffers or its curve."""
    folder = Path(folder)
    found = [
        name
        for name in (CHECKPOINT, algo, "learning_curve.png")
        if (folder / name).exists() or (folder / name).is_symlink()
    ]
    return ", ".join(found + [p.name for p in buffer_folders(folder)])


# a log holds a line of about 30 bytes per round of updates: 64 MiB is two million
# rounds, beyond any run of the recipes (2 M transitions in rounds of 64: 31,250)
LOG_BYTES = 64 * 2**20


def read_log(file: str | Path) -> list[tuple[float, float]]:
    """The ``(step, value)`` lines of a CSV log, checked: a regular file of at most
    :data:`LOG_BYTES`, each line two numbers, the step a non-negative integer count of
    transitions, the value finite."""
    rows = []
    try:
        text = received.text_file(file, "log of a run", LOG_BYTES)
    except received.BadFile as err:
        raise BadRun(str(err)) from None
    try:
        for number, row in enumerate(csv.reader(io.StringIO(text, newline="")), 1):
            try:
                step, value = (float(x) for x in row) if len(row) == 2 else (None, None)
            except ValueError:
                step = None
            # a run logs finite values only (a non-finite one stops it first)
            if (
                step is None
                or not (math.isfinite(step) and step >= 0 and step.is_integer())
                or not math.isfinite(value)
            ):
                raise BadRun(
                    f"{file}, line {number}: not a log line of a run (a step and a finite value), got "
                    f"{','.join(row)[:60]!r}"
                )
            rows.append((step, value))
    except csv.Error as err:
        raise BadRun(f"{file}: not a log of a run ({type(err).__name__})") from None
    return rows


def _write_rows(path: Path, rows) -> None:
    with path.open("w", newline="") as f:
        csv.writer(f).writerows((int(step), value) for step, value in rows)


class Diverged(ValueError):
    """Training reached a non-finite loss or weight."""


def _transition_bytes(buffer) -> float:
    """Bytes a transition of ``buffer`` takes on disk (0 while it is empty)."""
    if len(buffer) == 0:
        return 0.0
    return sum(
        t.element_size() * t[0].numel()
        for t in buffer.storage._storage.values(True, True)
        if isinstance(t, torch.Tensor)
    )


def tensorboard_installed() -> bool:
    return find_spec("tensorboard") is not None


def episode_values(data, reward_key: str | tuple[str, ...] = "reward") -> dict[str, float]:
    """The mean reward of a collected batch and the mean score of the episodes that
    ended in it (``RewardSum``'s ``episode_reward``); over the agents too where there
    are several (the team's score, as ``episodes.scores`` counts it)."""
    done = data["next", "done"][..., 0]
    reward, score = data["next", reward_key], data["next", sibling(reward_key, "episode_reward")]
    values = {"reward": reward.float().mean().item()}
    if done.any():
        score = score.float().reshape(*done.shape, -1).mean(-1)  # the team's score
        values["episode_score"] = score[done].mean().item()
    return values


# the float dtype the recipes train in, and the other dtypes a transition holds (flags,
# trajectory ids)
BUFFER_DTYPES = ("torch.float32", "torch.bool", "torch.int64")


def check_buffer(folder: Path, capacity: int, widest: int) -> None:
    """Refuse a saved replay buffer whose description (TorchRL's ``meta.json`` files)
    is not what a run of ``capacity`` transitions writes, before TorchRL allocates what
    it describes: every entry ``capacity`` long, no entry of a transition wider than
    the env's widest field (``widest``: its observation or action size), the recipes'
    dtypes, each file the size its entry says, and the whole fitting in memory."""
    metas = sorted(folder.rglob("meta.json"), key=lambda meta: len(meta.parts))
    if not metas:
        raise BadRun(f"{folder}: no description of the replay buffer's storage (meta.json)")
    total = 0
    for meta in metas:
        entries = received.json_file(meta, "replay buffer description")
        if not isinstance(entries, dict):
            raise BadRun(f"{meta}: not a replay buffer's description")
        for key, entry in entries.items():
            if key in ("shape", "device", "_type"):
                continue
            if not isinstance(entry, dict):
                raise BadRun(f"{meta}: entry {key!r} is not described")
            if entry.get("type") == "TensorDict" and set(entry) == {"type"}:
                continue  # a nested folder, described by its own meta.json
            shape, dtype = entry.get("shape"), entry.get("dtype")
            if (
                not isinstance(shape, list)
                or not shape
                or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape)
            ):
                raise BadRun(f"{meta}: entry {key!r} has no shape of sizes")
            width = math.prod(shape[1:])
            if shape[0] != capacity or width > widest:
                raise BadRun(
                    f"{meta}: entry {key!r} of shape {shape}, not {capacity:,} transitions of at most {widest} values "
                    f"(what this run's buffer holds)"
                )
            if dtype not in BUFFER_DTYPES:
                kinds = ", ".join(BUFFER_DTYPES)
                raise BadRun(f"{meta}: entry {key!r} of dtype {dtype!r}; a run's buffer holds {kinds}")
            nbytes = capacity * width * {"torch.float32": 4, "torch.bool": 1, "torch.int64": 8}[dtype]
            file = meta.parent / f"{key}.memmap"
            if file.is_symlink() or not file.is_file() or file.stat().st_size != nbytes:
                raise BadRun(f"{file}: not the {nbytes:,} bytes its description {meta} gives")
            total += nbytes
        # the storage's root holds one transition a row; a nested folder (the agents'
        # fields of a multi-agent layout) may add dimensions after it
        shape = entries.get("shape")
        nested = meta is not metas[0]
        if (
            not isinstance(shape, list)
            or shape[:1] != [capacity]
            or (not nested and shape != [capacity])
            or not all(isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in shape)
            or math.prod(shape[1:]) > widest
            or entries.get("_type") != "<class 'tensordict._td.TensorDict'>"
        ):
            raise BadRun(f"{meta}: not a replay buffer of {capacity:,} transitions")
    fits(f"{folder}: the replay buffer", total)


def fits(what: str, need: int, device="cpu") -> None:
    """Refuse to allocate ``need`` bytes of ``what`` on ``device`` beyond the memory
    free there, with the estimate."""
    free = available_bytes(torch.device(device))
    if free is not None and need > free:
        raise ValueError(
            f"{what} needs about {need / 2**30:,.2f} GiB on {device} and {free / 2**30:,.2f} GiB are free there"
        )


def corrupt_transitions(data) -> str:
    """What is wrong with stored transitions that no run collects ("" if nothing): a
    non-finite value, or an end of episode that is neither a termination nor a
    truncation."""
    for key, value in data.items(include_nested=True, leaves_only=True):
        if isinstance(value, torch.Tensor) and value.is_floating_point() and not bool(torch.isfinite(value).all()):
            return f"{key} has non-finite values"
    for prefix in ((), ("next",)):
        flags = [data.get((*prefix, k), None) for k in ("done", "terminated", "truncated")]
        if all(f is not None for f in flags) and not bool((flags[0] == (flags[1] | flags[2])).all()):
            return f"{'/'.join((*prefix, 'done'))} is not terminated or truncated"
    return ""


def load_optimiser(optim: torch.optim.Optimizer, saved, where: str) -> None:
    """Load an optimiser's saved state, refusing (:class:`ValueError` starting with
    ``where``) one that does not fit its parameters or that it cannot reach: per
    parameter, moments of its shape, finite once cast, a non-negative second moment,
    and Adam's bound on the first by the second (with decays b1, b2, b1**2 < b2,
    m**2 <= (1 - b1)**2 / ((1 - b2) (1 - b1**2 / b2)) v, whatever the gradients)."""
    if not isinstance(saved, dict) or not isinstance(saved.get("param_groups"), list):
        raise ValueError(f"{where} is not an optimiser's state")
    groups = optim.param_groups
    if len(saved["param_groups"]) != len(groups) or any(
        not isinstance(g, dict) or len(g.get("params", ())) != len(own["params"])
        for g, own in zip(saved["param_groups"], groups, strict=False)
    ):
        raise ValueError(f"{where} is not one of this run's optimisers (other parameter groups)")
    try:
        optim.load_state_dict(saved)
    except (ValueError, KeyError, TypeError, RuntimeError, IndexError) as err:
        first = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise ValueError(f"{where} is corrupt ({first})") from None
    for group in optim.param_groups:
        betas = group.get("betas")
        for p in group["params"]:
            state = optim.state.get(p, {})
            for key, value in state.items():
                if not isinstance(value, torch.Tensor):
                    continue
                if value.ndim and value.shape != p.shape:  # a moment (step counts are scalars)
                    shapes = f"{key} of shape {tuple(value.shape)} for a parameter of {tuple(p.shape)}"
                    raise ValueError(f"{where} is corrupt ({shapes})")
                if value.is_floating_point() and not bool(torch.isfinite(value).all()):
                    raise ValueError(f"{where} is corrupt (non-finite {key})")
                # a step count, NAdam's product of momenta (a scalar parameter's first
                # moment, SAC's entropy weight's, is a 0-dim tensor of either sign)
                if key in ("step", "mu_product") and bool((value < 0).any()):
                    raise ValueError(f"{where} is corrupt (a negative {key})")
            m, v = state.get("exp_avg"), state.get("exp_avg_sq")
            if v is not None and bool((v < 0).any()):
                raise ValueError(f"{where} is corrupt (a negative second moment)")
            if m is not None and v is not None and betas is not None and betas[0] ** 2 < betas[1]:
                b1, b2 = betas
                c = math.sqrt((1 - b1) ** 2 / ((1 - b2) * (1 - b1**2 / b2)))
                # the slack covers rounding and squares of gradients that underflow
                if bool((m.abs() > 1.001 * c * v.sqrt() + 1e-15).any()):
                    raise ValueError(f"{where} is corrupt (moments no sequence of gradients gives)")


def _tracker(name: str, algo: str, env_id: str, out: Path, settings: dict):
    """TorchRL's logger of an experiment tracker for a run in ``out``: Weights & Biases
    (its files in ``out/wandb``, W&B's own folder, where it keeps links of its own;
    ``WANDB_MODE=offline`` logs there only) or
    MLflow (to ``$MLFLOW_TRACKING_URI``, else a SQLite store ``out/mlflow.db`` with the
    artifacts in ``out/mlflow``), the run's settings recorded as its configuration."""
    if name == "wandb":
        from torchrl.record.loggers import WandbLogger

        logger = WandbLogger(
            exp_name=f"{algo}-{env_id}", project="beacon-torch", log_env_packages=False, save_dir=str(out.resolve())
        )
    else:
        from torchrl.record.loggers import MLFlowLogger

        uri = os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{(out / 'mlflow.db').resolve()}"
        artifacts = None if os.environ.get("MLFLOW_TRACKING_URI") else (out / "mlflow").resolve().as_uri()
        logger = MLFlowLogger(exp_name=f"{algo}-{env_id}", tracking_uri=uri, artifact_location=artifacts)
    logger.log_hparams({k: v for k, v in settings.items() if isinstance(v, (int, float, str, bool))})
    return logger


def _finish(logger) -> None:
    """Flush or end a logger beside the CSV ones at the end of a run."""
    experiment = logger.experiment
    for name in ("flush", "finish"):
        if callable(getattr(experiment, name, None)):
            getattr(experiment, name)()
            return
    if type(logger).__name__ == "MLFlowLogger":
        import mlflow

        mlflow.end_run()


class Run:
    """The directory ``out`` of one training of ``algo`` on ``env_id`` towards ``total``
    transitions, new or (``resume``) continued from its checkpoint. ``tensorboard``:
    True, False, or None for "when the package is installed"; ``tracker``: "wandb" or
    "mlflow" for TorchRL's logger of that experiment tracker too. ``settings`` (a dict) is
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
        tracker: str = "",
        checkpoint_every: int = 10,
    ) -> None:
        if tracker not in ("", "wandb", "mlflow"):
            raise ValueError(f"tracker must be 'wandb', 'mlflow' or '', got {tracker!r}")
        if tracker and find_spec(tracker) is None:
            raise ValueError(
                f"the {tracker} logger needs the {tracker} package (pip install 'beacon-torch[{tracker}]')"
            )
        self.out = Path(out)
        self.path = self.out / CHECKPOINT
        self.env_id, self.algo, self.total, self.seed = env_id, algo, total, seed
        self.settings = settings or {}
        self.checkpoint_every, self.rounds = checkpoint_every, 0
        self.state: dict | None = None
        # refused before anything is created; checked again under the lock
        self._refuse(resume)
        self.out.mkdir(parents=True, exist_ok=True)
        files.refuse_links(self.out)
        self.lock = files.Lock(self.out)
        try:
            self._open(resume)
        except BaseException:
            self.lock.release()
            raise
        self.frames = self.state["frames"] if self.state else 0
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
        if tracker:
            self.loggers.append(_tracker(tracker, algo, env_id, self.out, self.settings))
        self.last: dict[str, Any] = {"frames": self.frames}
        self.bar, self.progress = None, progress
        if progress and total > self.frames:
            from tqdm.auto import tqdm

            # the time left from the last round's rate alone: the first round, which
            # compiles the step, would stretch an average over the run for long
            self.bar = tqdm(total=total, initial=self.frames, unit="frames", desc=f"{algo} {env_id}", smoothing=1.0)

    def _refuse(self, resume: bool) -> None:
        """Refuse a new run in a directory that holds one, and a resume without a
        checkpoint."""
        found = holds_run(self.out, self.algo)
        if not resume:
            if found:
                raise FileExistsError(
                    f"{self.out} holds a run ({found}); continue it with --resume, or give a new --out"
                )
            return
        if not self.path.is_file() or self.path.is_symlink():
            # a run stopped before its first checkpoint, or someone's folder: a resume
            # continues a checkpoint and nothing else (its logs are left as they are)
            what = "a directory" if self.path.is_dir() else "a symbolic link" if self.path.is_symlink() else "missing"
            raise BadRun(
                f"{self.path}: no checkpoint to resume ({what}); a fresh run needs a new --out"
                + (f" (this one holds {found})" if found else "")
            )

    def _open(self, resume: bool) -> None:
        """Check the directory for a new run or read the checkpoint of a resumed one;
        trim the logs to it."""
        self._refuse(resume)
        if not resume:
            return
        self.state = load_checkpoint(self.out)
        if self.state["env"] != self.env_id or self.state["algo"] != self.algo:
            raise BadRun(
                f"{self.out} holds a {self.state['algo']} run on {self.state['env']}, not {self.algo} on {self.env_id}"
            )
        files.remove_partials(self.out)
        self._trim_logs(self.state["frames"])

    def _trim_logs(self, frames: int) -> None:
        """Drop the log lines of steps after the checkpoint (written before a stop), so
        that the resumed run's lines follow on without repeated or backward steps. Every
        line must be what :meth:`log` writes, a step and a value; anything else stops
        the resume, naming the file and line."""
        for file in sorted((self.out / self.algo / "scalars").glob("*.csv")):
            rows = read_log(file)
            files.replace_file(file, lambda tmp, rows=rows: _write_rows(tmp, [r for r in rows if r[0] <= frames]))

    @classmethod
    def of(cls, settings) -> Run:
        """The run of a recipe's settings: a dataclass with ``out``, ``env``, ``algo``,
        ``frames``, ``seed``, ``resume``, ``progress``, ``tensorboard``,
        ``checkpoint_every`` and ``threads`` (which sets torch's threads), recorded whole
        with the checkpoints."""
        s = settings
        # torch's threads for the whole training: the count asked for, else the
        # measured default for training on the env (beacon_torch.threads)
        threads.use(s.threads or None, s.env, s.num_envs, training=True)
        return cls(
            s.out,
            s.env,
            s.algo,
            s.frames,
            seed=s.seed,
            settings=dataclasses.asdict(s),
            resume=s.resume,
            progress=s.progress,
            tensorboard=s.tensorboard,
            tracker=getattr(s, "tracker", ""),
            checkpoint_every=s.checkpoint_every,
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
        names they were saved under) and ``buffer``; nothing for a new run. Each state
        must fit its module (entries and shapes), hold finite values once cast to its
        dtype and, for an optimiser, be one it can reach; anything else is named as
        corrupt (:class:`BadRun`)."""
        if self.state is None:
            return
        for name, module in modules.items():
            saved = self.state["modules"].get(name)
            where = f"{self.path}: the state of {name!r}"
            if saved is None:
                raise BadRun(f"{where} is missing (a checkpoint of another recipe?)")
            try:
                if isinstance(module, torch.optim.Optimizer):
                    load_optimiser(module, saved, where)
                else:
                    received.load_into(module, saved, where, f"this run's {name}")
            except ValueError as err:
                raise BadRun(f"{err}; resume from a copy of the run or start it again") from None
        if buffer is None or "buffer_len" not in self.counters:
            return
        folder = buffer_folder(self.out, self.counters)
        if "buffer_dir" not in self.counters and not folder.exists() and (self.out / "buffer.old").exists():
            folder = self.out / "buffer.old"  # an earlier version's stop between the two renames of a swap
        if not folder.exists():
            raise FileNotFoundError(
                f"{self.out}: the checkpoint refers to a replay buffer of "
                f"{self.counters['buffer_len']} transitions, and there is none"
            )
        for name, size in self.counters.get("buffer_files", {}).items():
            file = folder / name
            if not file.is_file() or file.stat().st_size != size:
                found = file.stat().st_size if file.is_file() else "no"
                raise ValueError(
                    f"{folder}: the replay buffer is damaged ({name}: {found} bytes, {size} when "
                    f"saved); resume from a copy of the run or start it again"
                )
        if any(folder.rglob("*.pkl")):
            # TorchRL unpickles these when it loads a buffer: code could run
            raise ValueError(
                f"{folder}: a replay buffer folder with pickle files is refused (loading it could "
                f"run code); ours hold tensors and JSON only"
            )
        capacity = self.counters["buffer_capacity"]
        recorded = self.state["config"].get("buffer_size") or self.state["config"].get("frames")
        if capacity != recorded:
            raise BadRun(
                f"{self.path}: a replay buffer of {capacity:,} transitions, not the {recorded!r} its settings give"
            )
        params = self.state["config"].get("params", {})
        sizes = ENVS[self.env_id].sizes(params)
        check_buffer(folder, capacity, max(*sizes, 1))
        # the transitions the checkpoint counted, oldest first (the buffer may hold more:
        # a stop between its save and the checkpoint's), into a buffer of the resumed size
        saved = type(buffer)(storage=type(buffer.storage)(capacity, device=buffer.storage.device))
        try:
            saved.loads(folder)
        except Exception as err:  # a tampered or foreign buffer: TorchRL's own errors name no file
            raise BadRun(
                f"{folder}: unreadable replay buffer ({type(err).__name__}: "
                f"{str(err).splitlines()[0] if str(err) else ''}); resume from a copy of the run or start it again"
            ) from None
        n = self.counters["buffer_len"]
        if len(saved) < n:
            raise ValueError(
                f"{folder}: the replay buffer holds {len(saved)} transitions, the checkpoint counted {n}: it is damaged"
            )
        if n:
            kept = saved[max(0, n - buffer.storage.max_size) : n]
            problem = corrupt_transitions(kept)
            if problem:
                raise BadRun(
                    f"{folder}: the replay buffer is corrupt ({problem}); resume from a copy of the run or start "
                    f"it again"
                )
            buffer.extend(kept)

    def seconds(self) -> float:
        return self.elapsed + time.perf_counter() - self._since

    def log(self, collected: int, values: dict[str, float], save=None) -> None:
        """Count and log one round of ``collected`` transitions; ``save()`` writes the
        checkpoint, called every ``checkpoint_every`` rounds."""
        bad = {name: value for name, value in values.items() if not math.isfinite(value)}
        if bad:
            # the networks are no longer usable: stop before the next checkpoint
            what = ", ".join(f"{k} = {v}" for k, v in bad.items())
            raise Diverged(
                f"{self.out}: training diverged after {self.frames:,} transitions ({what}); its "
                f"last checkpoint is kept. Lower the learning rate"
            )
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
        if not _finite_tensors(state["modules"]):
            raise Diverged(
                f"{self.out}: training diverged after {self.frames:,} transitions (non-finite "
                f"weights); its last checkpoint is kept. Lower the learning rate"
            )
        # the buffer is committed with the checkpoint that names it: until this line,
        # the previous checkpoint and its folder are the run
        files.save_tensors(state, self.path)
        if buffer is not None:
            for folder in buffer_folders(self.out):
                if folder.name != self.counters["buffer_dir"]:
                    shutil.rmtree(folder, ignore_errors=True)

    def _save_buffer(self, buffer) -> None:
        """The buffer into a new folder of its own; the checkpoint written next names
        it and records its size and files (``self.counters``: nothing on disk refers to
        the new folder before that checkpoint)."""
        # a buffer's files are memory maps: on a full disk, writing them ends the
        # process with SIGBUS, so the space is checked first (the previous folder stays)
        need, free = int(buffer.storage.max_size * _transition_bytes(buffer)), files.free_bytes(self.out)
        if need > free:
            raise OSError(
                f"{self.out}: no room to save the replay buffer ({need / 2**20:,.0f} MiB needed, "
                f"{free / 2**20:,.0f} MiB free); free some space and resume"
            )
        new = files.new_folder(self.out, "buffer.partial")
        buffer.dumps(new)
        # the state of TorchRL's prefetching, unused here, is its one pickle: not kept, so
        # that loading a buffer never unpickles
        for file in new.rglob("*.pkl"):
            file.unlink()
        # the next free number: a folder of that name left by a save whose checkpoint
        # was never written is named by no checkpoint, and replaced
        numbers = [int(p.name.split("-")[1]) for p in buffer_folders(self.out) if "-" in p.name]
        name = f"buffer-{max([0, *numbers]) + 1}"
        shutil.rmtree(self.out / name, ignore_errors=True)
        os.replace(new, self.out / name)
        self.counters.update(
            buffer_dir=name,
            # the size of every file, which a resume checks (a truncated file is never
            # read as zeros); a buffer's files have the size of its capacity, however full
            buffer_files={
                str(f.relative_to(self.out / name)): f.stat().st_size
                for f in sorted((self.out / name).rglob("*"))
                if f.is_file()
            },
            buffer_capacity=buffer.storage.max_size,
            buffer_len=len(buffer),
        )

    def close(self, save) -> dict[str, Any]:
        """End the run: the last checkpoint (``save()``), the loggers flushed, the lock
        released, the progress bar closed and the last values printed. Returns the last
        logged values and the transitions collected."""
        save()
        self.lock.release()
        for logger in self.loggers[1:]:
            _finish(logger)
        if self.bar is not None:
            self.bar.close()
        print(f"{self.algo} {self.env_id} seed {self.seed}: {self.last} -> {self.out}")
        # the folders TorchRL's CSV logger makes for texts and videos, empty in a run of ours
        for name in ("texts", "videos"):
            folder = self.out / self.algo / name
            if folder.is_dir() and not any(folder.iterdir()):
                folder.rmdir()
        return self.last
