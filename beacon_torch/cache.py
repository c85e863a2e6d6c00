"""Cache of expensive initial states (developed films, excited tanks).

A state is a dict of tensors identified by a name and a key of the parameters that
determine it. It is looked up in memory, then in the package data (the states of the
default parameters ship with the package), then in the user cache directory
(``$BEACON_TORCH_CACHE``, default ``~/.cache/beacon-torch``); on a miss it is computed by
the env's public generator function and written to the user cache.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import torch

State = dict[str, torch.Tensor]

PACKAGE_DATA = Path(__file__).parent / "data"
_memory: dict[str, State] = {}


def cache_dir() -> Path:
    return Path(os.environ.get("BEACON_TORCH_CACHE", Path.home() / ".cache" / "beacon-torch"))


def file_name(name: str, key: dict) -> str:
    digest = hashlib.sha1(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()[:16]
    return f"{name}-{digest}.pt"


def _load(path: Path) -> State | None:
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, EOFError):
        return None


def save(state: State, path: Path) -> None:
    """Write atomically, so that concurrent processes never read half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".tmp", delete=False) as tmp:
        torch.save({k: v.detach().cpu() for k, v in state.items()}, tmp)
    os.replace(tmp.name, path)


def cached(name: str, key: dict, compute: Callable[[], State]) -> State:
    """The state ``compute()`` returns, computed at most once per key and machine."""
    fname = file_name(name, key)
    if fname in _memory:
        return _memory[fname]
    state = None
    for folder in (PACKAGE_DATA, cache_dir()):
        if (folder / fname).is_file():
            state = _load(folder / fname)
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
