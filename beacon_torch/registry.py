"""Environment ids: what each one names (a physics, its card, its default parameters,
its layout), and the physics of an id as functions.

An id is a registration, :class:`EnvSpec`: a case's module declares its physics and
its card as plain values, and :func:`register` names them, so a variant (a level, a
layout, the continuous twin of a discrete env) is a registration of its own and not a
class. This module imports torch and the case modules only: the TorchRL env of an id
is built by :func:`beacon_torch.make` (:mod:`beacon_torch.base`, the shell every env is).
"""

from __future__ import annotations

import dataclasses
import importlib
import os
import re
import sys
from collections.abc import Mapping
from typing import Any

from beacon_torch import gym_ids
from beacon_torch.core.card import Card
from beacon_torch.core.checks import as_batch_size, as_count, as_device, as_dtype, check_memory
from beacon_torch.core.physics import Physics
from beacon_torch.params import resolve_params, resolved

# what make() takes beside an env's physical parameters
OPTIONS = (
    "compile",
    "differentiable",
    "grad_checkpoint",
    "grad_checkpoint_after",
    "record_history",
    "check_actions",
    "starts",
)


@dataclasses.dataclass(frozen=True, eq=False)
class EnvSpec:
    """A registered id: its ``physics`` (a :class:`~beacon_torch.core.physics.Physics`
    subclass), its ``card``, the ``defaults`` :func:`make` uses unless told otherwise
    (physical parameters and :data:`OPTIONS`), the id it is a variant of (``base``,
    against whose scores and speed it is measured) and, for TorchRL's multi-agent
    layout, the name of an agent (``agents``; None: one agent per member)."""

    env_id: str
    physics: type[Physics]
    card: Card = Card()
    defaults: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    base: str | None = None
    agents: str | None = None

    def same(self, other: EnvSpec) -> bool:
        """Whether ``other`` registers what this does (registrations compare, and hash,
        by identity)."""
        fields = lambda s: (s.env_id, s.physics, s.card, dict(s.defaults), s.base, s.agents)
        return fields(self) == fields(other)

    def base_id(self) -> str:
        """The benchmark env this one is a variant of, or its own id."""
        return self.base or self.env_id

    def physical_defaults(self) -> dict[str, Any]:
        """The defaults that are parameters of the physics (not options of the env)."""
        return {k: v for k, v in self.defaults.items() if k not in OPTIONS}

    def check(self, params: dict[str, Any]) -> dict[str, Any]:
        """``params`` if they are parameters of this id with admissible values (beside
        its defaults; a clear error naming the parameter otherwise), for settings that
        build the env later."""
        resolved(self.physics.Params, {**self.physical_defaults(), **params}, self.env_id)
        return params

    def sizes(self, params: dict[str, Any] | None = None) -> tuple[int, int]:
        """``(n_obs, n_actions)`` of this id with ``params`` beside its defaults,
        before any env is built."""
        given = {**self.physical_defaults(), **(params or {})}
        return self.physics.sizes(resolved(self.physics.Params, given, self.env_id))


ENVS: dict[str, EnvSpec] = {}
# the module that registered an id from outside the package, so that another process
# (a collector's worker) can import it again before building the env
ORIGIN: dict[str, str] = {}


