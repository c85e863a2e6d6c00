"""What a differentiated transition costs against a compiled forward one, per env, at the
short-horizon actor-critic's batch and settings (``SHACConfig``: its members and
``grad_checkpoint`` and ``grad_checkpoint_after``), in CPU time of this process, float32.

    .venv/bin/python benchmarks/grad_cost.py [--envs ...] [--rounds 5] [--horizon 4]
    .venv/bin/python benchmarks/grad_cost.py --page docs/measurements.md

Three ways of taking an action, measured side by side, one block of each in turn per
round, after a warm-up (compilation) that is not counted:

- ``forward``: the env compiled, no graph: one compiled call per action (what a
  collector runs);
- ``eager``: the differentiable env eager, ``horizon`` actions with the graph kept, then
  the backward pass of their summed rewards to the actions;
- ``compiled``: the same with the env compiled, as it runs (chunks of substeps, each
  one compiled call differentiated by torch.compile as one graph; the whole action as
  one such call where the physics asks for it, ``grad_whole_action``);
- ``compiled-K`` (asked for with ``--kinds``): the same with ``K`` substeps a compiled
  call (``compiled-1``: each substep its own call);
- ``kept`` (asked for with ``--kinds``): ``compiled`` with every action's graph kept
  whole where the actor-critic recomputes each action in the backward pass (mixing, the
  pinball): what a transition costs without the recomputation, at a horizon short
  enough to fit in memory.

Recorded per env and round: CPU seconds per transition of each, and of them the
kernel's (``system_s``) and the pages faulted in (``page_faults``); the ratios are the
medians over the rounds of each round's ratio; per way, the wall seconds of its two
warm-up blocks (``warmup_s``: the compilation, where the inductor cache is cold).
``--keep-free B`` sets the free heap kept between recomputed actions
(``beacon_torch.autograd.KEEP_FREE``; 0: trimmed after every action). Each way runs in
a process of its own (the rounds still alternate, the parent handing each process its
block in turn): a forward transition taken in a process that also differentiates ran
10 to 20 % slower on rayleigh-v0 than in a process that only steps (its heap and caches
as the differentiated blocks leave them), which made the ratio look better than what a
collector pays; ``--one-process`` measures the ways in one process, as records before
2026-12-06 did (``apart`` in a record says which). Writes a new
``grad-cost-ENV-DATE-TIME.json`` per env in ``benchmarks/results/grad_cost`` and prints
a table.
"""

from __future__ import annotations

import argparse
import resource
import statistics
import time
from pathlib import Path

import torch
from tensordict import TensorDict

from beacon_torch.registry import continuous_envs, env_spec

HERE = Path(__file__).resolve()
# a smooth reward where the default has no gradient
PARAMS = {"lorenz-continuous-v0": {"reward_width": 1.0}}


class Way:
    """One way of taking actions of ``env_id`` at ``members``."""

    def __init__(self, env_id: str, members: int, kind: str, checkpoint: bool, horizon: int, after: int = 0) -> None:
        import beacon_torch

        differentiable = kind != "forward"
        checkpoint = checkpoint and differentiable and kind != "kept"
        self.kind, self.horizon = kind, horizon
        self.env = beacon_torch.make(
            env_id,
            members,
            seed=0,
            compile=kind != "eager",
            differentiable=differentiable,
            grad_checkpoint=checkpoint,
            grad_checkpoint_after=after if checkpoint else 0,
            params=PARAMS.get(env_id, {}),
        )
        if kind.startswith("compiled-"):  # another chunk of substeps per compiled call
            self.env.physics.kernels.chunk = int(kind.split("-", 1)[1])
        self.env.reset()
        self.generator = torch.Generator().manual_seed(0)

    def actions(self) -> int:
        """One block: ``horizon`` actions (and their backward pass); returns the count."""
        env = self.env
        shape = (self.horizon, *env.batch_size, *env.action_spec.shape[1:])
        actions = 0.2 * (2 * torch.rand(shape, generator=self.generator) - 1)
        if self.kind == "forward":
            with torch.no_grad():
                for a in actions:
                    env.step(TensorDict({env.action_key: a}, batch_size=env.batch_size))
        else:
            actions.requires_grad_()
            total = 0.0
            for a in actions:
                total = (
                    total + env.step(TensorDict({env.action_key: a}, batch_size=env.batch_size))["next", "reward"].sum()
                )
            total.backward()
            env.detach_state()
        if bool(env.step_count.max() >= env.episode_length - self.horizon):
            env.reset()
        return self.horizon * env.num_envs


