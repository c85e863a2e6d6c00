"""Cache of expensive initial states (developed films, excited tanks).

A state is a dict of tensors identified by a name and a key of the parameters that
determine it. It is looked up in memory, then in the package data (the states of the
default parameters ship with the package), then in the user cache directory
(``$BEACON_TORCH_CACHE``, default ``~/.cache/beacon-torch``); on a miss it is computed by
the env's public generator function and written to the user cache.

A file that cannot be read, holds anything but tensors, has non-finite values or shapes
other than the ones expected is reported in a warning and the state computed again (and
the user cache's file replaced): a damaged cache never breaks ``make()``.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from beacon_torch.files import replace_file

if TYPE_CHECKING:
    from beacon_torch.base import State

PACKAGE_DATA = Path(__file__).parent / "data"
_memory: dict[str, State] = {}


def cache_dir() -> Path:
    """``$BEACON_TORCH_CACHE`` when set to a path (an empty value is unset, not the
    working directory), else ``~/.cache/beacon-torch``."""
    return Path(os.environ.get("BEACON_TORCH_CACHE") or Path.home() / ".cache" / "beacon-torch")


def file_name(name: str, key: dict) -> str:
    digest = hashlib.sha1(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()[:16]
    return f"{name}-{digest}.pt"


def _load(path: Path, shapes: dict[str, tuple[int, ...]] | None) -> State | None:
    """The state in ``path``, or None (with a warning saying why) if it is unusable."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, EOFError, pickle.UnpicklingError, ValueError) as err:
        problem = f"unreadable ({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''})"
    else:
        problem = _problem(state, shapes)
    if problem is None:
        return state
    warnings.warn(f"cached state {path}: {problem}; computing it again", stacklevel=3)
    return None


def _problem(state, shapes: dict[str, tuple[int, ...]] | None) -> str | None:
    if not isinstance(state, dict) or not all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items()
    ):
        return "not a dict of tensors"
    for key, value in state.items():
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            return f"non-finite values in {key!r}"
    if shapes is not None:
        if set(state) != set(shapes):
            return f"keys {sorted(state)}, expected {sorted(shapes)}"
        for key, shape in shapes.items():
            if tuple(state[key].shape) != tuple(shape):
                return f"{key!r} has shape {tuple(state[key].shape)}, expected {tuple(shape)}"
    return None


def save(state: State, path: Path) -> None:
    """Write atomically, so that concurrent processes never read half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    # a path that cannot be replaced (a folder of that name) removes the temporary file
    replace_file(path, lambda tmp: torch.save({k: v.detach().cpu() for k, v in state.items()}, tmp))


def cached(
    name: str, key: dict, compute: Callable[[], State], shapes: dict[str, tuple[int, ...]] | None = None
) -> State:
    """The state ``compute()`` returns, computed at most once per key and machine;
    ``shapes``: the shape of each of its tensors, which a stored file must have."""
    fname = file_name(name, key)
    if fname in _memory:
        return _memory[fname]
    state = None
    for folder in (PACKAGE_DATA, cache_dir()):
        if (folder / fname).is_file():
            state = _load(folder / fname, shapes)
            if state is not None:
                break
    if state is None:
        state = {k: v.detach().cpu() for k, v in compute().items()}
        try:
            save(state, cache_dir() / fname)
        except OSError:
            pass  # a read-only home only costs the recomputation next time
    _memory[fname] = state
    return state