def register(
    env_id: str,
    physics: type[Physics] | EnvSpec,
    card: Card | None = None,
    *,
    base: str | None = None,
    agents: str | None = None,
    **defaults: Any,
) -> EnvSpec:
    """Make an env available by id: :func:`beacon_torch.make`, gymnasium's
    ``beacon/<id>`` (and ``make_vec``), the Stable-Baselines3 vector env, the conformance
    kit, the recipes (their collector processes import the registering module again)
    and the CLI (as ``module:env-id``, or with ``beacon-torch --import module``).

    ``physics`` is a :class:`~beacon_torch.core.physics.Physics` subclass (a new case,
    with its ``card``; ``base``, a registered id it is a variant of; ``agents``, an
    agent's name for TorchRL's multi-agent layout) or a registered id's
    :class:`EnvSpec`: then the id is a variant of it, with its physics, card (unless one
    is given) and layout, measured against it. ``defaults`` are physical parameters and
    :data:`OPTIONS` that :func:`make` uses unless told otherwise (a variant's add to its
    base's). Returns the registration. Registering an id again as it is does nothing."""
    if not isinstance(env_id, str) or not re.fullmatch(r"[a-z0-9][a-z0-9_.-]*-v[0-9]+", env_id):
        raise ValueError(f"an env id is lower-case words and a version, like 'heat-v0'; got {env_id!r}")
    if isinstance(physics, EnvSpec):
        if ENVS.get(physics.env_id) is not physics:
            raise ValueError(f"{env_id}: a variant's base must be registered first ({physics.env_id!r} is not)")
        if base is not None or agents is not None:
            raise TypeError(f"{env_id}: a variant of {physics.env_id} takes its base and layout from it")
        spec = physics
        physics, card, base, agents = spec.physics, spec.card if card is None else card, spec.env_id, spec.agents
        defaults = {**spec.defaults, **defaults}
    _check_physics(env_id, physics)
    card = Card() if card is None else card
    if not isinstance(card, Card):
        raise TypeError(f"{env_id}: card must be a beacon_torch.core.card.Card, got {type(card).__name__}")
    if base is not None and base not in ENVS:
        raise ValueError(f"{env_id}: its base {base!r} is not registered; a variant's base must be registered first")
    if agents is not None and not (isinstance(agents, str) and agents.isidentifier()):
        raise ValueError(f"{env_id}: agents must be an agent's name (an identifier), got {agents!r}")
    _check_defaults(env_id, physics, defaults)
    spec = EnvSpec(env_id, physics, card, dict(defaults), base, agents)
    if env_id in ENVS:
        if ENVS[env_id].same(spec):
            return ENVS[env_id]
        raise ValueError(f"{env_id} is registered already; register a new version instead")
    ENVS[env_id] = spec
    caller = sys._getframe(1).f_globals.get("__name__", "")
    if caller.split(".")[0] != "beacon_torch":
        ORIGIN[env_id] = caller
    gym_ids.register(env_id, physics.episode_length)
    return spec


def _check_physics(env_id: str, physics: Any) -> None:
    if not (isinstance(physics, type) and issubclass(physics, Physics)):
        raise TypeError(
            f"{env_id}: register needs a beacon_torch.Physics subclass or a registered EnvSpec, got {physics!r}"
        )
    state_type = getattr(physics, "state_type", None)
    if not (isinstance(state_type, type) and issubclass(state_type, tuple) and hasattr(state_type, "_fields")):
        raise TypeError(f"{physics.__name__} declares no state type (state_type = a NamedTuple of its state's tensors)")
    params = getattr(physics, "Params", None)
    if not (isinstance(params, type) and dataclasses.is_dataclass(params)):
        raise TypeError(f"{physics.__name__} declares no parameters (Params = a frozen dataclass of params)")
    length = getattr(physics, "episode_length", None)
    if isinstance(length, bool) or not isinstance(length, int) or length < 1:
        raise TypeError(f"{physics.__name__} declares no episode length (episode_length = a positive int)")


def _check_defaults(env_id: str, physics: type[Physics], defaults: dict[str, Any]) -> None:
    known = {f.name for f in dataclasses.fields(physics.Params)} | set(OPTIONS)
    unknown = sorted(set(defaults) - known)
    if unknown:
        raise ValueError(f"{env_id}: unknown default(s) {unknown}; {physics.__name__} takes {sorted(known)}")
    # defaults that every make() would refuse are refused here, where they are given
    try:
        resolved(physics.Params, {k: v for k, v in defaults.items() if k not in OPTIONS}, env_id)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{env_id}: its default parameters: {err}") from None
    for name in ("differentiable", "grad_checkpoint", "record_history", "check_actions"):
        if name in defaults and not isinstance(defaults[name], bool):
            raise TypeError(f"{env_id}: the default {name} must be True or False, got {defaults[name]!r}")
    as_count("the default grad_checkpoint_after", defaults.get("grad_checkpoint_after", 0), env_id)
    if "compile" in defaults and not isinstance(defaults["compile"], (bool, dict)):
        raise TypeError(f"{env_id}: the default compile must be True, False or a dict of options")


def resolve_id(env_id: str) -> str:
    """An env id as written by a user: ``"module:env-id"`` (gymnasium's spelling)
    imports ``module``, which registers the env, and gives ``env-id``; a plain id is
    itself."""
    if not isinstance(env_id, str):
        raise TypeError(f"env id must be a string, got {type(env_id).__name__}")
    module, sep, bare = env_id.rpartition(":")
    if sep:
        if not MODULE_NAME.fullmatch(module) or not bare:
            raise ValueError(
                f"env id {env_id[:80]!r}: an id is NAME-vN, or MODULE:NAME-vN with MODULE a Python module that "
                f"registers it, named as import names it (my_envs.heat:heat-v0)"
            )
        try:
            importlib.import_module(module)
        except (ImportError, SyntaxError) as err:
            raise ValueError(f"{env_id}: cannot import {module!r} to register it ({err})") from None
    return bare


