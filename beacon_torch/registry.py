"""Environment ids and their classes."""

from __future__ import annotations

import dataclasses
import importlib
import os
import re
import sys
from typing import Any

from beacon_torch import gym_ids
from beacon_torch.base import FlowEnv
from beacon_torch.core.checks import as_batch_size, as_device, as_dtype, check_memory
from beacon_torch.core.physics import Physics
from beacon_torch.envs.burgers import BurgersEnv
from beacon_torch.envs.cylinder import CylinderEnv
from beacon_torch.envs.ks import KSEnv
from beacon_torch.envs.lorenz import LorenzContinuousEnv, LorenzEnv
from beacon_torch.envs.mixing import MixingContinuousEnv, MixingEnv
from beacon_torch.envs.pinball import PinballChaoticEnv, PinballEnv, PinballPeriodicEnv
from beacon_torch.envs.rayleigh import RayleighEnv, RayleighSeparableEnv
from beacon_torch.envs.shkadov import ShkadovEnv, ShkadovSeparableEnv
from beacon_torch.envs.sloshing import SloshingEnv
from beacon_torch.envs.vortex import VortexEnv
from beacon_torch.params import check_params, resolve_params

ENVS: dict[str, type[FlowEnv]] = {
    cls.env_id: cls
    for cls in (
        LorenzEnv,
        LorenzContinuousEnv,
        VortexEnv,
        BurgersEnv,
        SloshingEnv,
        ShkadovEnv,
        ShkadovSeparableEnv,
        RayleighEnv,
        RayleighSeparableEnv,
        MixingEnv,
        MixingContinuousEnv,
        CylinderEnv,
        KSEnv,
        PinballEnv,
        PinballPeriodicEnv,
        PinballChaoticEnv,
    )
}


# parameters and options that make() uses for a registered id unless given
DEFAULTS: dict[str, dict[str, Any]] = {}
# the module that registered an id from outside the package, so that another process
# (a collector's worker) can import it again before building the env
ORIGIN: dict[str, str] = {}
# what make() takes beside an env's physical parameters
OPTIONS = ("compile", "differentiable", "grad_checkpoint", "record_history", "check_actions", "starts")


def register(env_id: str, env_class: type[FlowEnv], **defaults: Any) -> type[FlowEnv]:
    """Make an env available by id: :func:`make`, gymnasium's ``beacon/<id>`` (and
    ``make_vec``), the Stable-Baselines3 vector env, the conformance kit, the recipes
    (their collector processes import the registering module again) and the CLI (as
    ``module:env-id``, or with ``beacon-torch --import module``). ``env_class`` is a :class:`FlowEnv` subclass whose
    ``env_id`` is ``env_id`` (a new case), or a registered env's class: then the id is a
    variant of it, measured against it, whose ``defaults`` (physical parameters and
    :data:`OPTIONS`) :func:`make` uses unless told otherwise. Returns the registered
    class. Registering an id again with the same class and defaults does nothing."""
    if not isinstance(env_id, str) or not re.fullmatch(r"[a-z0-9][a-z0-9_.-]*-v[0-9]+", env_id):
        raise ValueError(f"an env id is lower-case words and a version, like 'heat-v0'; got {env_id!r}")
    if not (isinstance(env_class, type) and issubclass(env_class, FlowEnv)):
        raise TypeError(f"register needs a FlowEnv subclass, got {env_class!r}")
    if not env_class.env_id:
        raise ValueError(f"{env_class.__name__} declares no env_id (set env_id = {env_id!r} on the class)")
    state_type = getattr(env_class, "state_type", None)
    if not (isinstance(state_type, type) and issubclass(state_type, tuple) and hasattr(state_type, "_fields")):
        raise TypeError(
            f"{env_class.__name__} declares no state type (state_type = a NamedTuple of its state's tensors)"
        )
    known = {f.name for f in dataclasses.fields(env_class.Params)} | set(OPTIONS)
    unknown = sorted(set(defaults) - known)
    if unknown:
        raise ValueError(f"{env_id}: unknown default(s) {unknown}; {env_class.__name__} takes {sorted(known)}")
    # defaults that every make() would refuse are refused here, where they are given
    physics = {k: v for k, v in defaults.items() if k not in OPTIONS}
    try:
        check_params(env_class, physics)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{env_id}: its default parameters: {err}") from None
    for name in ("differentiable", "grad_checkpoint", "record_history", "check_actions"):
        if name in defaults and not isinstance(defaults[name], bool):
            raise TypeError(f"{env_id}: the default {name} must be True or False, got {defaults[name]!r}")
    if "compile" in defaults and not isinstance(defaults["compile"], (bool, dict)):
        raise TypeError(f"{env_id}: the default compile must be True, False or a dict of options")
    if env_class.env_id != env_id:
        if ENVS.get(env_class.env_id) is not env_class:
            raise ValueError(
                f"{env_class.__name__} is {env_class.env_id!r}, not {env_id!r}; a variant's base "
                f"must be registered first"
            )
        variant = ENVS.get(env_id)
        if variant is not None and variant.__mro__[1] is env_class and DEFAULTS.get(env_id) == defaults:
            return variant
        env_class = type(
            env_class.__name__ + "Variant", (env_class,), {"env_id": env_id, "__module__": env_class.__module__}
        )
    if env_id in ENVS:
        if ENVS[env_id] is env_class and DEFAULTS.get(env_id, {}) == defaults:
            return env_class
        raise ValueError(f"{env_id} is registered already (as {ENVS[env_id].__name__}); register a new version instead")
    ENVS[env_id] = env_class
    DEFAULTS[env_id] = dict(defaults)
    caller = sys._getframe(1).f_globals.get("__name__", "")
    if caller.split(".")[0] != "beacon_torch":
        ORIGIN[env_id] = caller
    gym_ids.register(env_id, env_class.episode_length)
    return env_class


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
    return [env_id for env_id, cls in ENVS.items() if cls.base_id() == env_id]


