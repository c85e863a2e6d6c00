"""Memory and time of differentiating through the envs.

    .venv/bin/python benchmarks/grad_memory.py [--steps N] [--batch B] [--dtype float32]
    .venv/bin/python benchmarks/grad_memory.py --episode --envs vortex-v0 burgers-v0
    .venv/bin/python benchmarks/grad_memory.py --peak [--envs ...] [--members 8] [--horizon 16]

For every continuous env, a differentiable rollout of ``--steps`` random actions, then the
backward pass of the summed reward, with and without ``grad_checkpoint``. Reported per
batch member and action: the bytes autograd keeps for the backward pass (tensors saved by
the graph, each storage counted once), and the wall time of forward plus backward. With
``--episode``, one whole episode under ``grad_checkpoint`` instead: its saved bytes,
time and whether the gradient with respect to every action is finite. The tables in
docs/gradients.md come from this script.

With ``--peak``, the resident memory of a differentiated horizon as the actor-critic runs
it (``--members``, ``--horizon`` actions, ``grad_checkpoint`` and the compiled path as its
settings say, or as ``--compile`` and ``--grad-checkpoint`` say): one process per env, a first horizon to compile,
then the process's peak resident memory reset (Linux's ``clear_refs``) and a second
horizon with its backward pass. Recorded per env: the resident memory before it, the
peak during it (the process's whole, what a user's machine must hold) and the
difference (what the horizon itself holds), in ``benchmarks/results/grad_memory/``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import torch
from tensordict import TensorDict

import beacon_torch

HERE = Path(__file__).resolve()
# the envs whose horizons are large: the cavities, the cylinder and the pinball
PEAK_ENVS = ["rayleigh-v0", "mixing-continuous-v0", "cylinder-v0", "pinball-periodic-v0"]

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


def _status(field: str) -> int:
    """A memory field of this process's ``/proc/self/status`` (``VmRSS``, ``VmHWM``), bytes."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    raise RuntimeError(f"/proc/self/status has no {field}")


def horizon_peak(
    env_id: str,
    members: int,
    horizon: int,
    compile: bool | None = None,
    checkpoint: bool | None = None,
    after: int | None = None,
) -> dict:
    """The resident memory of one differentiated horizon of ``env_id`` with the
    actor-critic's settings (its ``grad_checkpoint`` and ``grad_checkpoint_after``;
    its compiled path unless ``compile`` says): before, at its peak (the process's) and the difference, in
    bytes, with the seconds of the horizon and whether its gradient is finite."""
    from beacon_torch.autograd import release_free_memory
    from beacon_torch.training.config import SHACConfig, configure

    cfg = configure(SHACConfig, env_id)
    compile = cfg.compile if compile is None else compile
    checkpoint = cfg.grad_checkpoint if checkpoint is None else checkpoint
    after = (cfg.grad_checkpoint_after if after is None else after) if checkpoint else 0
    env = beacon_torch.make(
        env_id,
        members,
        seed=0,
        compile=compile,
        differentiable=True,
        grad_checkpoint=checkpoint,
        grad_checkpoint_after=after,
    )
    env.reset()
    g = torch.Generator().manual_seed(0)

    def one() -> bool:
        actions = 0.2 * (2 * torch.rand((horizon, members, *env.action_spec.shape[1:]), generator=g) - 1)
        actions.requires_grad_()
        total = 0.0
        for a in actions:
            total = total + env.step(TensorDict({env.action_key: a}, batch_size=env.batch_size))["next", "reward"].sum()
        total.backward()
        env.detach_state()
        return bool(torch.isfinite(actions.grad).all())

    one()  # compiles
    release_free_memory(keep=0)
    before = _status("VmRSS")
    # the peak from here on (writing 5 resets the process's high-water mark)
    Path("/proc/self/clear_refs").write_text("5")
    start = time.perf_counter()
    finite = one()
    seconds = time.perf_counter() - start
    peak = _status("VmHWM")
    return dict(
        env=env_id,
        members=members,
        horizon=horizon,
        compile=compile,
        grad_checkpoint=checkpoint,
        grad_checkpoint_after=after,
        rss_before=before,
        peak=peak,
        held=peak - before,
        seconds=seconds,
        finite=finite,
    )