# a module as ``import`` names it: dotted identifiers, no path, nothing relative
MODULE_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*")


def qualified_id(env_id: str) -> str:
    """The id as another process rebuilds it: ``"module:env-id"`` for an env that an
    importable module registered (not a script run as ``__main__``, which a spawned
    process runs again by itself), else the id."""
    origin = ORIGIN.get(env_id)
    return f"{origin}:{env_id}" if origin and origin not in ("__main__", "__mp_main__") else env_id


def list_envs() -> list[str]:
    """The registered environment ids, sorted."""
    return sorted(ENVS)


def base_envs() -> list[str]:
    """The benchmark's own envs, without their variants, in the paper's order."""
    return [env_id for env_id, spec in ENVS.items() if spec.base_id() == env_id]


def continuous_envs() -> list[str]:
    """The package's own envs with continuous actions in their single-agent layout (the
    continuous twins of the discrete ones included), in the paper's order: what the
    gradient-based recipes and their benchmarks cover. Envs registered from outside
    the package are not among them."""
    return [
        env_id
        for env_id, spec in ENVS.items()
        if env_id not in ORIGIN and not spec.physics.discrete and spec.agents is None
    ]


def env_spec(env_id: str) -> EnvSpec:
    """The registration of an id (or of ``"module:env-id"``, :func:`resolve_id`)."""
    env_id = resolve_id(env_id)
    try:
        return ENVS[env_id]
    except KeyError:
        raise ValueError(f"unknown env id {env_id!r}; available: {', '.join(list_envs())}") from None


def compiles_by_default() -> bool:
    """Whether the gymnasium and Stable-Baselines3 adapters and the training recipes
    compile their env when not told (``compile=...``, ``--no-compile``): yes, unless the
    environment variable ``BEACON_TORCH_COMPILE`` says no (``0``, ``false``, ``no`` or
    ``off``: a debugging session, a test suite that checks behaviour rather than speed);
    any other value than those and ``1``, ``true``, ``yes``, ``on`` or empty is refused."""
    value = os.environ.get("BEACON_TORCH_COMPILE", "").strip().lower()
    if value in ("", "1", "true", "yes", "on"):
        return True
    if value in ("0", "false", "no", "off"):
        return False
    raise ValueError(
        f"$BEACON_TORCH_COMPILE must be 1, true, yes or on (compile) or 0, false, no or off (eager), got "
        f"{os.environ['BEACON_TORCH_COMPILE'][:40]!r}"
    )


def functional(
    env_id: str,
    num_envs: int | None = None,
    *,
    device: Any = "cpu",
    dtype: Any = "float32",
    params: Any = None,
    **given: Any,
) -> tuple[Physics, Any]:
    """The physics of a registered id as functions, with no env around it:
    ``(physics, params)``, the case's :class:`~beacon_torch.core.physics.Physics` for
    ``num_envs`` members (default 1) on ``device`` in ``dtype``, and its parameters
    resolved as :func:`make` resolves them (``params`` or keywords; a variant's
    defaults), per-member values ``[num_envs]``.

    A rollout is then a loop of pure calls, as in gymnax::

        physics, params = beacon_torch.functional("burgers-v0", 8, dtype="float64")
        state = physics.initial_state(params, generator)
        obs = physics.observe(params, state)
        out = beacon_torch.step(physics, params, state, action, physics.noise(params, generator))

    and ``torch.func`` maps or differentiates it over parameter values
    (``dataclasses.replace(params, re=value)`` inside the mapped function). The grid
    and kernels are those of the parameters given here: a mapped value may change a
    per-member parameter, not the grid's size."""
    env_id = resolve_id(env_id)
    spec = env_spec(env_id)
    physical = params_dict(spec, params)
    twice = sorted(set(given) & set(physical))
    if twice:
        raise TypeError(f"{env_id}: parameter {twice[0]!r} given twice, in params and as a keyword")
    options = sorted(set(given) & set(OPTIONS))
    if options:
        raise TypeError(f"{env_id}: {options[0]!r} is an option of the env (make), not of its physics")
    defaults = spec.physical_defaults()
    members = as_batch_size(1 if num_envs is None else num_envs)[0]
    device, dtype = as_device(device), as_dtype(dtype)
    resolved = resolve_params(
        spec.physics.Params,
        {**defaults, **physical, **given},
        batch_size=members,
        device=device,
        dtype=dtype,
        env_id=env_id,
    )
    physics = spec.physics(resolved, members, dtype=dtype, device=device)
    check_memory(env_id, physics)  # before a state of that batch is ever allocated
    return physics, resolved