def continuous_envs() -> list[str]:
    """The package's own envs with continuous actions in their single-agent layout (the
    continuous twins of the discrete ones included), in the paper's order: what the
    gradient-based recipes and their benchmarks cover. Envs registered from outside
    the package are not among them."""
    return [
        env_id
        for env_id, cls in ENVS.items()
        if env_id not in ORIGIN and not cls.discrete and isinstance(cls.observation_key, str)
    ]


def env_class(env_id: str) -> type[FlowEnv]:
    """The class of a registered id (or of ``"module:env-id"``, :func:`resolve_id`)."""
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
    (``BurgersEnv.Params(amp=5.0)``, every field) or a dict of some of its fields
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
    cls = env_class(env_id)
    if batch_size is not None:
        if num_envs is not None:
            raise TypeError(f"{env_id}: give num_envs or batch_size (TorchRL's name for it), not both")
        num_envs = batch_size
    physics = params_dict(cls, params)
    sugar = {k: v for k, v in options.items() if k not in OPTIONS}
    twice = sorted(set(sugar) & set(physics))
    if twice:
        raise TypeError(f"{env_id}: parameter {twice[0]!r} given twice, in params and as a keyword")
    defaults = DEFAULTS.get(env_id, {})
    return cls(
        1 if num_envs is None else num_envs, device=device, dtype=dtype, seed=seed, **{**defaults, **physics, **options}
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
    cls = env_class(env_id)
    physical = params_dict(cls, params)
    twice = sorted(set(given) & set(physical))
    if twice:
        raise TypeError(f"{env_id}: parameter {twice[0]!r} given twice, in params and as a keyword")
    options = sorted(set(given) & set(OPTIONS))
    if options:
        raise TypeError(f"{env_id}: {options[0]!r} is an option of the env (make), not of its physics")
    defaults = {k: v for k, v in DEFAULTS.get(env_id, {}).items() if k not in OPTIONS}
    members = as_batch_size(1 if num_envs is None else num_envs)[0]
    device, dtype = as_device(device), as_dtype(dtype)
    resolved = resolve_params(
        cls.Params, {**defaults, **physical, **given}, batch_size=members, device=device, dtype=dtype, env_id=env_id
    )
    physics = cls.physics_type(resolved, members, dtype=dtype, device=device)
    check_memory(env_id, physics)  # before a state of that batch is ever allocated
    return physics, resolved


def params_dict(cls: type[FlowEnv], params: Any) -> dict[str, Any]:
    """The parameters given to :func:`make` as a dict: ``None``, a dict of names to
    values, or an instance of the env's own ``Params``, which is the whole physics (every
    field, a registered variant's defaults included)."""
    if params is None:
        return {}
    if isinstance(params, dict):
        names = [f.name for f in dataclasses.fields(cls.Params)]
        unknown = sorted(set(params) - set(names))
        if unknown:
            # an option among them too: params are the physics alone
            raise TypeError(
                f"unknown parameter {unknown[0]!r} of {cls.env_id} (got an unexpected keyword argument "
                f"{unknown[0]!r}); the parameters are: {', '.join(names)}"
            )
        return dict(params)
    if isinstance(params, cls.Params):
        return {f.name: getattr(params, f.name) for f in dataclasses.fields(params)}
    raise TypeError(
        f"{cls.env_id}: params must be a {cls.Params.__name__} (the env's Params) or a dict of its fields, "
        f"got {type(params).__name__}"
    )