class Here:
    """A way measured in this process."""

    def __init__(self, kind: str, env_id: str, members: int, checkpoint: bool, horizon: int, after: int) -> None:
        self.way = Way(env_id, members, kind, checkpoint, horizon, after)

    def warm(self) -> float:
        """Two blocks (the compilation, forward and backward); their wall seconds."""
        start = time.perf_counter()
        self.way.actions()
        self.way.actions()
        return time.perf_counter() - start

    def block(self) -> tuple[float, float, float]:
        """One block: CPU seconds, kernel seconds and pages faulted in, per transition."""
        usage, start = resource.getrusage(resource.RUSAGE_SELF), time.process_time()
        n = self.way.actions()
        cpu = (time.process_time() - start) / n
        after = resource.getrusage(resource.RUSAGE_SELF)
        return cpu, (after.ru_stime - usage.ru_stime) / n, (after.ru_minflt - usage.ru_minflt) / n

    def close(self) -> None:
        pass


def _serve(conn, keep_free: int, kind: str, *settings) -> None:
    """A way's own process: builds it, then answers each request of the parent's."""
    torch.set_num_threads(1)
    from beacon_torch import autograd

    autograd.KEEP_FREE = keep_free
    here = Here(kind, *settings)
    for request in iter(conn.recv, "stop"):
        conn.send(getattr(here, request)())


class Apart:
    """A way measured in a process of its own, one block whenever asked."""

    def __init__(self, kind: str, *settings) -> None:
        import multiprocessing

        from beacon_torch import autograd

        context = multiprocessing.get_context("spawn")
        self.conn, child = context.Pipe()
        args = (child, autograd.KEEP_FREE, kind, *settings)  # this process's setting, as --keep-free left it
        self.process = context.Process(target=_serve, args=args, daemon=True)
        self.process.start()

    def warm(self) -> float:
        self.conn.send("warm")
        return self.conn.recv()

    def block(self) -> tuple[float, float, float]:
        self.conn.send("block")
        return self.conn.recv()

    def close(self) -> None:
        self.conn.send("stop")
        self.process.join(timeout=60)


def measure(
    env_id: str,
    rounds: int,
    horizon: int,
    kinds: list[str],
    grad_checkpoint_after: int | None = None,
    apart: bool = True,
) -> dict:
    from beacon_torch import autograd
    from beacon_torch.training.config import SHACConfig, configure

    cfg = configure(SHACConfig, env_id)
    kept = cfg.grad_checkpoint_after if grad_checkpoint_after is None else grad_checkpoint_after
    given = (env_id, cfg.num_envs, cfg.grad_checkpoint, horizon, kept)
    ways = {k: (Apart(k, *given) if apart else Here(k, *given)) for k in kinds}
    try:
        warmup = {k: way.warm() for k, way in ways.items()}  # compilation, forward and backward
        per = {k: [] for k in kinds}
        # per transition: the kernel's share of the CPU time and the pages faulted in
        system, faults = {k: [] for k in kinds}, {k: [] for k in kinds}
        for _ in range(rounds):
            for k, way in ways.items():
                cpu, kernel, faulted = way.block()
                per[k].append(cpu)
                system[k].append(kernel)
                faults[k].append(faulted)
    finally:
        for way in ways.values():
            way.close()
    row = dict(
        env=env_id,
        members=cfg.num_envs,
        grad_checkpoint=cfg.grad_checkpoint,
        grad_checkpoint_after=kept,
        horizon=horizon,
        rounds=per,
        system_s=system,
        page_faults=faults,
        keep_free=autograd.KEEP_FREE,
        warmup_s=warmup,
        apart=apart,
    )
    for k in kinds:
        row[f"{k}_s"] = statistics.median(per[k])
        if k != "forward":
            row[f"{k}_ratio"] = statistics.median(d / f for d, f in zip(per[k], per["forward"], strict=True))
    return row


BEGIN, END = (
    "<!-- differentiated transitions: benchmarks/grad_cost.py -->",
    "<!-- end of differentiated transitions -->",
)


def settings(row: dict) -> tuple:
    """What a row's ways were measured with (records from before
    ``grad_checkpoint_after`` recomputed every action)."""
    return row.get("members"), row.get("grad_checkpoint"), row.get("grad_checkpoint_after", 0)


