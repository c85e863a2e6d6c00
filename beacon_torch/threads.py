"""How many threads torch uses inside a step: the count measured fastest for the env
and batch size on an idle machine, unless told otherwise.

Torch's default is one thread per core. On an idle machine that is often right for the
2-D flows and wrong for the small ones, whose steps are too short to share; on a
machine where another process holds a core it can be far slower than one thread (the
threads wait on each other). The recipes and the ``beacon-torch`` commands therefore
take ``--threads N``; without it they take, in this order, ``$BEACON_TORCH_THREADS``,
the count that ``benchmarks/threads.py`` measured fastest on an idle machine
(``data/threads.json``, no more than this machine's cores) for the env's training (the
recipes: collection and network updates) or for its step at the nearest measured batch
size (the commands, which only step envs), or torch's default. On a shared machine
give ``--threads 1``.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

TABLE = Path(__file__).parent / "data" / "threads.json"
# the batch sizes measured (benchmarks/threads.py)
BATCHES = (1, 16, 64)


@functools.cache
def _table() -> dict:
    from beacon_torch import received

    try:
        table = received.json_file(TABLE, "table of thread counts")
    except (OSError, ValueError):
        return {}
    return table if isinstance(table, dict) else {}


def _count(value) -> int | None:
    return value if isinstance(value, int) and not isinstance(value, bool) and value >= 1 else None


def fastest(env_id: str, batch: int, training: bool = False) -> int | None:
    """The thread count measured fastest for ``env_id`` (its base env's physics): its
    step at the measured batch size nearest to ``batch`` (on a log scale), or with
    ``training`` its recipe's training (PPO at the recipe's defaults: collection and
    network updates); at most this machine's cores, None where it was not measured."""
    from beacon_torch.registry import env_spec

    env = env_spec(env_id).base_id()
    if training:
        count = _count((_table().get("training") or {}).get(env))
        return None if count is None else min(count, cores())
    measured = (_table().get("steps") or {}).get(env, {})
    sizes = [int(b) for b in measured if str(b).isdigit() and _count(measured[b])]
    if not sizes:
        return None
    nearest = min(sizes, key=lambda b: (abs(_log(b) - _log(batch)), b))
    return min(measured[str(nearest)], cores())


def _log(n: int) -> float:
    import math

    return math.log(max(n, 1))


def cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def check(count, what: str = "threads", zero: str = "") -> int:
    """``count`` if it is a thread count this machine can use: a positive integer up to
    its cores (0 too, meaning ``zero``, where that is given); one line naming ``what``
    otherwise. More threads than cores only wait on each other, and torch fails to
    start hundreds of thousands."""
    lowest = 0 if zero else 1
    if isinstance(count, bool) or not isinstance(count, int) or not lowest <= count <= cores():
        meaning = f" (0: {zero})" if zero else ""
        raise ValueError(
            f"{what} must be an integer in [{lowest}, {cores()}]{meaning}, this machine's cores being {cores()}, "
            f"got {count!r}"
        )
    return count


def choose(given: int | None, env_id: str | None = None, batch: int = 1, training: bool = False) -> tuple[int, str]:
    """The thread count to use and why: ``given`` (a positive integer up to the cores),
    else ``$BEACON_TORCH_THREADS``, else the measured fastest for ``env_id`` at ``batch``
    (its training, with ``training``), else torch's default."""
    import torch

    if given is not None:
        return check(given), "given"
    env = os.environ.get("BEACON_TORCH_THREADS", "")
    if env:
        return check(int(env) if env.isdigit() else env, "$BEACON_TORCH_THREADS"), "$BEACON_TORCH_THREADS"
    if env_id is not None:
        best = fastest(env_id, batch, training)
        if best is not None:
            what = "training on" if training else f"stepping {batch} member{'s' * (batch > 1)} of"
            return best, f"measured fastest for {what} {env_id} on an idle machine"
    return torch.get_num_threads(), "torch's default"


def use(given: int | None, env_id: str | None = None, batch: int = 1, training: bool = False) -> int:
    """Set torch's thread count as :func:`choose` says; returns it."""
    import torch

    count, _ = choose(given, env_id, batch, training)
    if count != torch.get_num_threads():
        torch.set_num_threads(count)
    return count
