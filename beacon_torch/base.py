"""``FlowEnv``: the batched TorchRL environment every BEACON env is.

The env is a shell around a case's physics (:class:`~beacon_torch.core.physics.Physics`,
declared as the env class's ``physics_type``): it holds the batch size, device and
dtype, the parameters, the seeded generators, the specs, the current state and its
counters, and steps them with the one step function
(:func:`~beacon_torch.core.step.step`), eagerly, compiled as one call, or keeping the
autograd graph. What a case knows of its equations (the hooks ``initial_state``,
``advance``, ``observe``, ...) lives on its physics and takes the parameters as an
argument; the env's class mirrors the physics' facts (``Params``, ``state_type``,
``episode_length``, ``discrete``, ...) and adds its card, rendering and, for layouts of
several agents, its specs. What the physics set up (a grid, the kernels) reads through
the env as well (``env.n_cells`` is ``env.physics.n_cells``).

Besides its physics an env class declares its card, class attributes that say what the
library knows of it (family, cost, the published code's speed, the paper's PPO score,
its gradient check, cheap settings for tests; see ``FlowEnv``), which benchmarks,
reports and tests read instead of keeping lists of envs.

With ``differentiable=True`` the steps keep the autograd graph through the state, so the
rewards can be differentiated with respect to the actions, to parameters given as
tensors that require grad and to a state set by :meth:`FlowEnv.set_state`. Resets are
not differentiated: an episode starts from data (the published starts are developed by
long uncontrolled runs).
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import Any, ClassVar

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from beacon_torch import starts as start_sets
from beacon_torch.autograd import graph_mode
from beacon_torch.compiled import standard
from beacon_torch.core.physics import Physics
from beacon_torch.core.state import Noise, State, finite_members, map_state, select, where_members
from beacon_torch.core.step import settle, step
from beacon_torch.history import History
from beacon_torch.params import resolve_params

__all__ = ["FlowEnv", "GradCheck", "Noise", "Physics", "State", "map_state", "select", "settle", "where_members"]


_DTYPES = {"float32": torch.float32, "float64": torch.float64}


def _as_dtype(dtype: Any) -> torch.dtype:
    if isinstance(dtype, str):
        dtype = _DTYPES.get(dtype.removeprefix("torch."), dtype)
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}")
    return dtype


# far beyond any use (the smallest env holds about 100 bytes a member), and below what
# makes an allocation fail in the middle of a set-up
MAX_MEMBERS = 2**24


def _as_batch_size(batch_size: Any) -> torch.Size:
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


def _as_flag(name: str, value: Any) -> bool:
    """An on/off option: a bool, not anything truthy (``differentiable="no"`` is not on)."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    raise TypeError(f"{name} must be True or False, got {value!r}")


def _as_seed(seed: Any) -> int:
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)):
        raise TypeError(f"seed must be an integer in [0, 2**64), got {seed!r}")
    if not 0 <= int(seed) < 2**64:
        raise ValueError(f"seed must be an integer in [0, 2**64), got {seed}")
    return int(seed)


def _as_device(device: Any) -> torch.device:
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


# mixed into the seed of the random actions' generator: a stream apart from the physics'
ACTION_STREAM = 0x9E3779B97F4A7C15

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


def _standard(state: State, obs: torch.Tensor) -> tuple[State, torch.Tensor]:
    """``state`` and ``obs`` as a step leaves them: standard strides, and no two
    tensors sharing memory. A compiled step is specialised on its inputs' strides and
    on which of them alias, and a start's views (a slice, a member of size one, an
    observation that is a view of the state) or shared zeros would otherwise compile it
    again on the second step."""
    out, storages = [], set()
    for value in (*state, obs):
        storage = value.untyped_storage().data_ptr()
        out.append(standard(value) if storage not in storages else value.clone(memory_format=torch.contiguous_format))
        storages.add(storage)
    *fields, obs = out
    return type(state)(*fields), obs


def _short_params(params) -> str:
    """Parameters as a repr shows them: a per-member value once when the members share
    it, else its range over the members (not 64 numbers at 64 members)."""
    shown = []
    for f in dataclasses.fields(params):
        value = getattr(params, f.name)
        if isinstance(value, torch.Tensor) and value.ndim >= 1 and value.numel() > 0:
            flat = value.detach().flatten()
            if bool((flat == flat[0]).all()):
                value = repr(flat[0].item())
            elif flat.is_complex():
                value = f"<{flat.numel()} complex values>"
            else:
                value = f"<{flat.numel()} values in [{flat.min().item():.4g}, {flat.max().item():.4g}]>"
        else:
            value = repr(value)
        shown.append(f"{f.name}={value}")
    return f"{type(params).__name__}({', '.join(shown)})"


