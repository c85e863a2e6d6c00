"""``FlowEnv``, the batched TorchRL environment every BEACON env is, and :func:`make`.

There is one env class: a shell around a registered id
(:class:`~beacon_torch.registry.EnvSpec`: a case's physics, its card, its layout). It
holds the batch size, device and dtype, the parameters, the seeded generators, the
specs, the current state and its counters, and steps them with the one step function
(:func:`~beacon_torch.core.step.step`), eagerly, compiled as one call, or keeping the
autograd graph. What a case knows of its equations (the hooks ``initial_state``,
``advance``, ``observe``, ...) lives on its physics (``env.physics``, with what it set
up: ``env.physics.n_cells``) and takes the parameters as an argument; what the library
knows of it beyond them (family, cost, the published code's speed, the paper's PPO
score, its gradient check, cheap settings for tests, its frame) is its card
(``env.card``), which benchmarks, reports and tests read instead of keeping lists of
envs. What is a concern of its own is a part the env calls with its inputs named:
where the entries of a TensorDict sit (``env.layout``), what it refuses of what it is
given (``env.guard``), a state dict's entries (:mod:`beacon_torch.core.saving`), the
states kept for rendering (``env.history``).

With ``differentiable=True`` the steps keep the autograd graph through the state, so the
rewards can be differentiated with respect to the actions, to parameters given as
tensors that require grad and to a state set by :meth:`FlowEnv.set_state`. Resets are
not differentiated: an episode starts from data (the published starts are developed by
long uncontrolled runs).
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from beacon_torch import seeds
from beacon_torch import starts as start_sets
from beacon_torch.autograd import graph_mode
from beacon_torch.compiled import step_inputs
from beacon_torch.core import saving
from beacon_torch.core.card import FrameInputs
from beacon_torch.core.checks import (
    Guard,
    as_batch_size,
    as_count,
    as_device,
    as_dtype,
    as_flag,
    as_seed,
    check_memory,
)
from beacon_torch.core.state import State, map_state, where_members
from beacon_torch.core.step import step
from beacon_torch.history import History
from beacon_torch.layout import Agents, Members
from beacon_torch.params import resolve_params, short_repr
from beacon_torch.registry import OPTIONS, EnvSpec, env_spec, params_dict, resolve_id


class FlowEnv(EnvBase):
    """A batched BEACON environment of a registered id (see the module docstring); built
    by :func:`make`."""

    def __init__(
        self,
        spec: EnvSpec,
        batch_size: int | tuple[int] = 1,
        *,
        device: str | torch.device = "cpu",
        dtype: str | torch.dtype = torch.float32,
        seed: int | None = None,
        check_actions: bool = True,
        record_history: bool = False,
        differentiable: bool = False,
        grad_checkpoint: bool = False,
        grad_checkpoint_after: int = 0,
        starts: str | None = None,
        **params: Any,
    ) -> None:
        if not isinstance(spec, EnvSpec):
            raise TypeError(f"FlowEnv takes a registered id's EnvSpec (beacon_torch.make builds one), got {spec!r}")
        # the id, its physics' type and its card: what the env is
        self.env_spec, self.env_id, self.card = spec, spec.env_id, spec.card
        batch_size = as_batch_size(batch_size)
        device = as_device(device)
        flags = dict(
            check_actions=check_actions,
            record_history=record_history,
            differentiable=differentiable,
            grad_checkpoint=grad_checkpoint,
        )
        check_actions, record_history, differentiable, grad_checkpoint = (
            as_flag(name, value) for name, value in flags.items()
        )
        super().__init__(device=device, batch_size=batch_size)
        self.dtype = as_dtype(dtype)
        self.num_envs = batch_size[0]
        self.params = resolve_params(
            spec.physics.Params,
            params,
            batch_size=self.num_envs,
            device=device,
            dtype=self.dtype,
            env_id=self.env_id,
        )
        # Checking action values needs a host-device synchronisation on accelerators;
        # a trusted training loop may switch it off there.
        self.check_actions = check_actions
        if grad_checkpoint and not differentiable:
            raise ValueError(f"{self.env_id}: grad_checkpoint=True needs differentiable=True")
        self.differentiable = differentiable
        # a named set of developed start states instead of the env's own start
        self.starts = start_sets.check(starts)
        # recompute each action's substeps in the backward pass instead of keeping them,
        # but for the first ``grad_checkpoint_after`` actions since the graph was last cut
        # (a reset of every member, detach_state): as many graphs kept whole as memory
        # allows cost no second forward pass
        self.grad_checkpoint = grad_checkpoint
        self.grad_checkpoint_after = as_count("grad_checkpoint_after", grad_checkpoint_after, self.env_id)
        if self.grad_checkpoint_after and not grad_checkpoint:
            raise ValueError(f"{self.env_id}: grad_checkpoint_after needs grad_checkpoint=True")
        self._kept_whole = 0
        self.history = History(record_history)
        # a state given to set_state with a graph, not stepped yet: a reset would drop it
        self._traced_start = False
        self.physics = spec.physics(self.params, self.num_envs, dtype=self.dtype, device=device)
        # what it is given while it runs is checked by a guard of its own
        self.guard = Guard(self.env_id, self.physics, differentiable)
        self.guard.traced_params(self.params)
        # the observation size; continuous: the action dimension, discrete: the number
        # of choices
        self.n_obs, self.n_actions = self.physics.n_obs, self.physics.n_actions
        # where the action is read from and the observation and reward written to
        # (nested keys for the multi-agent layout)
        if spec.agents is None:
            self.layout = Members(self.batch_size, device, self.dtype)
        else:
            self.layout = Agents(spec.agents, self.physics.action_shape[0], self.batch_size, device, self.dtype)
        # compiled, a whole step is this one call
        self._whole_step = self.physics.kernels(step)
        check_memory(self.env_id, self.physics)
        self._make_specs()
        self._add_diagnostics_spec()
        self._closed = False
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
        """Run the step through ``torch.compile`` from now on; returns the env.
        ``make(..., compile=True)`` (or a dict of ``torch.compile`` options) calls this:
        unlike TorchRL's default, which traces the whole ``step_and_maybe_reset``, only
        the step function is compiled, into one graph with static shapes
        (``fullgraph=True, dynamic=False`` unless given; its substep loops become
        ``while_loop``s), so that the TorchRL step around it stays eager and flexible.
        ``warmup`` is accepted for TorchRL's signature and has nothing to do here."""
        self.physics.kernels.compile(**kwargs)
        return self

    def to(self, *args, **kwargs) -> FlowEnv:
        """The env itself: its state, generator and kernels live on the device it was
        made on and in its dtype, so moving or converting it is refused
        (``make(..., device=..., dtype=...)`` builds one there)."""
        device, dtype = torch._C._nn._parse_to(*args, **kwargs)[:2]
        if device is not None and as_device(device) != self.device:
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

    def _check_open(self, what: str) -> None:
        if self._closed:
            raise RuntimeError(f"{self.env_id}: {what}() on a closed env; make a new one")

    def close(self, *, raise_if_closed: bool = True) -> None:
        """Free the state; stepping or resetting afterwards is an error."""
        self._closed = True
        self._state = None
        super().close(raise_if_closed=raise_if_closed)

    @property
    def discrete(self) -> bool:
        """Whether the actions are choices (an integer per member) rather than values."""
        return self.physics.discrete

    @property
    def episode_length(self) -> int:
        """Actions per episode: a member's episode is truncated after them."""
        return self.physics.episode_length

    @property
    def diagnostics(self) -> dict[str, str]:
        """The physical quantities given beside the reward (name -> meaning), under
        "diagnostics" in the TensorDicts, one number per member each."""
        return self.physics.diagnostics

    @property
    def action_key(self) -> str | tuple[str, ...]:
        """Where the action is read from (``("agents", "action")`` in the multi-agent
        layout)."""
        return self.layout.action_key

    @property
    def observation_key(self) -> str | tuple[str, ...]:
        """Where the observation is written."""
        return self.layout.observation_key

    @property
    def reward_key(self) -> str | tuple[str, ...]:
        """Where the reward is written."""
        return self.layout.reward_key

    @property
    def agent_name(self) -> str | None:
        """An agent's name in the multi-agent layout (PettingZoo's agents are
        ``f"{agent_name}_{i}"``); None with one agent per member."""
        return self.layout.agent_name

    @property
    def n_agents(self) -> int:
        """Agents per member: the physics' actuators in the multi-agent layout, else 1."""
        return self.layout.n_agents

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
    def _observation_shape(self) -> torch.Size:
        return self.observation_spec[self.observation_key].shape

    def _field_shapes(self) -> dict[str, torch.Size]:
        """The shape of each field of the state (the batch first): the current state's,
        or, before the first reset, that of the physics' :meth:`~beacon_torch.core.physics.Physics.state_like`, or else
        that of a start computed once without drawing from the env's generator."""
        if self._state is not None:
            return {key: value.shape for key, value in self._state._asdict().items()}
        if self._shapes is None:
            with torch.no_grad():
                like = self.physics.state_like(self.params)
            if like is None:
                rng = self.rng.get_state()
                try:
                    with torch.no_grad():
                        like = self.physics.initial_state(self.params, self.rng)
                finally:
                    self.rng.set_state(rng)
            self._shapes = {key: value.shape for key, value in like._asdict().items()}
        return self._shapes

    def _make_specs(self) -> None:
        B = self.batch_size
        dev = self.device
        for name, spec in self.layout.specs(self.n_obs, self.action_shape, self._action_leaf_spec).items():
            setattr(self, name, spec)
        flag = lambda: Categorical(2, shape=(*B, 1), dtype=torch.bool, device=dev)
        self.done_spec = Composite(done=flag(), terminated=flag(), truncated=flag(), shape=B, device=dev)

    def _add_diagnostics_spec(self) -> None:
        """The diagnostics' entries, one number per member, under "diagnostics" beside
        the observation."""
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

    # ------------------------------------------------------------------ seeding
    def _set_seed(self, seed: int | None) -> None:
        seed = seeds.fresh() if seed is None else as_seed(seed)
        self.rng.manual_seed(seed)
        self.action_rng.manual_seed(seeds.actions(seed))

    @property
    def action_shape(self) -> tuple[int, ...]:
        """Per-member shape of the action: ``()`` for discrete, ``(n_actions,)`` else."""
        return self.physics.action_shape

    def null_action(self) -> torch.Tensor:
        """The benchmark's "no control" action of every member (the physics')."""
        return self.physics.null_action()

    def random_action(self, generator: torch.Generator | None = None) -> torch.Tensor:
        """A uniformly random action batch (from ``generator``, not the env's own, so
        that a random policy does not shift the env's random stream)."""
        return self.physics.random_action(generator)

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
        action = self.guard.action(action)
        taken, valid = self.physics.action_values(action)
        if self.check_actions and not bool(valid):
            self.guard.refuse_values(action)
        return taken

    # ------------------------------------------------------------------ gradients
    def detach_state(self) -> None:
        """Cut the autograd graph at the current state (truncated backpropagation):
        later rewards are differentiated back to here, not further."""
        if self._state is None:
            raise RuntimeError(f"{self.env_id}: call reset() before detach_state()")
        self._state = map_state(torch.Tensor.detach, self._state)
        self._obs = self._obs.detach()
        self._kept_whole = 0

    def set_state(self, state: State | dict[str, torch.Tensor], count: int | torch.Tensor = 0) -> torch.Tensor:
        """Continue every member from ``state`` (an instance of the env's
        :attr:`state_type` like :attr:`state`, or a dict of its fields, e.g. saved from
        this env or another one of the same kind and batch size) with ``count`` actions
        already taken; returns the observation. Tensors that require grad are kept, so a
        differentiable env gives gradients with respect to the state."""
        state, traced = self.guard.state(state, self._field_shapes())
        count = self.guard.count(count)
        with graph_mode(self.differentiable):
            obs = self.physics.observe(self.params, state)
        self.guard.observation(obs, self._observation_shape())
        self._state, self._obs = step_inputs(state, obs)
        with graph_mode(self.differentiable):
            self._diagnostics = self.physics.diagnose(self.params, self._state)
        self._count = count.expand(self.batch_size).clone()
        self._traced_start = self.differentiable and bool(traced)
        return self._obs

    # ------------------------------------------------------------------ saving
    def state_dict(self, *args, destination=None, prefix: str = "", keep_vars: bool = False):
        """Where the env is: the state of every member (``state.<key>``), the actions
        taken in their episodes (``count``), the generators' states (``rng``,
        ``action_rng``) and the parameters it steps with (``params``);
        :meth:`load_state_dict` continues from there (an env of the same id, batch size
        and parameters)."""
        out = super().state_dict(*args, destination=destination, prefix=prefix, keep_vars=keep_vars)
        generators = {"rng": self.rng, "action_rng": self.action_rng}
        out.update(saving.entries(self._state, self._count, generators, self.params, prefix, keep_vars))
        return out

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Continue from :meth:`state_dict` (its state checked as :meth:`set_state`
        checks it, after the cast to this env's dtype). The parameters it records must
        be this env's (a state of other physics is refused); ``strict`` (the default)
        also requires every entry a stepped env's state dict has, and no other."""
        generators = {"rng": self.rng, "action_rng": self.action_rng}
        fields = self.physics.state_type._fields
        state, count, saved = saving.read(state_dict, self.env_id, fields, self.params, generators, strict)
        if state:
            self.set_state(state, count)
        for key, value in saved.items():
            generators[key].set_state(value)
        return torch.nn.modules.module._IncompatibleKeys([], [])

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
        mask = self.guard.members_mask(mask, "_reset")
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
        self.guard.start_type(init)
        if self.starts is not None:
            init = self._from_start_set()
        # in differentiable mode the members that go on keep their graph through a
        # partial reset; the new starts are data
        with graph_mode(self.differentiable):
            if mask is None or self._state is None:
                self._state = init
                self._count = torch.zeros_like(self._count)
                self._kept_whole = 0
            else:
                self._state = where_members(mask, init, self._state)
                self._count = torch.where(mask, torch.zeros_like(self._count), self._count)
            obs = self.physics.observe(self.params, self._state)
        self.guard.start(self._state, obs, self.params, self._observation_shape())
        self._state, self._obs = step_inputs(self._state, obs)
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
        return self.physics.state_type(*(value[index] for value in pool))

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
        self.guard.dropped_gradient(action)
        action = self.guard.action(action)
        stepping = self.guard.members_mask(stepping, "_step")
        with torch.no_grad():
            noise = self.physics.noise(self.params, self.rng)
        inputs = (self.physics, self.params, self._state, action, noise, self._count, self._obs, stepping)
        with graph_mode(self.differentiable):
            if self.differentiable and torch.is_grad_enabled():
                recompute = self.grad_checkpoint and self._kept_whole >= self.grad_checkpoint_after
                self._kept_whole += not recompute
                out = step(*inputs, keep_graph=True, checkpoint=recompute)
            else:
                # compiled, this is one call: the action's values, the physics, the
                # blow-up bookkeeping and the counters
                out = self._whole_step(*inputs)
        if self.check_actions and not bool(out.valid):
            self.guard.refuse_values(action)
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
                **self.layout.pack(obs, None),
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
                **self.layout.pack(obs, reward),
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

    def render_frame(self, states: list[State], step: int) -> np.ndarray:
        """The card's frame of member :attr:`render_index`, drawn from ``states``
        (:class:`~beacon_torch.core.card.FrameInputs`)."""
        if self.card.frame is None:
            raise NotImplementedError(f"{self.env_id}: its card has no frame to draw")
        inputs = FrameInputs(self.physics, self.params, self.render_index, states, step, self.history.enabled)
        return self.card.frame(inputs)

    def __repr__(self) -> str:
        return (
            f"FlowEnv(id={self.env_id!r}, batch_size={tuple(self.batch_size)}, "
            f"device={self.device}, dtype={self.dtype}, params={short_repr(self.params)})"
        )


def make(
    env_id: str,
    num_envs: int | None = None,
    *,
    device: Any = "cpu",
    dtype: Any = "float32",
    seed: int | None = None,
    params: Any = None,
    batch_size: int | None = None,
    **options: Any,
) -> FlowEnv:
    """Build a batched BEACON environment.

    ``num_envs`` members are stepped together (default 1; ``batch_size`` is TorchRL's
    name for the same number, accepted as TorchRL users write it); ``device`` and
    ``dtype`` (float32 or float64) place the state; ``seed`` seeds the env's own
    generator. ``params`` is the physics, a value: an instance of the env's ``Params``
    (``beacon_torch.envs.burgers.BurgersParams(amp=5.0)``, every field) or a dict of some of its fields
    (``{"amp": 5.0}``, the others at their defaults; ``beacon-torch list``,
    ``docs/envs``). A parameter may also be given as a keyword
    (``make("burgers-v0", amp=5.0)``). The other keywords are the options every env
    has:

    ``compile``
        True (or a dict of ``torch.compile`` options) runs each step as one compiled
        call (:meth:`FlowEnv.compile`); default False, eager (the gymnasium and
        Stable-Baselines3 adapters default to True).
    ``differentiable``
        True keeps the autograd graph through the steps, so that rewards can be
        differentiated with respect to actions, parameters and states; default False
        (no graph).
    ``grad_checkpoint``
        with ``differentiable``, recompute each action's substeps in the backward pass
        instead of keeping them (the memory of a differentiated episode becomes one
        state per action); default False.
    ``grad_checkpoint_after``
        with ``grad_checkpoint``, keep the graphs of the first N actions since the graph
        was last cut (a reset of every member, :meth:`FlowEnv.detach_state`) whole and
        recompute only the later ones: each action kept whole saves a second forward
        pass for the memory of its graph; default 0 (every action recomputed).
    ``record_history``
        True keeps member ``render_index``'s states since its reset, so that
        ``render()`` draws the episode so far; default False (the current state only).
    ``check_actions``
        False skips the check of action values (NaN, range), which synchronises with
        an accelerator on every step; default True.
    ``starts``
        ``"train"``, ``"validation"`` or ``"test"``: every episode starts from a state
        of that set of developed, uncontrolled states (:mod:`beacon_torch.starts`)
        instead of the env's own start; default None (the env's own, the paper's).
    """
    env_id = resolve_id(env_id)
    spec = env_spec(env_id)
    if batch_size is not None:
        if num_envs is not None:
            raise TypeError(f"{env_id}: give num_envs or batch_size (TorchRL's name for it), not both")
        num_envs = batch_size
    physics = params_dict(spec, params)
    sugar = {k: v for k, v in options.items() if k not in OPTIONS}
    twice = sorted(set(sugar) & set(physics))
    if twice:
        raise TypeError(f"{env_id}: parameter {twice[0]!r} given twice, in params and as a keyword")
    given = {**spec.defaults, **physics, **options}
    env = FlowEnv(spec, 1 if num_envs is None else num_envs, device=device, dtype=dtype, seed=seed, **given)
    return env
