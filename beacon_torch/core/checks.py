"""What an env checks of what it is given, each refusal one line naming the problem:
its construction's arguments, the memory a batch needs, actions, masks, states and
counts given to it, and what its physics returns."""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import torch

from beacon_torch.core.state import finite_members

_DTYPES = {"float32": torch.float32, "float64": torch.float64}


def as_dtype(dtype: Any) -> torch.dtype:
    if isinstance(dtype, str):
        dtype = _DTYPES.get(dtype.removeprefix("torch."), dtype)
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}")
    return dtype


# far beyond any use (the smallest env holds about 100 bytes a member), and below what
# makes an allocation fail in the middle of a set-up
MAX_MEMBERS = 2**24


def as_batch_size(batch_size: Any) -> torch.Size:
    if isinstance(batch_size, (bool, np.bool_)):
        raise TypeError(f"batch_size must be a positive integer, got {batch_size!r}")
    if isinstance(batch_size, (int, np.integer)):
        batch_size = (int(batch_size),)
    try:
        size = torch.Size(batch_size)
    except TypeError:
        raise TypeError(f"batch_size must be a positive integer, got {batch_size!r}") from None
    if len(size) != 1 or size[0] < 1:
        raise ValueError(f"batch_size must be a positive integer (a 1-D batch), got {tuple(size)}")
    if size[0] > MAX_MEMBERS:
        raise ValueError(
            f"batch_size {size[0]} is beyond what one env holds (at most {MAX_MEMBERS:,} members); use several envs"
        )
    return size


def as_flag(name: str, value: Any) -> bool:
    """An on/off option: a bool, not anything truthy (``differentiable="no"`` is not on)."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    raise TypeError(f"{name} must be True or False, got {value!r}")


def as_count(name: str, value: Any, env_id: str) -> int:
    """A number of things: a non-negative integer, not a bool or a float."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{env_id}: {name} must be a non-negative integer, got {value!r}")
    if value < 0:
        raise ValueError(f"{env_id}: {name} must be a non-negative integer, got {value}")
    return int(value)


def as_seed(seed: Any) -> int:
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)):
        raise TypeError(f"seed must be an integer in [0, 2**64), got {seed!r}")
    if not 0 <= int(seed) < 2**64:
        raise ValueError(f"seed must be an integer in [0, 2**64), got {seed}")
    return int(seed)


def as_device(device: Any) -> torch.device:
    try:
        device = torch.device(device)
    except (RuntimeError, TypeError) as err:
        raise ValueError(f"device {device!r} is not a torch device ({err})") from None
    if device.type == "meta":
        raise ValueError("device 'meta' holds no values, so an env cannot step there; use 'cpu' or an accelerator")
    try:
        torch.empty(0, device=device)
    except (RuntimeError, AssertionError) as err:
        raise ValueError(f"device {str(device)!r} cannot be used on this machine ({err})") from None
    return device


# a step's temporaries, in states of the batch: what a batch's memory is estimated by
WORKSPACE = 16


def available_bytes(device: torch.device) -> int | None:
    """The memory free for new tensors on ``device`` (None where it cannot be told)."""
    if device.type == "cuda":
        return torch.cuda.mem_get_info(device)[0]
    if device.type == "cpu":
        try:
            with open("/proc/meminfo") as f:
                fields = dict(line.split(":", 1) for line in f)
            return int(fields["MemAvailable"].split()[0]) * 1024
        except (OSError, KeyError, ValueError):
            return None
    return None


def check_memory(name: str, batch) -> None:
    """Refuse a batch (an env or a physics: its members, device, dtype and
    ``member_floats()``) whose states would not fit in the device's free memory, before
    anything of its size is allocated."""
    free = available_bytes(batch.device)
    per_member = batch.member_floats() * batch.dtype.itemsize * WORKSPACE
    need = batch.num_envs * per_member
    if free is not None and need > free:
        raise ValueError(
            f"{name}: {batch.num_envs:,} members need about {need / 2**30:,.1f} GiB on {batch.device}, "
            f"{free / 2**30:,.1f} GiB are free; at most about {max(1, free // per_member):,} members fit"
        )


