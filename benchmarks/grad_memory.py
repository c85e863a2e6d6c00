"""Memory and time of differentiating through the envs.

    .venv/bin/python benchmarks/grad_memory.py [--steps N] [--batch B] [--dtype float32]
    .venv/bin/python benchmarks/grad_memory.py --episode --envs vortex-v0 burgers-v0

For every continuous env, a differentiable rollout of ``--steps`` random actions, then the
backward pass of the summed reward, with and without ``grad_checkpoint``. Reported per
batch member and action: the bytes autograd keeps for the backward pass (tensors saved by
the graph, each storage counted once), and the wall time of forward plus backward. With
``--episode``, one whole episode under ``grad_checkpoint`` instead: its saved bytes,
time and whether the gradient with respect to every action is finite. The tables in
docs/gradients.md come from this script.
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


def measure(
    env_id: str, steps: int, batch: int, dtype: torch.dtype, checkpoint: bool, **params
) -> tuple[float, float, bool, float]:
    """(saved bytes per member and action, seconds per action of forward + backward,
    whether the gradient with respect to every action is finite, its largest finite
    magnitude)."""
    env = beacon_torch.make(
        env_id, batch_size=batch, dtype=dtype, seed=0, differentiable=True, grad_checkpoint=checkpoint, **params
    )
    env.reset()
    g = torch.Generator().manual_seed(0)
    actions = torch.rand((steps, batch, *env.action_spec.shape[1:]), generator=g, dtype=dtype) - 0.5
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
    finite = torch.isfinite(actions.grad)
    largest = float(torch.where(finite, actions.grad, 0.0).abs().max())
    return sum(storages.values()) / (steps * batch), seconds / steps, bool(finite.all()), largest


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=4)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    parser.add_argument("--envs", nargs="*", default=list(ENVS), choices=list(ENVS))
    parser.add_argument("--episode", action="store_true", help="one whole episode with grad_checkpoint")
    args = parser.parse_args(argv)
    dtype = getattr(torch, args.dtype)
    if args.episode:
        print(f"one episode, batch {args.batch}, {args.dtype}, grad_checkpoint, {torch.get_num_threads()} threads")
        print(
            "| env | actions | saved for the backward pass, per member | forward + backward | "
            "gradient finite | largest derivative |"
        )
        print("|---|---|---|---|---|---|")
        for env_id in args.envs:
            n = beacon_torch.registry.ENVS[env_id].episode_length
            per_action, seconds, finite, largest = measure(env_id, n, args.batch, dtype, True, **ENVS[env_id])
            print(
                f"| {env_id} | {n} | {_bytes(per_action * n)} | {seconds * n:,.1f} s | {finite} | {largest:.1e} |",
                flush=True,
            )
        return
    print(f"{args.steps} actions, batch {args.batch}, {args.dtype}, {torch.get_num_threads()} threads")
    print(
        "| env | state per member | graph per member and action | with grad_checkpoint | time per "
        "action (batch) | with grad_checkpoint |"
    )
    print("|---|---|---|---|---|---|")
    for env_id in args.envs:
        params = ENVS[env_id]
        probe = beacon_torch.make(env_id, num_envs=1, dtype=dtype, seed=0, **params)
        probe.reset()
        state = sum(v.numel() * v.element_size() for v in probe.state)
        full, t_full, *_ = measure(env_id, args.steps, args.batch, dtype, False, **params)
        ck, t_ck, *_ = measure(env_id, args.steps, args.batch, dtype, True, **params)
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
