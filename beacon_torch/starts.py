"""Start states: the ones stored with the published BEACON code, or our generators'.

Three envs of the published code (sloshing, shkadov, rayleigh) start every episode from a
state stored in a text file next to the env, not from one computed at run time, and the
published uncontrolled scores are properties of those files. They ship here unchanged
(``beacon_torch/data/*-published-start.dat``, MIT licence in ``data/NOTICE``) and are
each parsed once per process. Each of these envs has a ``start`` parameter:

- ``"published"``: the stored state (the default where the parameters are the
  published ones);
- ``"generated"``: the env's own public generator, run from the equations, cached (the
  default when a parameter that shapes the start differs from the published value,
  since the stored state belongs to the published grid and physics).

Start sets (:data:`SETS`, the ``starts`` option of ``make``): train, validation and test
episodes that begin from different points of the uncontrolled flow. The published envs
start every episode from one state (the paper's), so a policy is only ever judged from
where it was trained. A start set holds states of the developed,
uncontrolled dynamics instead, as FluidGym draws its episodes from snapshots of the
developed flow: state ``k`` of a set is where member ``k`` of the env, made with the
set's seed (its start and noise drawn from that seed, as ``make(..., seed=)`` draws
them) and left uncontrolled, stands after ``offsets[k]`` actions. The offsets lie in
``[0, episode_length)``, drawn from the same seed, and those of one set are all of one
residue modulo 3 (train 0, validation 1, test 2), so the three sets never share a
start even on an env without noise (lorenz-v0, vortex-v0), whose uncontrolled path from
the published start is one and the same. An env that draws its starts from a bank of
developed flows per set, as FluidGym's modes do (its ``domains`` parameter: the rbc2d
levels), takes a set's states from that set's own bank.

``make(env_id, n, starts="test")`` starts member ``i`` of every reset from state
``i mod size`` of the test set (the same episodes for every evaluation), and with
``starts="train"`` from a state drawn from the env's own generator at each reset. The
states are computed on first use, in the env's dtype and with its parameters (shared
by its members), and kept for the process.
"""

from __future__ import annotations

import math
from dataclasses import fields

import numpy as np
import torch

from beacon_torch import cache, received, seeds
from beacon_torch.cache import PACKAGE_DATA
from beacon_torch.params import number, param

PUBLISHED = "published"
GENERATED = "generated"


def start_param(doc: str):
    """The ``start`` field of a Params dataclass (None: decided by :func:`choose_start`)."""
    auto = "; None: the published one unless a parameter it was made with is changed"
    return param(None, kind="choice", choices=(PUBLISHED, GENERATED), doc=doc + auto)


def _differs(value, default) -> bool:
    if isinstance(value, str):
        return value != default
    if isinstance(value, torch.Tensor):
        # in the parameter's own dtype: a float32 9.81 is the default 9.81
        value = value.detach()
        return bool((value != torch.as_tensor(default, dtype=value.dtype, device=value.device)).any())
    return not math.isclose(number(value), default, rel_tol=0.0, abs_tol=0.0)


def choose_start(params, shaping: tuple[str, ...]) -> None:
    """Resolve ``params.start`` (in a Params ``__post_init__``): the published state
    unless one of the ``shaping`` parameters (those the stored state was made with)
    differs from its default; an explicit ``start="published"`` with such a parameter is
    an error that names it."""
    defaults = {f.name: f.default for f in fields(params)}
    changed = [name for name in shaping if _differs(getattr(params, name), defaults[name])]
    start = params.start
    # whether the start was left to this choice (then members whose own parameters are
    # the published ones may still start from the stored state: published_members)
    object.__setattr__(params, "start_chosen", start is None)
    if start is None:
        start = GENERATED if changed else PUBLISHED
    elif start == PUBLISHED and changed:
        name = changed[0]
        raise ValueError(
            f"parameter {name!r} = {getattr(params, name)!r} differs from the published start's "
            f"{defaults[name]!r}: the stored state belongs to the published parameters; "
            f"use start='generated' (or leave start unset)"
        )
    object.__setattr__(params, "start", start)


def published_members(params, shaping: tuple[str, ...]) -> torch.Tensor | None:
    """Per member, whether it may start from the stored state although the batch as a
    whole does not: the start was left to :func:`choose_start` and every ``shaping``
    parameter of the member is the published one (``g=[5, 9.81]``: the second member).
    None where no member may."""
    if not getattr(params, "start_chosen", False):
        return None
    defaults = {f.name: f.default for f in fields(params)}
    mask = None
    for name in shaping:
        value = getattr(params, name)
        if isinstance(value, torch.Tensor) and value.ndim == 1:
            same = value.detach() == torch.as_tensor(defaults[name], dtype=value.dtype, device=value.device)
            mask = same if mask is None else mask & same
        elif _differs(value, defaults[name]):
            return None
    return mask if mask is not None and bool(mask.any()) else None