def params_dict(spec: EnvSpec, params: Any) -> dict[str, Any]:
    """The parameters given to :func:`make` as a dict: ``None``, a dict of names to
    values, or an instance of the env's own ``Params``, which is the whole physics (every
    field, a registered variant's defaults included)."""
    if params is None:
        return {}
    if isinstance(params, dict):
        names = [f.name for f in dataclasses.fields(spec.physics.Params)]
        unknown = sorted(set(params) - set(names))
        if unknown:
            # an option among them too: params are the physics alone
            raise TypeError(
                f"unknown parameter {unknown[0]!r} of {spec.env_id} (got an unexpected keyword argument "
                f"{unknown[0]!r}); the parameters are: {', '.join(names)}"
            )
        return dict(params)
    if isinstance(params, spec.physics.Params):
        return {f.name: getattr(params, f.name) for f in dataclasses.fields(params)}
    raise TypeError(
        f"{spec.env_id}: params must be a {spec.physics.Params.__name__} (the env's Params) or a dict of its fields, "
        f"got {type(params).__name__}"
    )


# the package's own ids, in the paper's order (then the cases beyond it)
from beacon_torch.envs import (  # noqa: E402 (the registry exists before the cases are named)
    burgers,
    cylinder,
    ks,
    lorenz,
    mixing,
    pinball,
    rayleigh,
    rbc2d,
    shkadov,
    sloshing,
    vortex,
)

register("lorenz-v0", lorenz.LorenzPhysics, lorenz.CARD)
register("lorenz-continuous-v0", lorenz.LorenzContinuousPhysics, lorenz.CONTINUOUS_CARD, base="lorenz-v0")
register("vortex-v0", vortex.VortexPhysics, vortex.CARD)
register("burgers-v0", burgers.BurgersPhysics, burgers.CARD)
register("sloshing-v0", sloshing.SloshingPhysics, sloshing.CARD)
register("shkadov-v0", shkadov.ShkadovPhysics, shkadov.CARD)
register("shkadov-separable-v0", shkadov.ShkadovSeparablePhysics, shkadov.CARD, base="shkadov-v0", agents="jet")
register("rayleigh-v0", rayleigh.RayleighPhysics, rayleigh.CARD)
register(
    "rayleigh-separable-v0",
    rayleigh.RayleighSeparablePhysics,
    rayleigh.SEPARABLE_CARD,
    base="rayleigh-v0",
    agents="segment",
)
register("mixing-v0", mixing.MixingPhysics, mixing.CARD)
register("mixing-continuous-v0", mixing.MixingContinuousPhysics, mixing.CONTINUOUS_CARD, base="mixing-v0")
register("cylinder-v0", cylinder.CylinderPhysics, cylinder.CARD)
register("ks-v0", ks.KSPhysics, ks.CARD)
register("pinball-v0", pinball.PinballPhysics, pinball.CARD)
register("pinball-periodic-v0", ENVS["pinball-v0"], pinball.PERIODIC_CARD, **pinball.PERIODIC)
register("pinball-chaotic-v0", ENVS["pinball-v0"], pinball.CHAOTIC_CARD, **pinball.CHAOTIC)
# FluidGym's three levels, each single- and multi-agent; the harder ones are the easy
# level's variants (one page, one parameter table)
_easy = register("rbc2d-easy-v0", rbc2d.Rbc2dPhysics, rbc2d.level_card("easy"), **rbc2d.LEVELS["easy"])
for _level, _settings in rbc2d.LEVELS.items():
    _card = rbc2d.level_card(_level)
    _single = _easy if _level == "easy" else register(f"rbc2d-{_level}-v0", _easy, _card, **_settings)
    register(
        f"rbc2d-{_level}-ma-v0",
        rbc2d.Rbc2dSeparablePhysics,
        _card,
        base=_single.env_id,
        agents="heater",
        **_settings,
    )