class Guard:
    """What an env checks of what it is given while it runs, as one object of its own:
    built from the env's name, its physics (the batch, device, dtype, state type and
    actions it takes) and whether it keeps a graph; it reads nothing else of the env.
    Each check returns what it was given in the env's form, or raises one line naming
    the problem; the warnings point at the user's call."""

    def __init__(self, name: str, physics, differentiable: bool) -> None:
        self.name, self.physics, self.differentiable = name, physics, differentiable
        self.batch_size = torch.Size(physics.batch_size)
        self.num_envs = physics.num_envs
        self.device, self.dtype = physics.device, physics.dtype
        # the dropped gradient of an action is said once per env
        self.warned_grad = False

    def refuse_values(self, action: torch.Tensor) -> None:
        p = self.physics
        if p.discrete:
            raise ValueError(f"{self.name}: action values must be in [0, {p.n_actions - 1}], got {action.tolist()}")
        raise ValueError(
            f"{self.name}: action contains NaN or inf; expected shape "
            f"{(*self.batch_size, *p.action_shape)} with values in [-1, 1]"
        )

    def action(self, action: Any) -> torch.Tensor:
        """The action batch as a tensor of the env's device and dtype, its type and
        shape checked (its values are checked by the step, which reads them anyway)."""
        name, p = self.name, self.physics
        if action is None:
            raise KeyError(f"{name}: the input tensordict has no 'action' entry")
        if not isinstance(action, (torch.Tensor, np.ndarray, list, tuple, int, float, np.number)):
            raise TypeError(
                f"{name}: the action must be a tensor (or an array of numbers), got {type(action).__name__}"
            )
        if not isinstance(action, torch.Tensor):
            try:
                action = torch.as_tensor(np.asarray(action))
            except (TypeError, ValueError, RuntimeError) as err:
                raise TypeError(
                    f"{name}: the action must be a tensor (or an array of numbers), got {type(action).__name__} ({err})"
                ) from None
        shape = (*self.batch_size, *p.action_shape)
        if p.discrete:
            expected = f"shape {shape} with integer values in [0, {p.n_actions - 1}]"
            if action.dtype == torch.bool or action.is_floating_point() or action.is_complex():
                raise TypeError(f"{name}: action must be an integer tensor of {expected}, got dtype {action.dtype}")
            if tuple(action.shape) != shape:
                raise ValueError(f"{name}: action must have {expected}, got shape {tuple(action.shape)}")
            return action.to(device=self.device, dtype=torch.int64)
        expected = f"shape {shape} with values in [-1, 1]"
        if not action.is_floating_point():
            raise TypeError(f"{name}: action must be a floating tensor of {expected}, got dtype {action.dtype}")
        if tuple(action.shape) != shape:
            raise ValueError(f"{name}: action must have {expected}, got shape {tuple(action.shape)}")
        return action.to(device=self.device, dtype=self.dtype)

    def observation(self, obs: torch.Tensor, shape: torch.Size) -> None:
        """Refuse an observation of another shape than the spec's ``shape`` (a physics
        whose ``observe`` disagrees with its ``sizes``)."""
        if obs.shape != shape:
            raise ValueError(
                f"{self.name}: observe() returned shape {tuple(obs.shape)}, the observation spec says "
                f"{tuple(shape)} (sizes() gives {self.physics.n_obs} observations)"
            )

    def members_mask(self, mask: Any, key: str) -> torch.Tensor | None:
        """A ``_reset`` or ``_step`` entry as ``[batch]`` bool on the env's device (None:
        every member)."""
        if mask is None:
            return None
        if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool:
            raise TypeError(
                f"{self.name}: the {key!r} mask must be a bool tensor, got "
                f"{getattr(mask, 'dtype', type(mask).__name__)}"
            )
        if mask.numel() != self.num_envs:
            raise ValueError(
                f"{self.name}: the {key!r} mask must have one entry per member "
                f"({self.num_envs}), got shape {tuple(mask.shape)}"
            )
        return mask.reshape(self.batch_size).to(self.device)

    def traced_params(self, params) -> None:
        """Say so where parameters require grad and the env keeps no graph."""
        if self.differentiable:
            return
        traced = [
            name for name, value in vars(params).items() if isinstance(value, torch.Tensor) and value.requires_grad
        ]
        if traced:
            why = "their gradients are dropped (make(..., differentiable=True) keeps them)"
            warnings.warn(
                f"{self.name}: parameter(s) {traced} require grad but the env is not differentiable; {why}",
                stacklevel=4,
            )

    def dropped_gradient(self, action: Any) -> None:
        """Say so, once, where an action requires grad and the env keeps no graph."""
        if isinstance(action, torch.Tensor) and action.requires_grad and not self.differentiable:
            if not self.warned_grad:
                self.warned_grad = True
                warnings.warn(
                    f"{self.name}: the action requires grad but the env is not differentiable; its "
                    f"gradient is dropped (make(..., differentiable=True) keeps it)",
                    stacklevel=4,
                )

    def state(self, state: Any, shapes: dict[str, torch.Size]) -> tuple[Any, list[str]]:
        """A state given to ``set_state`` (the env's state type, or a dict of its
        fields) as the env's state type in its dtype and on its device, its fields,
        ``shapes`` and values checked; and the fields that require grad."""
        name, state_type = self.name, self.physics.state_type
        fields = state_type._fields
        if isinstance(state, state_type):
            state = state._asdict()
        if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
            raise TypeError(f"{name}: set_state needs a {state_type.__name__} of tensors like env.state")
        missing = sorted(set(fields) - set(state))
        extra = sorted(set(state) - set(fields))
        if missing or extra:
            raise KeyError(f"{name}: set_state needs the fields {list(fields)}; missing {missing}, unknown {extra}")
        for key, value in state.items():
            if value.shape != shapes[key]:
                raise ValueError(
                    f"{name}: state.{key} must have shape {tuple(shapes[key])} (the batch of {self.num_envs} "
                    f"first), got {tuple(value.shape)}"
                )
            if value.is_complex() or value.dtype == torch.bool:
                raise TypeError(f"{name}: state.{key} must hold real numbers, got dtype {value.dtype}")
        traced = [key for key, value in state.items() if value.requires_grad]
        if traced and not self.differentiable:
            warnings.warn(
                f"{name}: state fields {traced} require grad but the env is not differentiable; their "
                f"gradients are dropped (make(..., differentiable=True) keeps them)",
                stacklevel=3,
            )
        # every state is of the env's dtype (integers given are cast), as its specs say;
        # its values are checked after the cast (1e39 is finite in float64 only)
        state = state_type(*(state[k].to(self.device, self.dtype) for k in fields))
        for key, value in state._asdict().items():
            if not bool(torch.isfinite(value.detach()).all()):
                raise ValueError(f"{name}: state.{key} has values that are not finite in {self.dtype}")
        return state, traced

    def count(self, count: Any) -> torch.Tensor:
        """The actions already taken given to ``set_state``: an integer, or one per
        member, each in ``[0, episode_length)``."""
        name, length = self.name, self.physics.episode_length
        integer = isinstance(count, (int, np.integer)) and not isinstance(count, (bool, np.bool_))
        if isinstance(count, torch.Tensor):
            integer = not (count.is_floating_point() or count.is_complex() or count.dtype == torch.bool)
            integer = integer and count.shape in ((), self.batch_size)
        if not integer:
            shown = tuple(count.shape) if isinstance(count, torch.Tensor) else repr(count)[:40]
            raise TypeError(
                f"{name}: count must be an integer, or an integer tensor of one per member ({self.num_envs}), "
                f"got {shown}"
            )
        if not isinstance(count, torch.Tensor) and not 0 <= count < length:
            raise ValueError(f"{name}: count must be in [0, {length}) (actions already taken), got {count}")
        count = torch.as_tensor(count, dtype=torch.int64, device=self.device)
        if bool(((count < 0) | (count >= length)).any()):
            raise ValueError(f"{name}: count must be in [0, {length}) (actions already taken), got {count.tolist()}")
        return count

    def start_type(self, state: Any) -> None:
        """Refuse a start that is not of the env's state type (a physics whose
        ``initial_state`` returns a dict or a tuple)."""
        state_type = self.physics.state_type
        if type(state) is not state_type:
            raise TypeError(
                f"{self.name}: initial_state returned a {type(state).__name__}, not the env's "
                f"state type {state_type.__name__}"
            )

    def start(self, state: Any, obs: torch.Tensor, params, shape: torch.Size) -> None:
        """Refuse a start with values that are not finite (parameters out of the
        physics' range), naming the members, and an observation of another shape than
        the spec's ``shape``."""
        with torch.no_grad():
            started = finite_members(obs)
            for value in state:
                if value.is_floating_point():
                    started = started & finite_members(value)
        if not bool(started.all()):
            bad = (~started).nonzero()[:, 0].tolist()
            raise ValueError(
                f"{self.name}: the initial state of batch member(s) {bad} is not finite; "
                f"check their parameters ({params})"
            )
        self.observation(obs, shape)