# the longest line of a stored start: three or 52 numbers of 13 characters each
LINE_BYTES = 64 * 16


def _table(env: str, rows: int, columns: int) -> np.ndarray:
    path = PACKAGE_DATA / f"{env}-published-start.dat"
    # bounded by what the table holds before the text is parsed
    received.size_of(path, f"stored start of {env}", rows * max(columns, 4) * 16 + LINE_BYTES)
    try:
        table = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as err:
        raise received.BadFile(f"{path}: not a table of numbers ({str(err).splitlines()[0]})") from None
    if table.shape != (rows, columns) or not np.isfinite(table).all():
        raise received.BadFile(
            f"{path}: a table of {table.shape[0]} rows of {table.shape[1]} numbers, finite or not; "
            f"{env}'s start has {rows} rows of {columns} finite numbers (the file is damaged)"
        )
    table.setflags(write=False)
    return table


def published_table(env: str, rows: int, columns: int) -> torch.Tensor:
    """The stored start of ``env`` (sloshing, shkadov, rayleigh) as a float64 tensor of
    ``rows`` rows and ``columns`` columns, the shape the env's grid gives it (another
    shape is a damaged file, refused); the text is parsed once per process."""
    table = cache.memo((f"{env}-published-start.dat", rows, columns), lambda: _table(env, rows, columns))
    return torch.from_numpy(table.copy())


# ---------------------------------------------------------------- start sets
# name -> (seed, number of states, residue of the offsets modulo 3)
SETS = {
    "train": (202_611, 64, 0),
    "validation": (202_612, 8, 1),
    "test": (202_613, 8, 2),
}


def check(name):
    """``name`` if it names a start set (None: the env's own start)."""
    if name is not None and name not in SETS:
        raise ValueError(f"starts must be one of {', '.join(SETS)} (or None, the env's own start), got {name!r}")
    return name


def offsets(name: str, episode_length: int) -> torch.Tensor:
    """The actions after which each state of the set ``name`` is taken."""
    seed, size, residue = SETS[name]
    slots = max(1, (episode_length - residue + 2) // 3)  # values residue, residue + 3, ... below the length
    drawn = torch.randint(slots, (size,), generator=seeds.generator(seed))
    return torch.clamp(residue + 3 * drawn, max=episode_length - 1)


def shared_params(env) -> dict:
    """The env's parameters as values its members share; refused when they differ."""
    shared = {}
    for f in fields(env.params):
        value = getattr(env.params, f.name)
        if isinstance(value, torch.Tensor) and value.ndim >= 1:
            flat = value.detach().flatten()
            if flat.numel() and not bool((flat == flat[0]).all()):
                raise ValueError(
                    f"{env.env_id}: start sets need parameters shared by the members; {f.name} differs between them"
                )
            value = flat[0].item() if flat.numel() else value
        shared[f.name] = value
    return shared


def states(env, name: str):
    """The states of the set ``name`` for ``env`` (its id, dtype, device and
    parameters): the env's state type with the set's size as its batch."""
    params = tuple(sorted(shared_params(env).items()))
    return _computed(type(env), env.env_spec, name, str(env.dtype).removeprefix("torch."), str(env.device), params)


def _computed(shell, spec, name: str, dtype: str, device: str, params: tuple):
    # the set is computed once per process, in the one memo of starts
    return cache.memo(
        ("start set", spec, name, dtype, device, params), lambda: _run(shell, spec, name, dtype, device, params)
    )


def _run(shell, spec, name: str, dtype: str, device: str, params: tuple):
    seed, size, _ = SETS[name]
    params = dict(params)
    if "domains" in params:  # an env with a bank of developed flows per set: the set's own
        params["domains"] = name
    env = shell(spec, size, device=device, dtype=getattr(torch, dtype), seed=seed, **params)
    at = offsets(name, env.episode_length).to(env.device)
    kept = None
    with torch.no_grad():
        env.reset_members()
        for step in range(int(at.max()) + 1):
            if step:
                env.step_members(env.null_action())
            taken = at == step
            state = env.state
            if kept is None:
                kept = [torch.zeros_like(v) for v in state]
            for into, value in zip(kept, state, strict=True):
                into[taken] = value[taken]
    env.close()
    return env.physics.state_type(*kept)