@dataclasses.dataclass(frozen=True)
class GradCheck:
    """An env's gradient check (``beacon_torch.gradcheck``): the reward summed over
    ``steps`` random actions after ``warmup`` of them, differentiated with respect to
    the actions and to the parameter ``param`` at ``value``, with the other parameters
    ``params``."""

    param: str
    value: float
    warmup: int
    steps: int
    params: dict[str, Any] = dataclasses.field(default_factory=dict)


# what a physics defines; an env class defining one would not be read
PHYSICS_HOOKS = {
    "setup",
    "initial_state",
    "advance",
    "observe",
    "noise",
    "null_action",
    "out_of_bounds",
    "diagnose",
    "member_floats",
}


class FlowEnv(EnvBase):
    """Base of the batched BEACON environments (see the module docstring)."""

    env_id: ClassVar[str] = ""
    # the case's equations; its facts below are mirrored on the env class
    physics_type: ClassVar[type[Physics]]
    Params: ClassVar[type]
    episode_length: ClassVar[int]
    discrete: ClassVar[bool] = False
    state_type: ClassVar[type]
    blowup_reward: ClassVar[float] = -1.0
    diagnostics: ClassVar[dict[str, str]] = {}
    deterministic: ClassVar[bool] = True
    # where the action is read from and the observation and reward written to
    # (nested keys for multi-agent variants)
    action_key: ClassVar[str | tuple[str, ...]] = "action"
    observation_key: ClassVar[str | tuple[str, ...]] = "observation"
    reward_key: ClassVar[str | tuple[str, ...]] = "reward"
    # The env's card: what the library knows of it beyond its equations, declared in its
    # module (a variant subclasses its base env and inherits it). Benchmarks, reports
    # and the test suite read it; nothing keeps a list of envs of its own.
    # Facts an env does not have stay None: a user's env registers without them.
    # what the env solves: "ode", "1-D" or "2-D" (a flow in one or two space dimensions)
    family: ClassVar[str]
    # whether an action costs seconds rather than milliseconds: tests and benchmarks
    # run fewer of its steps
    costly: ClassVar[bool] = False
    # transitions per second of the published single-env NumPy/Numba code on one core
    # of this project's Intel Xeon machine kind (None: no published code is run here)
    published_speed: ClassVar[float | None] = None
    # the speed-up over it aimed at, at the best batch size, float32, 2 CPU cores
    speed_target: ClassVar[float | None] = None
    # the score the paper's PPO reaches, read from its curves as the mean of the last
    # tenth of its training episodes (the 1 of the reports' normalised scores; None:
    # no paper score, and the protocol has nothing to normalise by)
    paper_ppo: ClassVar[float | None] = None
    # the gradient check on the published settings (None where the actions are discrete)
    gradcheck: ClassVar[GradCheck | None] = None
    # parameters that make an episode cheap, for the behaviour tests run on every env
    test_settings: ClassVar[dict[str, Any]] = {}

    # the physics' facts an env class shows as its own
    MIRRORED: ClassVar[tuple[str, ...]] = (
        "Params",
        "state_type",
        "episode_length",
        "discrete",
        "blowup_reward",
        "diagnostics",
        "deterministic",
        "sizes",
        "inductor_options",
    )

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        hooks = sorted(set(vars(cls)) & PHYSICS_HOOKS)
        if hooks:
            raise TypeError(
                f"{cls.__name__} defines the physics hook(s) {hooks} on the env: they belong to a "
                f"beacon_torch.Physics subclass, named by the env class's physics_type, and take the "
                f"parameters as their first argument (docs/adding-an-env.md)"
            )
        physics = vars(cls).get("physics_type")
        # a variant's own episode length or blow-up reward (an env class that says
        # ``episode_length = 25``) makes a physics of its own with them
        overrides = {name: vars(cls)[name] for name in ("episode_length", "blowup_reward") if name in vars(cls)}
        if overrides and getattr(cls, "physics_type", None) is not None:
            base = physics or cls.physics_type
            physics = type(base.__name__, (base,), {**overrides, "__module__": cls.__module__})
            cls.physics_type = physics
        if physics is not None:
            for name in cls.MIRRORED:
                if hasattr(physics, name):
                    setattr(cls, name, getattr(physics, name))

    def __getattr__(self, name: str) -> Any:
        # what the physics set up (a grid, its kernels) and its hooks read through the env
        try:
            return super().__getattr__(name)
        except AttributeError:
            physics = self.__dict__.get("physics")
            if physics is None or name.startswith("__"):
                raise
            return getattr(physics, name)

    @classmethod
    def base_id(cls) -> str:
        """The benchmark env this one is a variant of, or its own id: a variant
        subclasses its base env, against whose scores and speed it is measured."""
        for klass in cls.__mro__[1:]:
            if klass.__dict__.get("env_id"):
                return klass.env_id
        return cls.env_id

    def __init__(
        self,
        batch_size: int | tuple[int] = 1,
        *,
        device: str | torch.device = "cpu",
        dtype: str | torch.dtype = torch.float32,
        seed: int | None = None,
        check_actions: bool = True,
        record_history: bool = False,
        differentiable: bool = False,
        grad_checkpoint: bool = False,
        starts: str | None = None,
        **params: Any,
    ) -> None:
        batch_size = _as_batch_size(batch_size)
        device = _as_device(device)
        flags = dict(
            check_actions=check_actions,
            record_history=record_history,
            differentiable=differentiable,
            grad_checkpoint=grad_checkpoint,
        )
        check_actions, record_history, differentiable, grad_checkpoint = (
            _as_flag(name, value) for name, value in flags.items()
        )
        super().__init__(device=device, batch_size=batch_size)
        self.dtype = _as_dtype(dtype)
        self.num_envs = batch_size[0]
        self.params = resolve_params(
            self.Params,
            params,
            batch_size=self.num_envs,
            device=device,
            dtype=self.dtype,
            env_id=self.env_id,
        )
        # the observation size; continuous: the action dimension, discrete: the number
        # of choices
        # Checking action values needs a host-device synchronisation on accelerators;
        # a trusted training loop may switch it off there.
        self.check_actions = check_actions
        if grad_checkpoint and not differentiable:
            raise ValueError(f"{self.env_id}: grad_checkpoint=True needs differentiable=True")
        self.differentiable = differentiable
        # a named set of developed start states instead of the env's own start
        self.starts = start_sets.check(starts)
        # recompute each action's substeps in the backward pass instead of keeping them
        self.grad_checkpoint = grad_checkpoint
        self._warned_grad = False
        self.history = History(record_history)
        # a state given to set_state with a graph, not stepped yet: a reset would drop it
        self._traced_start = False
        if not differentiable:
            traced = [
                name
                for name, value in vars(self.params).items()
                if isinstance(value, torch.Tensor) and value.requires_grad
            ]
            if traced:
                why = "their gradients are dropped (make(..., differentiable=True) keeps them)"
                warnings.warn(
                    f"{self.env_id}: parameter(s) {traced} require grad but the env is not differentiable; {why}",
                    stacklevel=3,
                )
        self.physics = self.physics_type(self.params, self.num_envs, dtype=self.dtype, device=device)
        # the observation size; continuous: the action dimension, discrete: the number
        # of choices
        self.n_obs, self.n_actions = self.physics.n_obs, self.physics.n_actions
        # compiled, a whole step is this one call
        self._whole_step = self.physics.kernels(step)
        self._check_memory()
        self._make_specs()
        self._add_diagnostics_spec()
        self._closed = False
        if seed is None:
            seed = int(torch.empty((), dtype=torch.int64).random_().item()) % 2**63
        self.rng = torch.Generator(device=device)
        # TorchRL's random actions (a rollout without a policy), a stream of their own
        # so that they leave the physics' draws as they are
        self.action_rng = torch.Generator(device=device)
        self.set_seed(seed)
        self._state: State | None = None
        self._shapes: dict[str, torch.Size] | None = None
        self._diagnostics: dict[str, torch.Tensor] = {}
        self._count = torch.zeros(batch_size, dtype=torch.int64, device=device)

    def compile(self, *, warmup: int | None = None, **kwargs: Any) -> FlowEnv:
        """Run the physics kernels through ``torch.compile`` from now on; returns the
        env. ``make(..., compile=True)`` (or a dict of ``torch.compile`` options) calls
        this: unlike TorchRL's default, which traces the whole ``step_and_maybe_reset``,
        only the substeps are compiled, each into one fused graph with static shapes
        (``fullgraph=True, dynamic=False`` unless given; the cavities leave their
        transport sweep outside the graphs), so that the TorchRL step around them stays
        eager and flexible. ``warmup`` is accepted for TorchRL's signature and has
        nothing to do here."""
        self.physics.kernels.compile(**kwargs)
        return self

    def _check_memory(self) -> None:
        """Refuse a batch whose states would not fit in the device's free memory, before
        anything of its size is allocated."""
        free = available_bytes(self.device)
        need = self.num_envs * self.member_floats() * self.dtype.itemsize * WORKSPACE
        if free is not None and need > free:
            fits = max(1, free // (self.member_floats() * self.dtype.itemsize * WORKSPACE))
            raise ValueError(
                f"{self.env_id}: {self.num_envs:,} members need about {need / 2**30:,.1f} GiB on "
                f"{self.device}, {free / 2**30:,.1f} GiB are free; at most about {fits:,} members fit"
            )

    def to(self, *args, **kwargs) -> FlowEnv:
        """The env itself: its state, generator and kernels live on the device it was
        made on and in its dtype, so moving or converting it is refused
        (``make(..., device=..., dtype=...)`` builds one there)."""
        device, dtype = torch._C._nn._parse_to(*args, **kwargs)[:2]
        if device is not None and _as_device(device) != self.device:
            raise ValueError(
                f"{self.env_id}: an env stays on the device it was made on ({self.device}); "
                f"make(..., device={str(device)!r}) builds one on {device}"
            )
        if dtype is not None and dtype != self.dtype:
            name = str(dtype).removeprefix("torch.")
            raise ValueError(
                f"{self.env_id}: an env keeps the dtype it was made with ({self.dtype}); "
                f"make(..., dtype={name!r}) builds one in {name}"
            )
        return self

    def close(self, *, raise_if_closed: bool = True) -> None:
        """Free the state; stepping or resetting afterwards is an error."""
        self._closed = True
        self._state = None
        super().close(raise_if_closed=raise_if_closed)

    def _check_open(self, what: str) -> None:
        if self._closed:
            raise RuntimeError(f"{self.env_id}: {what}() on a closed env; make a new one")

    def state_dict(self, *args, destination=None, prefix: str = "", keep_vars: bool = False):
        """Where the env is: the state of every member (``state.<key>``), the actions
        taken in their episodes (``count``), the generators' states (``rng``,
        ``action_rng``) and the parameters it steps with (``params``);
        :meth:`load_state_dict` continues from there (an env of the same id, batch size
        and parameters)."""
        out = super().state_dict(*args, destination=destination, prefix=prefix, keep_vars=keep_vars)
        if self._state is not None:
            for key, value in self._state._asdict().items():
                out[f"{prefix}state.{key}"] = value if keep_vars else value.detach()
            out[f"{prefix}count"] = self._count.clone()
        out[f"{prefix}rng"] = self.rng.get_state()
        out[f"{prefix}action_rng"] = self.action_rng.get_state()
        out[f"{prefix}params"] = {
            f.name: getattr(self.params, f.name).detach().clone()
            if isinstance(getattr(self.params, f.name), torch.Tensor)
            else getattr(self.params, f.name)
            for f in dataclasses.fields(self.params)
        }
        return out

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Continue from :meth:`state_dict` (its state checked as :meth:`set_state`
        checks it, after the cast to this env's dtype). The parameters it records must
        be this env's (a state of other physics is refused); ``strict`` (the default)
        also requires every entry a stepped env's state dict has, and no other."""
        name = self.env_id or type(self).__name__
        if not isinstance(state_dict, dict):
            raise TypeError(f"{name}: a state dict is a dict (env.state_dict()), got {type(state_dict).__name__}")
        state = {key.removeprefix("state."): value for key, value in state_dict.items() if key.startswith("state.")}
        entries = ("count", "rng", "action_rng", "params")
        unknown = set(state_dict) - {f"state.{k}" for k in state} - set(entries)
        missing = [] if state else [f"state.{k}" for k in self.state_type._fields]
        missing += [key for key in entries if key not in state_dict and (key != "count" or state)]
        if strict and (unknown or missing):
            raise KeyError(
                f"{name}: the state dict has unknown entries {sorted(unknown)} and lacks {missing}; "
                f"load_state_dict(..., strict=False) loads what it holds"
            )
        if "params" in state_dict:
            self._check_same_params(state_dict["params"])
        generators = {key: getattr(self, key) for key in ("rng", "action_rng") if key in state_dict}
        for key, generator in generators.items():
            saved, own = state_dict[key], generator.get_state()
            if not isinstance(saved, torch.Tensor) or saved.dtype != torch.uint8 or saved.shape != own.shape:
                raise ValueError(
                    f"{name}: {key!r} must be a generator state of this device (a uint8 tensor "
                    f"of shape {tuple(own.shape)})"
                )
        if state:
            self.set_state(state, state_dict.get("count", 0))
        for key, generator in generators.items():
            generator.set_state(state_dict[key])
        return torch.nn.modules.module._IncompatibleKeys([], [])

    def _check_same_params(self, saved) -> None:
        """Refuse the parameters of a saved state dict that are not this env's."""
        name = self.env_id or type(self).__name__
        own = {f.name: getattr(self.params, f.name) for f in dataclasses.fields(self.params)}
        if not isinstance(saved, dict) or set(saved) != set(own):
            raise ValueError(f"{name}: the state dict's 'params' are not those of {name} ({sorted(own)})")
        for key, mine in own.items():
            theirs = saved[key]
            if isinstance(mine, torch.Tensor):
                same = (
                    isinstance(theirs, (torch.Tensor, int, float))
                    and not isinstance(theirs, bool)
                    and torch.as_tensor(theirs).numel() in (1, mine.numel())
                    and bool((torch.as_tensor(theirs).to(mine.device, mine.dtype) == mine.detach()).all())
                )
            else:
                same = type(theirs) is type(mine) and theirs == mine
            if not same:
                shown = theirs.tolist() if isinstance(theirs, torch.Tensor) and theirs.numel() < 8 else theirs
                raise ValueError(
                    f"{name}: the state dict was saved by an env with other parameters ({key} = {shown!r} there, "
                    f"{mine.tolist() if isinstance(mine, torch.Tensor) else mine!r} here); make the env with its "
                    f"parameters to continue it"
                )

    @property
    def state(self) -> State:
        """The current state tensors (read-only view; reset first)."""
        if self._state is None:
            raise RuntimeError(f"{self.env_id}: call reset() before reading the state")
        return self._state

    @property
    def observation(self) -> torch.Tensor:
        """The latest observation of every member (after a partial reset, TorchRL's
        ``reset`` returns zeros for the members that were not reset; this does not)."""
        if self._state is None:
            raise RuntimeError(f"{self.env_id}: call reset() before reading the observation")
        return self._obs

    @property
    def step_count(self) -> torch.Tensor:
        """Actions taken in the current episode, per member."""
        return self._count

    # ------------------------------------------------------------------ specs
    def _make_specs(self) -> None:
        B = self.batch_size
        dev = self.device
        self.observation_spec = Composite(
            observation=Unbounded(shape=(*B, self.n_obs), dtype=self.dtype, device=dev),
            shape=B,
            device=dev,
        )
        self.action_spec = self._action_leaf_spec((*B, *self.action_shape))
        self.reward_spec = Unbounded(shape=(*B, 1), dtype=self.dtype, device=dev)
        flag = lambda: Categorical(2, shape=(*B, 1), dtype=torch.bool, device=dev)
        self.done_spec = Composite(done=flag(), terminated=flag(), truncated=flag(), shape=B, device=dev)

    def _add_diagnostics_spec(self) -> None:
        """The diagnostics' entries, one number per member, under "diagnostics" beside
        the observation (after the env's own specs, which a layout may redefine)."""
        if not self.diagnostics:
            return
        B, dev = self.batch_size, self.device
        entries = {name: Unbounded(shape=B, dtype=self.dtype, device=dev) for name in self.diagnostics}
        self.observation_spec["diagnostics"] = Composite(entries, shape=B, device=dev)

    @property
    def last_diagnostics(self) -> dict[str, torch.Tensor]:
        """The :attr:`diagnostics` of the current state (``[batch]`` each), as the last
        reset or step left it."""
        if self._state is None:
            raise RuntimeError(f"{self.env_id}: call reset() before reading the diagnostics")
        return self._diagnostics

    def _action_leaf_spec(self, shape: tuple[int, ...]):
        if self.discrete:
            return Categorical(self.n_actions, shape=shape, dtype=torch.int64, device=self.device)
        return Bounded(low=-1.0, high=1.0, shape=shape, dtype=self.dtype, device=self.device)

    def _pack(self, obs: torch.Tensor, reward: torch.Tensor | None) -> dict:
        """TensorDict entries of an observation and a reward (multi-agent variants nest
        them)."""
        out = {"observation": obs}
        if reward is not None:
            out["reward"] = reward[:, None]
        return out

    # ------------------------------------------------------------------ seeding
    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            seed = int(torch.empty((), dtype=torch.int64).random_().item()) % 2**63
        self.rng.manual_seed(_as_seed(seed))
        self.action_rng.manual_seed(_as_seed(seed) ^ ACTION_STREAM)

    def rand_action(self, tensordict: TensorDictBase | None = None) -> TensorDictBase:
        """A uniformly random action of every member, written into ``tensordict`` (what
        TorchRL's ``rollout`` plays without a policy), drawn from :attr:`action_rng`:
        reproducible from the env's seed, and leaving the physics' draws from
        :attr:`rng` as they are."""
        if tensordict is None:
            tensordict = TensorDict({}, batch_size=self.batch_size, device=self.device)
        tensordict.set(self.action_key, self.random_action(self.action_rng))
        return tensordict

    # ------------------------------------------------------------------ actions
    def check_action(self, action: torch.Tensor | None) -> torch.Tensor:
        """Validate an action batch and bring it to the env's device/dtype.

        Continuous actions are clipped to [-1, 1]; NaN/inf, a wrong shape or a
        non-floating dtype raise. Discrete actions must be integers in [0, n).
        """
        action = self._action_form(action)
        taken, valid = self.physics.action_values(action)
        if self.check_actions and not bool(valid):
            self._refuse_values(action)
        return taken

    def _refuse_values(self, action: torch.Tensor) -> None:
        name = self.env_id or type(self).__name__
        if self.discrete:
            raise ValueError(f"{name}: action values must be in [0, {self.n_actions - 1}], got {action.tolist()}")
        raise ValueError(
            f"{name}: action contains NaN or inf; expected shape "
            f"{(*self.batch_size, *self.action_shape)} with values in [-1, 1]"
        )

    def _action_form(self, action: Any) -> torch.Tensor:
        """The action batch as a tensor of the env's device and dtype, its type and
        shape checked (its values are checked by :meth:`_action_values`)."""
        B = tuple(self.batch_size)
        name = self.env_id or type(self).__name__
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
        shape = (*B, *self.action_shape)
        if self.discrete:
            expected = f"shape {shape} with integer values in [0, {self.n_actions - 1}]"
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

    # ------------------------------------------------------------------ gradients
    def detach_state(self) -> None:
        """Cut the autograd graph at the current state (truncated backpropagation):
        later rewards are differentiated back to here, not further."""
        if self._state is None:
            raise RuntimeError(f"{self.env_id}: call reset() before detach_state()")
        self._state = map_state(torch.Tensor.detach, self._state)
        self._obs = self._obs.detach()

    def set_state(self, state: State | dict[str, torch.Tensor], count: int | torch.Tensor = 0) -> torch.Tensor:
        """Continue every member from ``state`` (an instance of the env's
        :attr:`state_type` like :attr:`state`, or a dict of its fields, e.g. saved from
        this env or another one of the same kind and batch size) with ``count`` actions
        already taken; returns the observation. Tensors that require grad are kept, so a
        differentiable env gives gradients with respect to the state."""
        name = self.env_id or type(self).__name__
        fields = self.state_type._fields
        if isinstance(state, self.state_type):
            state = state._asdict()
        if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
            raise TypeError(f"{name}: set_state needs a {self.state_type.__name__} of tensors like env.state")
        missing = sorted(set(fields) - set(state))
        extra = sorted(set(state) - set(fields))
        if missing or extra:
            raise KeyError(f"{name}: set_state needs the fields {list(fields)}; missing {missing}, unknown {extra}")
        shapes = self._field_shapes()
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
                stacklevel=2,
            )
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
        if not isinstance(count, torch.Tensor) and not 0 <= count < self.episode_length:
            raise ValueError(
                f"{name}: count must be in [0, {self.episode_length}) (actions already taken), got {count}"
            )
        count = torch.as_tensor(count, dtype=torch.int64, device=self.device)
        if bool(((count < 0) | (count >= self.episode_length)).any()):
            raise ValueError(
                f"{name}: count must be in [0, {self.episode_length}) (actions already taken), got {count.tolist()}"
            )
        # every state is of the env's dtype (integers given are cast), as its specs say;
        # its values are checked after the cast (1e39 is finite in float64 only)
        state = self.state_type(*(state[k].to(self.device, self.dtype) for k in fields))
        for key, value in state._asdict().items():
            if not bool(torch.isfinite(value.detach()).all()):
                raise ValueError(f"{name}: state.{key} has values that are not finite in {self.dtype}")
        with graph_mode(self.differentiable):
            obs = self.physics.observe(self.params, state)
        self._check_observation(obs)
        self._state, self._obs = _standard(state, obs)
        with graph_mode(self.differentiable):
            self._diagnostics = self.physics.diagnose(self.params, self._state)
        self._count = count.expand(self.batch_size).clone()
        self._traced_start = self.differentiable and bool(traced)
        return self._obs

    def _field_shapes(self) -> dict[str, torch.Size]:
        """The shape of each field of the state (the batch first): the current state's,
        or, before the first reset, that of a start computed once without drawing from
        the env's generator."""
        if self._state is not None:
            return {key: value.shape for key, value in self._state._asdict().items()}
        if self._shapes is None:
            rng = self.rng.get_state()
            try:
                with torch.no_grad():
                    start = self.physics.initial_state(self.params, self.rng)
            finally:
                self.rng.set_state(rng)
            self._shapes = {key: value.shape for key, value in start._asdict().items()}
        return self._shapes

    def _check_observation(self, obs: torch.Tensor) -> None:
        """Refuse an observation of another shape than the spec's (a physics whose
        ``observe`` disagrees with its ``sizes``)."""
        spec = self.observation_spec[self.observation_key].shape
        if obs.shape != spec:
            raise ValueError(
                f"{self.env_id}: observe() returned shape {tuple(obs.shape)}, the observation spec says "
                f"{tuple(spec)} (sizes() gives {self.n_obs} observations)"
            )

    # ------------------------------------------------------------------ the step itself
    # TorchRL's ``reset``/``step`` and the gymnasium and Stable-Baselines3 adapters all
    # go through these two, so every path runs the same checks and blow-up handling;
    # the adapters skip TensorDict construction and TorchRL's step wrappers, which at a
    # batch of one cost more than the physics of the fast envs.
    def reset_members(self, mask: torch.Tensor | None = None) -> torch.Tensor:
        """Start new episodes for the members where ``mask`` (``[batch]`` or
        ``[batch, 1]`` bool) is true, for all of them when it is None; returns the
        observation of every member (the others keep theirs)."""
        self._check_open("reset")
        if mask is not None:
            if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool:
                raise TypeError(
                    f"{self.env_id}: the '_reset' mask must be a bool tensor, got "
                    f"{getattr(mask, 'dtype', type(mask).__name__)}"
                )
            if mask.numel() != self.num_envs:
                raise ValueError(
                    f"{self.env_id}: the '_reset' mask must have one entry per member "
                    f"({self.num_envs}), got shape {tuple(mask.shape)}"
                )
            mask = mask.reshape(self.batch_size).to(self.device)
        if self._traced_start and (mask is None or bool(mask.any())):
            warnings.warn(
                f"{self.env_id}: this reset replaces the state given to set_state, and with it the gradient "
                f"with respect to that state; env.rollout resets first unless told not to: "
                f"env.rollout(n, policy, auto_reset=False, tensordict=env.current())",
                stacklevel=2,
            )
            self._traced_start = False
        with torch.no_grad():
            init = self.physics.initial_state(self.params, self.rng, mask)
        if type(init) is not self.state_type:
            raise TypeError(
                f"{self.env_id}: initial_state returned a {type(init).__name__}, not the env's "
                f"state type {self.state_type.__name__}"
            )
        if self.starts is not None:
            init = self._from_start_set()
        # in differentiable mode the members that go on keep their graph through a
        # partial reset; the new starts are data
        with graph_mode(self.differentiable):
            if mask is None or self._state is None:
                self._state = init
                self._count = torch.zeros_like(self._count)
            else:
                self._state = where_members(mask, init, self._state)
                self._count = torch.where(mask, torch.zeros_like(self._count), self._count)
            obs = self.physics.observe(self.params, self._state)
        with torch.no_grad():
            started = finite_members(obs)
            for value in self._state:
                if value.is_floating_point():
                    started = started & finite_members(value)
        if not bool(started.all()):
            bad = (~started).nonzero()[:, 0].tolist()
            raise ValueError(
                f"{self.env_id}: the initial state of batch member(s) {bad} is not finite; "
                f"check their parameters ({self.params})"
            )
        self._check_observation(obs)
        self._state, self._obs = _standard(self._state, obs)
        with graph_mode(self.differentiable):
            self._diagnostics = self.physics.diagnose(self.params, self._state)
        self.history.reset(self._state, mask)
        return obs

    def _from_start_set(self) -> State:
        """A start for every member from the env's start set: member ``i`` takes state
        ``i`` (modulo the set's size) of a validation or test set, a state drawn from
        the env's generator of the train set."""
        pool = start_sets.states(self, self.starts)
        size = pool[0].shape[0]
        if self.starts == "train":
            index = torch.randint(size, self.batch_size, generator=self.rng, device=self.device)
        else:
            index = torch.arange(self.num_envs, device=self.device) % size
        return self.state_type(*(value[index] for value in pool))

    def step_members(
        self, action: Any, stepping: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """One action of every member (of those where ``stepping`` is true, when
        given): ``(observation, reward, terminated, truncated)``, the reward as the
        physics gives it (``[batch]``, ``[batch, n_agents]`` for multi-agent variants),
        the two flags ``[batch]``. A member whose state leaves its bounds keeps its last
        finite state and observation, gets ``blowup_reward`` and is terminated."""
        self._check_open("step")
        if self._state is None:
            raise RuntimeError(f"{self.env_id}: call reset() before step()")
        if (
            isinstance(action, torch.Tensor)
            and action.requires_grad
            and not self.differentiable
            and not self._warned_grad
        ):
            self._warned_grad = True
            warnings.warn(
                f"{self.env_id}: the action requires grad but the env is not differentiable; its "
                f"gradient is dropped (make(..., differentiable=True) keeps it)",
                stacklevel=3,
            )
        action = self._action_form(action)
        if stepping is not None:
            if not isinstance(stepping, torch.Tensor) or stepping.dtype != torch.bool:
                raise TypeError(
                    f"{self.env_id}: the '_step' mask must be a bool tensor, got "
                    f"{getattr(stepping, 'dtype', type(stepping).__name__)}"
                )
            if stepping.numel() != self.num_envs:
                raise ValueError(
                    f"{self.env_id}: the '_step' mask must have one entry per member "
                    f"({self.num_envs}), got shape {tuple(stepping.shape)}"
                )
            stepping = stepping.reshape(self.batch_size).to(self.device)
        with torch.no_grad():
            noise = self.physics.noise(self.params, self.rng)
        inputs = (self.physics, self.params, self._state, action, noise, self._count, self._obs, stepping)
        with graph_mode(self.differentiable):
            if self.differentiable and torch.is_grad_enabled():
                out = step(*inputs, keep_graph=True, checkpoint=self.grad_checkpoint)
            else:
                # compiled, this is one call: the action's values, the physics, the
                # blow-up bookkeeping and the counters
                out = self._whole_step(*inputs)
        if self.check_actions and not bool(out.valid):
            self._refuse_values(action)
        self._state, self._obs, self._count, self._diagnostics = out.state, out.observation, out.count, out.diagnostics
        self._traced_start = False
        self.history.append(out.state)
        return out.observation, out.reward, out.terminated, out.truncated

    # ------------------------------------------------------------------ TorchRL API
    def rollout(self, max_steps: int, *args, **kwargs):
        """TorchRL's rollout of ``max_steps`` steps (a positive integer)."""
        if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
            raise ValueError(f"{self.env_id}: rollout needs a positive number of steps, got {max_steps!r}")
        return super().rollout(max_steps, *args, **kwargs)

    def _reset(self, tensordict: TensorDictBase | None, seed: int | None = None, **kwargs) -> TensorDictBase:
        # TorchRL passes ``set_state`` to envs that declare it; it means nothing here
        unknown = sorted(k for k in kwargs if k != "set_state")
        if unknown:
            raise TypeError(f"{self.env_id}: reset() takes a tensordict and seed=, got unknown keyword(s) {unknown}")
        if seed is not None:
            self.set_seed(seed)  # as set_seed would: the generators, then the episode
        self.reset_members(None if tensordict is None else tensordict.get("_reset", None))
        return self.current()

    def current(self) -> TensorDictBase:
        """The members' current observation as :meth:`reset` returns it, without
        resetting: where ``rollout(n, policy, auto_reset=False, tensordict=env.current())``
        starts, e.g. from a state given to :meth:`set_state` (whose gradient a reset
        would lose)."""
        if self._state is None:
            raise RuntimeError(f"{self.env_id}: call reset() or set_state() before current()")
        obs = self._obs
        false = torch.zeros((*self.batch_size, 1), dtype=torch.bool, device=self.device)
        return TensorDict(
            {
                **self._pack(obs, None),
                **self._diagnostics_entry(),
                "done": false,
                "terminated": false.clone(),
                "truncated": false.clone(),
            },
            batch_size=self.batch_size,
            device=self.device,
        )

    def _diagnostics_entry(self) -> dict:
        """The "diagnostics" entry of a TensorDict (none for an env without them)."""
        if not self.diagnostics:
            return {}
        return {"diagnostics": TensorDict(self._diagnostics, batch_size=self.batch_size, device=self.device)}

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs, reward, terminated, truncated = self.step_members(
            tensordict.get(self.action_key, None), tensordict.get("_step", None)
        )
        terminated, truncated = terminated[:, None], truncated[:, None]
        return TensorDict(
            {
                **self._pack(obs, reward),
                **self._diagnostics_entry(),
                "done": terminated | truncated,
                "terminated": terminated,
                "truncated": truncated,
            },
            batch_size=self.batch_size,
            device=self.device,
        )

    # ------------------------------------------------------------------ rendering
    @property
    def render_index(self) -> int:
        """The batch member that :meth:`render` draws (0 by default)."""
        return self.history.index

    @render_index.setter
    def render_index(self, index: int) -> None:
        if (
            isinstance(index, (bool, np.bool_))
            or not isinstance(index, (int, np.integer))
            or not 0 <= index < self.num_envs
        ):
            raise ValueError(
                f"{self.env_id}: render_index must be a member's index in [0, {self.num_envs}), got {index!r}"
            )
        self.history.index = int(index)

    def render(self) -> np.ndarray:
        """An RGB frame (``H x W x 3`` uint8) of member ``render_index``.

        With ``record_history=True`` the frame shows the episode so far (trajectories,
        space-time diagrams); without it, only the current state. The clock is the
        member's own either way: its actions since its last reset.
        """
        if self._state is None:
            raise RuntimeError(f"{self.env_id}: call reset() before render()")
        step = int(self._count[self.history.index])
        return self.render_frame(self.history.frames(self._state), step)

    def render_frame(self, history: list[State], step: int) -> np.ndarray:
        """The frame of the render member: ``history`` its states to draw (the episode
        so far with ``record_history=True``, else the current one), ``step`` the number
        of actions it has taken since its last reset (the clock of the last state)."""
        raise NotImplementedError

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(id={self.env_id!r}, batch_size={tuple(self.batch_size)}, "
            f"device={self.device}, dtype={self.dtype}, params={_short_params(self.params)})"
        )