def peaks(
    envs: list[str],
    members: int,
    horizon: int,
    compile: bool | None,
    checkpoint: bool | None,
    out: Path,
    after: int | None = None,
) -> Path:
    """:func:`horizon_peak` of each env in a process of its own; writes the record."""
    rows = []
    for env_id in envs:
        command = [
            sys.executable,
            str(HERE),
            "--peak-one",
            env_id,
            "--members",
            str(members),
            "--horizon",
            str(horizon),
        ]
        for flag, value in (("--compile", compile), ("--grad-checkpoint", checkpoint)):
            if value is not None:
                command += [flag, str(value).lower()]
        if after is not None:
            command += ["--grad-checkpoint-after", str(after)]
        done = subprocess.run(command, capture_output=True, text=True, check=True)
        rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
        r = rows[-1]
        print(
            f"| {env_id} | {members} x {horizon} | {r['compile']} | {r['grad_checkpoint']} | {_bytes(r['rss_before'])} "
            f"| {_bytes(r['peak'])} | {_bytes(r['held'])} | {r['seconds']:.1f} s | {r['finite']} |",
            flush=True,
        )
    from beacon_torch.files import save_rows

    return save_rows(rows, out, "peak")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=4)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    parser.add_argument("--envs", nargs="*", default=None, choices=sorted({*ENVS, *PEAK_ENVS}))
    parser.add_argument("--episode", action="store_true", help="one whole episode with grad_checkpoint")
    parser.add_argument("--peak", action="store_true", help="the resident memory of a horizon (--envs, --members)")
    parser.add_argument("--peak-one", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--members", type=int, default=8)
    parser.add_argument("--horizon", type=int, default=16)
    parser.add_argument("--compile", choices=["true", "false"], default=None, help="default: the recipe's setting")
    parser.add_argument("--grad-checkpoint", choices=["true", "false"], default=None, help="default: the recipe's")
    parser.add_argument(
        "--grad-checkpoint-after", type=int, default=None, help="actions kept whole a horizon (default: the recipe's)"
    )
    parser.add_argument("--out", type=Path, default=HERE.parent / "results" / "grad_memory")
    args = parser.parse_args(argv)
    compile = None if args.compile is None else args.compile == "true"
    checkpoint = None if args.grad_checkpoint is None else args.grad_checkpoint == "true"
    if args.peak_one is not None:
        after = args.grad_checkpoint_after
        print(json.dumps(horizon_peak(args.peak_one, args.members, args.horizon, compile, checkpoint, after)))
        return
    if args.peak:
        envs = args.envs or PEAK_ENVS
        print(f"one horizon, {torch.get_num_threads()} threads, resident memory of the process")
        print("| env | members x actions | compiled | grad_checkpoint | before | peak | held | time | finite |")
        print("|---|---|---|---|---|---|---|---|---|")
        record = peaks(envs, args.members, args.horizon, compile, checkpoint, args.out, args.grad_checkpoint_after)
        print(f"written to {record}")
        return
    dtype = getattr(torch, args.dtype)
    args.envs = args.envs or list(ENVS)
    if args.episode:
        print(f"one episode, batch {args.batch}, {args.dtype}, grad_checkpoint, {torch.get_num_threads()} threads")
        print(
            "| env | actions | saved for the backward pass, per member | forward + backward | "
            "gradient finite | largest derivative |"
        )
        print("|---|---|---|---|---|---|")
        for env_id in args.envs:
            n = beacon_torch.registry.ENVS[env_id].physics.episode_length
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