def page_table(folder: Path) -> str:
    """The newest measurement of each env and way in ``folder`` as a markdown table (a
    way missing from an env's newest record, such as the cavities' eager path, keeps
    its newest earlier ratio measured on the same CPU at the same members,
    ``grad_checkpoint`` and ``grad_checkpoint_after``; each ratio is against the forward
    way of its own record)."""
    from beacon_torch import received

    newest: dict[str, dict] = {}
    for path in sorted(folder.glob("grad-cost-*.json"), key=lambda p: p.name[-20:]):
        record = received.json_file(path, "a differentiated transitions record")
        # the day from the record's name, the processor from its machine line
        day = "-".join((path.stem[-15:-11], path.stem[-11:-9], path.stem[-9:-7]))
        cpu = str(record.get("machine", "")).split(",")[0].replace("(R)", "").replace(" Processor", "")
        for row in record["rows"]:
            if "warmup_s" not in row and "compiled_ratio" in row:
                # recorded before the chunks: its compiled way was a call a substep
                row = {**row, "compiled-1_ratio": row["compiled_ratio"]}
                del row["compiled_ratio"]
            before = newest.get(row["env"], {})
            if settings(before) != settings(row) or before.get("cpu") != cpu:
                before = {}  # ways measured with other settings or on another CPU are not this row's
            apart = ", each way its own process" if row.get("apart") else ""
            newest[row["env"]] = {**before, **row, "cpu": cpu, "measured": f"{day}, {cpu}{apart}"}
    lines = [
        "| env | members | grad_checkpoint | forward, compiled (ms per transition) | differentiated, eager "
        "| compiled, a call a substep | compiled, as the env runs it | measured (each row's ways side by side) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for env_id in [e for e in continuous_envs() if e in newest]:
        r = newest[env_id]
        # a way not measured (the wakes' eager path: minutes a round) is a dash
        ratio = lambda kind, r=r: f"{r[f'{kind}_ratio']:.1f} x" if f"{kind}_ratio" in r else "-"
        physics = env_spec(env_id).physics
        way = "one graph an action" if physics.grad_whole_action else f"chunks of {physics.grad_chunk}"
        # an action in C leaves no compiled substeps to call one by one
        substeps = "-" if physics.grad_action_in_c else ratio("compiled-1")
        way = "the action in C" if physics.grad_action_in_c else way
        if getattr(physics, "substep_adjoint", None) is not None:
            way = f"the substeps' adjoint written out, chunks of {physics.adjoint_chunk or physics.grad_chunk}"
        compiled = f"{ratio('compiled')} ({way})" if "compiled_ratio" in r else "-"
        checkpoint = str(r["grad_checkpoint"])
        if r["grad_checkpoint"] and r.get("grad_checkpoint_after"):
            checkpoint += f" (after {r['grad_checkpoint_after']} actions kept whole)"
        lines.append(
            f"| {env_id} | {r['members']} | {checkpoint} | {1e3 * r['forward_s']:.3g} "
            f"| {ratio('eager')} | {substeps} | {compiled} | {r['measured']} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", default=continuous_envs())
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--horizon", type=int, default=4)
    parser.add_argument("--kinds", nargs="+", default=["forward", "eager", "compiled"])
    parser.add_argument(
        "--keep-free",
        type=int,
        default=None,
        help="free heap bytes kept between recomputed actions (default: beacon_torch.autograd.KEEP_FREE)",
    )
    parser.add_argument(
        "--grad-checkpoint-after",
        type=int,
        default=None,
        help="the recomputing env's actions kept whole a horizon (default: the actor-critic's setting)",
    )
    parser.add_argument(
        "--one-process", action="store_true", help="every way in this process (as records before 2026-12-06)"
    )
    parser.add_argument("--out", type=Path, default=HERE.parent / "results" / "grad_cost")
    parser.add_argument("--page", type=Path, default=None, help="write --out's newest records as this page's table")
    args = parser.parse_args()
    if args.page is not None:
        from beacon_torch.training.report import write_block

        print(write_block(args.page, BEGIN, END, page_table(args.out)))
        return
    torch.set_num_threads(1)
    from beacon_torch import autograd
    from beacon_torch.files import save_rows

    if args.keep_free is not None:
        autograd.KEEP_FREE = args.keep_free

    ways = ("eager", "compiled", "kept")
    print(
        "| env | members | checkpoint | forward (ms/transition) | " + " | ".join(f"{k} / forward" for k in ways) + " |"
    )
    print("|---|---|---|---|---|---|---|", flush=True)
    for env_id in args.envs:
        row = measure(env_id, args.rounds, args.horizon, args.kinds, args.grad_checkpoint_after, not args.one_process)
        ratios = " | ".join(f"{row.get(f'{k}_ratio', float('nan')):.1f}" for k in ways)
        print(f"| {env_id} | {row['members']} | {row['grad_checkpoint']} | {1e3 * row['forward_s']:.3g} | {ratios} |")
        # a record per env, written as soon as it is measured
        print(f"written to {save_rows([row], args.out, f'grad-cost-{env_id}')}", flush=True)


if __name__ == "__main__":
    main()
