"""``Physics``: what an env's equations are, apart from any env object.

A case's module declares a :class:`Physics` subclass: its parameters' dataclass
(``Params``), its state's NamedTuple (``state_type``), the episode's length, whether the
actions are discrete, and its hooks. Built for a batch size, a dtype and a device, it
derives what the fixed parameters give (grid, kernels, masks) once, in :meth:`setup`;
after that its hooks are functions of the parameters and the state. Every hook takes
the parameters as its first argument and reads of the physics object only what
``setup`` fixed, so that one step is one function of ``(physics, params, state,
action)`` (:func:`beacon_torch.core.step.step`): the TorchRL env steps it with its own
parameters, and ``torch.func`` maps or differentiates it over others.

The hooks, on a state of tensors whose leading dimension is the batch:

``sizes(params)`` (a class method)
    the observation size and the action size (continuous) or number of actions
    (discrete) that the parameters give;
``initial_state(params, generator, mask=None)``
    the state at the start of an episode for the whole batch;
``advance(params, state, action, count, noise)``
    the state after one action and the reward earned by it;
``observe(params, state)``
    the observation;

and optionally ``setup(params)``, ``noise(params, generator)`` (the random numbers of
one action: drawn before the step, so that a compiled step draws nothing),
``null_action()`` (the benchmark's "no control" action), ``out_of_bounds(params,
state)`` (physical bounds beyond finiteness), ``diagnose(params, state)`` (the
quantities named in ``diagnostics``) and ``state_like(params)`` (the start's shapes
without its cost). Their contracts are in their docstrings.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import Any, ClassVar

import torch

from beacon_torch.compiled import Kernels, member_vectors
from beacon_torch.core.state import Noise, State
from beacon_torch.core.step import advance_settled, settle


class Physics(abc.ABC):
    """The physics of a case for one batch size, dtype and device (see the module
    docstring)."""

    # the parameters' frozen dataclass (fields declared with ``beacon_torch.params.param``)
    Params: ClassVar[type]
    # the type of the state: a NamedTuple of tensors, batch first
    state_type: ClassVar[type]
    # actions per episode
    episode_length: ClassVar[int]
    discrete: ClassVar[bool] = False
    # reward of the step on which a member leaves its physical bounds (episode ends)
    blowup_reward: ClassVar[float] = -1.0
    # the physical quantities a flow-control user reads beside the reward, each one
    # number per member (name -> meaning), computed by ``diagnose``
    diagnostics: ClassVar[dict[str, str]] = {}
    # False where the physics draws from a generator (noisy inflows, random starts):
    # members then depend on the seed and on the batch size
    deterministic: ClassVar[bool] = True
    # inductor options of the compiled path: with the C++ wrapper a compiled call costs
    # a few microseconds instead of tens, and a while_loop's iteration runs in C++
    # rather than in the generated Python wrapper
    inductor_options: ClassVar[dict] = {"cpp_wrapper": True}
    # whether the fields' contiguous axis is the members (the 2-D flows' batch-last
    # layout): the compiled kernels' vectors are then as wide as a row of members fills
    # (:func:`~beacon_torch.compiled.member_vectors`)
    members_innermost: ClassVar[bool] = False
    # substeps a compiled call runs where autograd records (compile=True with
    # differentiable=True; see Kernels.loop): fewer calls, each with its fixed cost,
    # against a compilation that grows with the chunk
    grad_chunk: ClassVar[int] = 8
    # where autograd records on the compiled path, the whole action (the substeps
    # unrolled, the bounds, the observation, the containment of blow-ups) as one compiled
    # call differentiated as one graph: for an action of a few small substeps, whose
    # calls and eager glue around the graphs cost more than the graphs (its compilation
    # grows with the substeps; the graph's partitioner, not ``grad_checkpoint``, decides
    # what the backward pass keeps)
    grad_whole_action: ClassVar[bool] = False
    # where autograd records on the CPU (eager or compiled), the action runs as one C
    # loop a member and its backward pass as that loop's adjoint (the 1-D flows): the
    # two ways above then do not apply
    grad_action_in_c: ClassVar[bool] = False

    def __init__(
        self,
        params: Any,
        batch_size: int = 1,
        *,
        dtype: torch.dtype = torch.float32,
        device: str | torch.device = "cpu",
    ) -> None:
        self.num_envs = int(batch_size)
        self.batch_size = torch.Size((self.num_envs,))
        self.dtype = dtype
        self.device = torch.device(device)
        # the observation size; continuous: the action dimension, discrete: the number
        # of choices
        self.n_obs, self.n_actions = self.sizes(params)
        # the compiled path: which functions run through torch.compile, decided later
        options = dict(self.inductor_options)
        if self.members_innermost:
            options.update(member_vectors(self.num_envs, dtype, self.device))
        self.kernels = Kernels(options, chunk=self.grad_chunk)
        self.settle = self.kernels(settle)
        self.settled_action = self.kernels(advance_settled)
        with torch.no_grad():
            self.setup(params)

    # ------------------------------------------------------------------ hooks
    @classmethod
    @abc.abstractmethod
    def sizes(cls, params) -> tuple[int, int]:
        """``(n_obs, n_actions)`` with the parameters ``params``: the observation size
        per member (per agent for multi-agent layouts) and the action size
        (continuous) or number of actions (discrete)."""

    def setup(self, params) -> None:  # noqa: B027 (optional: most physics derive something)
        """Derive what the parameters fix (grid, kernels, masks; the substep loops
        through ``self.kernels``). Runs once, without autograd, and reads only what
        does not vary between steps (the grid's sizes, not a per-member or
        differentiable value: those are read by the hooks from their ``params``)."""

    @abc.abstractmethod
    def initial_state(self, params, generator: torch.Generator | None, mask: torch.Tensor | None = None) -> State:
        """The state at the start of an episode, for the whole batch: a
        :attr:`state_type` of tensors whose first dimension is the batch, in the
        physics' dtype and on its device. Random starts draw from ``generator``.
        ``mask`` (``[batch]`` bool, or None for all) says which members are being
        reset; the others' entries are discarded, so a costly start may compute only
        the masked members."""

    @abc.abstractmethod
    def advance(self, params, state: State, action: torch.Tensor, count: torch.Tensor, noise: Noise):
        """``(new_state, reward)`` after one action of the whole batch: ``action`` is in
        range (``[batch, *action_shape]``; int64 indices if discrete), ``count`` the
        actions already taken in each member's episode (``[batch]`` int64), ``noise``
        what :meth:`noise` drew for this action. The reward is ``[batch]``
        (``[batch, n_agents]`` for multi-agent layouts). Pure: no random draws and no
        host reads (``.item()``, Python branches on values), so that a compiled step is
        one graph; the state given is not modified in place."""

    @abc.abstractmethod
    def observe(self, params, state: State) -> torch.Tensor:
        """The observation of ``state``: ``[batch, n_obs]`` (``[batch, n_agents,
        n_obs]`` for multi-agent layouts), in the physics' dtype."""

    def state_like(self, params) -> State | None:
        """A state with the fields and shapes of a start, cheap to build (a flow at
        rest will do), for a physics whose start is costly (a developed flow, a run
        from it): what a state given before the first reset is checked against. None
        (the default): the env computes a start once to learn its shapes."""
        return None

    def noise(self, params, generator: torch.Generator | None) -> Noise:
        """The random numbers one action of the whole batch uses, drawn from
        ``generator`` (none for deterministic physics)."""
        return {}

    def null_action(self) -> torch.Tensor:
        """The benchmark's "no control" action, for the whole batch: zeros (action 0
        if discrete) unless the physics says otherwise."""
        dtype = torch.int64 if self.discrete else self.dtype
        return torch.zeros((*self.batch_size, *self.action_shape), dtype=dtype, device=self.device)

    def out_of_bounds(self, params, state: State) -> torch.Tensor:
        """``[batch]`` bool: the members whose state left its physical bounds (beyond
        non-finite values, which are always caught); their episode ends with
        ``blowup_reward``."""
        return torch.zeros(self.batch_size, dtype=torch.bool, device=self.device)

    def diagnose(self, params, state: State) -> dict[str, torch.Tensor]:
        """The :attr:`diagnostics` of ``state``: each a ``[batch]`` tensor in the
        physics' dtype (none by default). Pure, like :meth:`advance`."""
        return {}

    def member_floats(self) -> int:
        """About how many numbers one member's state holds, once ``setup()`` has run
        (what the memory of a batch is estimated from; fields override it)."""
        return 4 * self.n_obs

    # ------------------------------------------------------------------ helpers
    def remembered(self, key: Any, compute: Callable[[], Any]) -> Any:
        """``compute()`` the first time ``key`` is asked for, what it gave after: what
        this physics derives once from its set-up (the loads of its start, the shapes of
        its noise); ``key`` names the parameters it depends on, as a physics' hooks may
        be called with other parameters than the first ones (e.g. mapped by
        ``torch.func``). Starts themselves are kept once per process by
        :func:`beacon_torch.cache.cached`, the one memo of starts."""
        kept = self.__dict__.setdefault("_remembered", {})
        if key not in kept:
            kept[key] = compute()
        return kept[key]

    def recalled(self, key: Any) -> Any:
        """What :meth:`remembered` keeps for ``key``, or None (nothing is computed)."""
        return self.__dict__.get("_remembered", {}).get(key)

    @property
    def action_shape(self) -> tuple[int, ...]:
        """Per-member shape of the action: ``()`` for discrete, ``(n_actions,)`` else."""
        return () if self.discrete else (self.n_actions,)

    def action_values(self, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The action as the physics takes it (continuous: clipped to [-1, 1], as
        exploration noise leaves the box and the actuators saturate; discrete: kept in
        range, so that no table is indexed out of it) and whether all its values are
        admissible (a 0-dim bool tensor: read once, after a compiled step)."""
        if self.discrete:
            return action.clamp(0, self.n_actions - 1), ((action >= 0) & (action < self.n_actions)).all()
        return action.clamp(-1.0, 1.0), torch.isfinite(action).all()

    def random_action(self, generator: torch.Generator | None = None) -> torch.Tensor:
        """A uniformly random action batch drawn from ``generator``."""
        shape = (*self.batch_size, *self.action_shape)
        if self.discrete:
            return torch.randint(self.n_actions, shape, generator=generator, device=self.device)
        u = torch.rand(shape, generator=generator, dtype=self.dtype, device=self.device)
        return 2.0 * u - 1.0

    def member(self, value: torch.Tensor, dims: int = 1) -> torch.Tensor:
        """A per-member parameter ``[batch]`` shaped to broadcast against fields with
        ``dims`` dimensions after the batch: ``[batch, 1, ...]``."""
        return value.reshape(-1, *(1,) * dims)

    def tensor(self, value: Any) -> torch.Tensor:
        """A tensor on the physics' device and dtype."""
        return torch.as_tensor(value, dtype=self.dtype, device=self.device)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(batch_size={self.num_envs}, dtype={self.dtype}, device={self.device})"
