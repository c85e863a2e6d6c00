"""Memory and time of differentiating through the envs (issue 7).

    .venv/bin/python benchmarks/grad_memory.py [--steps N] [--batch B] [--dtype float32]

For every continuous env, a differentiable rollout of ``--steps`` random actions, then the
backward pass of the summed reward, with and without ``grad_checkpoint``. Reported per
batch member and action: the bytes autograd keeps for the backward pass (tensors saved by
the graph, each storage counted once), and the wall time of forward plus backward. The
table in docs/gradients.md comes from this script.
"""

from __future__ import annotations

import argparse
import time

import torch
from tensordict import TensorDict

import beacon_torch

ENVS = {
    "lorenz-continuous-v0": {"reward_width": 1.0},
    "vortex-v0": {},
    "burgers-v0": {},
    "sloshing-v0": {},
    "shkadov-v0": {"random_start": 0},
    "rayleigh-v0": {},
    "mixing-continuous-v0": {},
}


def measure(env_id: str, steps: int, batch: int, dtype: torch.dtype, checkpoint: bool, **params) -> tuple[float, float]:
    """(saved bytes per member and action, seconds per action of forward + backward)."""
    env = beacon_torch.make(
        env_id, batch_size=batch, dtype=dtype, seed=0, differentiable=True, grad_checkpoint=checkpoint, **params
    )
    env.reset()
    g = torch.Generator().manual_seed(0)
    actions = (torch.rand((steps, batch, *env.action_spec.shape[1:]), generator=g, dtype=dtype) - 0.5)
    actions.requires_grad_()
    storages: dict[int, int] = {}

    def pack(t: torch.Tensor) -> torch.Tensor:
        s = t.untyped_storage()
        storages[s.data_ptr()] = s.nbytes()
        return t

    start = time.perf_counter()
    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        total = 0.0
        for a in actions:
            td = env.step(TensorDict({env.action_key: a}, batch_size=env.batch_size))
            total = total + td["next", env.reward_key].sum()
    total.backward()
    seconds = time.perf_counter() - start
    return sum(storages.values()) / (steps * batch), seconds / steps


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=4)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    parser.add_argument("--envs", nargs="*", default=list(ENVS))
    args = parser.parse_args(argv)
    dtype = getattr(torch, args.dtype)
    print(f"{args.steps} actions, batch {args.batch}, {args.dtype}, {torch.get_num_threads()} threads")
    print("| env | state per member | graph per member and action | with grad_checkpoint | time per action (batch) | with grad_checkpoint |")
    print("|---|---|---|---|---|---|")
    for env_id in args.envs:
        params = ENVS[env_id]
        probe = beacon_torch.make(env_id, batch_size=1, dtype=dtype, seed=0, **params)
        probe.reset()
        state = sum(v.numel() * v.element_size() for v in probe.state.values())
        full, t_full = measure(env_id, args.steps, args.batch, dtype, False, **params)
        ck, t_ck = measure(env_id, args.steps, args.batch, dtype, True, **params)
        print(
            f"| {env_id} | {_bytes(state)} | {_bytes(full)} | {_bytes(ck)} | "
            f"{t_full * 1e3:,.1f} ms | {t_ck * 1e3:,.1f} ms |",
            flush=True,
        )


def _bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:,.1f} {unit}"
        n /= 1024


if __name__ == "__main__":
    main()
