"""Two versions of the package step alike: every env's first actions, bit for bit.

    .venv/bin/python validation/same_steps.py BEFORE AFTER [--envs ...] [--members 2] [--out FILE]

``BEFORE`` and ``AFTER`` are source trees of the package (two clones or worktrees of two
commits). A process per tree makes every env (or those of ``--envs``) at two members (seed 0;
``--members``: the kernels inlined for a batch of 8 or 16 take another path),
in float32 and float64, eagerly and, for the envs whose actions are cheap, compiled;
resets it and takes two random actions at half amplitude (a fixed seed). Every
observation, reward, flag, state field and diagnostic is compared with ``torch.equal``
between the trees. Prints the cases that differ and writes a JSON summary (machine,
trees and their commits, cases, tensors compared, differences) to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve()


def worker(out: str, envs: list[str] | None, members: int = 2) -> None:
    """Every env's record in this process's tree (those of ``envs`` when given), saved
    to ``out``."""
    import torch

    import beacon_torch
    from beacon_torch import registry

    torch.set_num_threads(1)
    records = {}
    for env_id in envs or beacon_torch.list_envs():
        # the tree before may be one whose ids were classes with the card's fields on them
        spec = registry.env_spec(env_id) if hasattr(registry, "env_spec") else registry.env_class(env_id)
        costly = spec.card.costly if hasattr(spec, "card") else spec.costly
        for mode in ["eager"] + ([] if costly else ["compiled"]):
            for dtype in ("float32", "float64"):
                env = beacon_torch.make(env_id, members, seed=0, dtype=dtype, compile=mode == "compiled")
                env.reset()
                generator = torch.Generator().manual_seed(3)
                record = {"observation 0": env.observation.clone()}
                for k in (1, 2):
                    action = env.random_action(generator)
                    obs, reward, terminated, truncated = env.step_members(action if env.discrete else 0.5 * action)
                    record[f"observation {k}"], record[f"reward {k}"] = obs.clone(), reward.clone()
                    record[f"flags {k}"] = torch.stack([terminated, truncated])
                record.update({f"state.{key}": value.clone() for key, value in env.state._asdict().items()})
                record.update({f"diagnostics.{key}": value.clone() for key, value in env.last_diagnostics.items()})
                records[f"{env_id} {mode} {dtype}"] = record
    torch.save(records, out)


def run(tree: Path, out: Path, envs: list[str] | None, members: int) -> None:
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
    command = [sys.executable, str(HERE), "--worker", str(out), "--members", str(members)]
    command += ["--envs", *envs] if envs else []
    done = subprocess.run(command, env=env, cwd=tree, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"{tree}: the worker failed:\n{done.stderr[-3000:]}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("trees", nargs="*", type=Path, help="BEFORE and AFTER: two source trees of the package")
    parser.add_argument("--envs", nargs="+", default=None, help="env ids (default: every registered one)")
    parser.add_argument("--members", type=int, default=2, help="members of each env (default 2)")
    parser.add_argument("--out", type=Path, default=None, help="the JSON summary (default: printed only)")
    parser.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args.worker, args.envs, args.members)
        return
    if len(args.trees) != 2:
        parser.error("give two source trees, BEFORE and AFTER")
    import torch

    from beacon_torch.files import machine, revision

    with tempfile.TemporaryDirectory() as folder:
        files = [Path(folder) / f"{name}.pt" for name in ("before", "after")]
        for tree, file in zip(args.trees, files, strict=True):
            run(tree.resolve(), file, args.envs, args.members)
        before, after = (torch.load(file, weights_only=True) for file in files)
    cases = sorted(set(before) & set(after))
    differ = [
        f"{case}: {key}"
        for case in cases
        for key in sorted(set(before[case]) | set(after[case]))
        if key not in before[case] or key not in after[case] or not torch.equal(before[case][key], after[case][key])
    ]
    summary = dict(
        machine=machine(),
        trees=[str(t) for t in args.trees],
        commits=[revision(t) for t in args.trees],
        members=args.members,
        cases=len(cases),
        only_in_one=sorted(set(before) ^ set(after)),
        tensors=sum(len(before[case]) for case in cases),
        differ=differ,
    )
    print(f"{summary['cases']} cases, {summary['tensors']} tensors compared; {len(differ)} differ")
    for line in differ:
        print(f"  {line}")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        with open(args.out, "x") as f:  # a new record, never one replaced
            json.dump(summary, f, indent=1)


if __name__ == "__main__":
    main()
