"""Cache of expensive initial states (developed films, excited tanks).

A state is a NamedTuple of tensors (an env's state type, or part of one), stored as a
dict of its fields and identified by a name and a key of the parameters that determine
it. It is looked up in memory (the library's one memo of starts: :func:`memo`, once per
process, and a copy per device and dtype asked for), then in the package data (the states of the
default parameters ship with the package), then in the user cache directory
(``$BEACON_TORCH_CACHE``, default ``~/.cache/beacon-torch``); on a miss it is computed by
the env's public generator function and written to the user cache.

A file that cannot be read, holds anything but tensors, has non-finite values, shapes
other than the ones expected or values beyond the bounds its case declares (the physical
bounds past which an episode ends: a start outside them would end every episode at its
first action) is reported in a warning and the state computed again (and the user
cache's file replaced): a damaged cache never breaks ``make()``.
"""

from __future__ import annotations

import hashlib
import json
import os
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from beacon_torch import received
from beacon_torch.core.state import State
from beacon_torch.files import save_tensors

PACKAGE_DATA = Path(__file__).parent / "data"
# every start read or computed in this process, by its file's name (and the device and
# dtype of a copy), and the published tables by their file
_memory: dict[tuple, Any] = {}


def memo(key: tuple, compute: Callable[[], Any]) -> Any:
    """``compute()`` the first time ``key`` is asked for in this process, what it gave
    after. ``key`` must name everything the value depends on (a file's name does: it
    hashes the parameters that determine the state)."""
    if key not in _memory:
        _memory[key] = compute()
    return _memory[key]


def cache_dir() -> Path:
    """``$BEACON_TORCH_CACHE`` when set to a path (an empty value is unset, not the
    working directory), else ``~/.cache/beacon-torch``."""
    return Path(os.environ.get("BEACON_TORCH_CACHE") or Path.home() / ".cache" / "beacon-torch")


def file_name(name: str, version: int, key: dict) -> str:
    """The file of the state ``name`` of generation ``version`` (a case's declared
    ``START_VERSION``) for the parameters ``key``."""
    keyed = {**key, "version": version}
    digest = hashlib.sha1(json.dumps(keyed, sort_keys=True, default=str).encode()).hexdigest()[:16]
    return f"{name}-{digest}.pt"


# per field, the least and greatest value a stored state may hold
Bounds = dict[str, tuple[float, float]]


def _load(path: Path, like: State, bounds: Bounds | None = None) -> State | None:
    """The state in ``path``, of ``like``'s type and shapes, within ``bounds``, or None
    (with a warning saying why) if it is unusable."""

    def check(state) -> None:
        problem = _problem(state, like, bounds or {})
        if problem is not None:
            raise ValueError(problem)

    try:
        # read within bounds, its shapes compared with ``like``'s before any copy
        state = received.torch_file(path, "cached state", check)
    except (OSError, ValueError) as err:
        warnings.warn(f"cached state {path}: {str(err).removeprefix(f'{path}: ')}; computing it again", stacklevel=3)
        return None
    return type(like)(**state)


def _problem(state, like: State, bounds: Bounds) -> str | None:
    if not isinstance(state, dict) or not all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items()
    ):
        return "not a dict of tensors"
    shapes = {key: tuple(value.shape) for key, value in like._asdict().items()}
    if set(state) != set(shapes):
        return f"keys {sorted(state)}, expected {sorted(shapes)}"
    for key, shape in shapes.items():
        if tuple(state[key].shape) != shape:
            return f"{key!r} has shape {tuple(state[key].shape)}, expected {shape}"
    for key, value in state.items():
        if value.is_complex() or not (value.is_floating_point() or value.dtype == like._asdict()[key].dtype):
            return f"{key!r} holds {value.dtype} values"
        if value.is_floating_point() and not bool(torch.isfinite(value.to(like._asdict()[key].dtype)).all()):
            return f"non-finite values in {key!r}"
    for key, (low, high) in bounds.items():
        value = state[key]
        if value.numel() and not (low <= float(value.min()) and float(value.max()) <= high):
            return (
                f"{key!r} holds values in [{float(value.min()):.4g}, {float(value.max()):.4g}], beyond its case's "
                f"bounds [{low:g}, {high:g}]"
            )
    return None


def save(state: State, path: Path) -> None:
    """Write atomically, so that concurrent processes never read half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    # a path that cannot be replaced (a folder of that name) removes the temporary file
    save_tensors({k: v.detach().cpu() for k, v in state._asdict().items()}, path)


def cached(
    name: str,
    version: int,
    key: dict,
    compute: Callable[[], State],
    like: State,
    bounds: Bounds | None = None,
    *,
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float64,
) -> State:
    """The state ``compute()`` returns (float64, or float32 where a bank of starts is kept
    so; on the CPU), computed at most once per
    key and machine, read at most once per process, and given on ``device`` in
    ``dtype`` (a copy made once per process). ``version`` is the case's declared
    generation of its starts (its module's ``START_VERSION``, raised whenever a change
    of the scheme changes them, so that no stale file is read). ``like`` is a cheap
    state of the same type and shapes (at rest, say): a stored file must have its
    fields and shapes, and its fields named in ``bounds`` their values within them."""
    fname = file_name(name, version, key)
    state = memo((fname,), lambda: _stored_or_computed(fname, name, key, compute, like, bounds))
    device = torch.device(device)
    # a state kept in float32 (a bank of starts) is given in float64 too
    if all(v.device == device and v.dtype == dtype for v in state):
        return state
    return memo((fname, str(device), dtype), lambda: type(state)(*(v.to(device=device, dtype=dtype) for v in state)))


def _stored_or_computed(
    fname: str, name: str, key: dict, compute: Callable[[], State], like: State, bounds: Bounds | None
) -> State:
    state = None
    for folder in (PACKAGE_DATA, cache_dir()):
        if (folder / fname).is_file():
            state = _load(folder / fname, like, bounds)
            if state is not None:
                break
    if state is None:
        # minutes for a developed start: said before, and how long it took after
        import sys
        import time

        where = ", ".join(f"{k}={v}" for k, v in key.items())
        print(
            f"beacon-torch: generating the {name} start ({where}) once; it is cached in {cache_dir()}",
            file=sys.stderr,
            flush=True,
        )
        began = time.perf_counter()
        state = type(like)(*(v.detach().cpu() for v in compute()))
        print(f"beacon-torch: {name} generated in {time.perf_counter() - began:.0f} s", file=sys.stderr, flush=True)
        try:
            save(state, cache_dir() / fname)
        except OSError:
            pass  # a read-only home only costs the recomputation next time
    return state
