"""Where a differentiated transition's time goes, per env, split by piece, at the
short-horizon actor-critic's batch and settings (``SHACConfig``), float32, one thread.

    .venv/bin/python benchmarks/grad_profile.py [--envs ...] [--horizon 2] [--ways eager compiled kernels]
    .venv/bin/python benchmarks/grad_profile.py --page docs/measurements.md

Two profiles of the same block of actions (forward with the graph kept, then the
backward pass of the summed rewards to the actions), each after a warm-up block:

- **eager, by piece.** Every function and method of ``beacon_torch.numerics`` and every
  function of the env's own modules runs inside a profiler scope of its name; each
  operator's own time goes to its innermost scope. A backward operator goes to the scope
  of the forward operator it differentiates (autograd's sequence numbers link the two),
  so each piece has a forward and a backward share; forward operators run again during
  the backward pass (gradient checkpointing recomputing an action) are counted as the
  piece's ``recomputed`` share. The autograd engine's own bookkeeping (its per-node
  frames, gradient accumulation, the seed of the backward pass) is ``autograd``; the
  process time outside every operator (Python: the env's code, the wrappers, the
  profiler's own) is ``python``.
- **compiled, by kind.** The env as ``compile=True`` runs it differentiated: the
  compiled forward graphs, the compiled backward graphs, the C kernels
  (``beacon_torch::*``), operators outside the graphs, the wrappers around each compiled
  call (dynamo's guard check, AOTAutograd's runtime, the autograd engine's frames) and
  Python.
- **compiled, by generated kernel** (``--ways kernels``, not by default: the graphs are
  compiled again with inductor's per-kernel profiler scopes). Each kernel's time and
  calls, forward or backward, under the name inductor gives it from the operators it
  fuses; the page says how much of the backward is in kernels that hold a slice's
  backward (a padding, whose every element is read under index masks).

Shares are fractions of the profiled block's wall time, one thread on an otherwise idle
core (the profiler slows every operator a little, so the absolute times are above
``grad_cost.py``'s). Writes
``grad-profile-ENV-DATE-TIME.json`` per env to ``benchmarks/results/grad_profile``.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import inspect
import sys
import time
from collections import defaultdict
from pathlib import Path

import torch
from tensordict import TensorDict

from beacon_torch.registry import continuous_envs

HERE = Path(__file__).resolve()
PARAMS = {"lorenz-continuous-v0": {"reward_width": 1.0}}
SCOPE = "piece:"
# the wrappers around a compiled call, and the autograd engine's own frames
WRAPPERS = (
    "CompiledFunction",
    "CompiledFunctionBackward",
    "Torch-Compiled Region",
    "TorchDynamo Cache Lookup",
    "AOTDispatcher",
    "Pregraph bytecode",
    "autograd::engine::evaluate_function",
    "torch::autograd::AccumulateGrad",
)


def _scoped(fn, name: str):
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with torch.profiler.record_function(SCOPE + name):
            return fn(*args, **kwargs)

    wrapper._profiled = True
    return wrapper


def _own_modules(env_id: str) -> list:
    """The numerics modules and the env's own (its module, and its package's modules)."""
    from beacon_torch.registry import env_spec

    package = env_spec(env_id).__module__.rsplit(".", 1)[0]
    if package == "beacon_torch.envs":  # a one-module env
        package = env_spec(env_id).__module__
    return [
        m
        for name, m in sorted(sys.modules.items())
        if m is not None and (name.startswith("beacon_torch.numerics") or name.startswith(package))
    ]


@contextlib.contextmanager
def scopes(env_id: str):
    """Every function of the numerics and of the env's modules, and every method of their
    classes, inside a profiler scope of its qualified name (rebound wherever a module of
    the package holds the same object), for the duration of the block."""
    modules = _own_modules(env_id)
    wrapped: dict[int, object] = {}
    undo: list[tuple[object, str, object]] = []

    def wrap(owner, attr: str, fn, label: str) -> None:
        if getattr(fn, "_profiled", False):
            return
        if id(fn) not in wrapped:
            wrapped[id(fn)] = _scoped(fn, label)
        undo.append((owner, attr, fn))
        setattr(owner, attr, wrapped[id(fn)])

    for module in modules:
        short = module.__name__.removeprefix("beacon_torch.")
        for attr, value in list(vars(module).items()):
            if inspect.isfunction(value) and value.__module__ == module.__name__:
                wrap(module, attr, value, f"{short}.{attr}")
            elif inspect.isclass(value) and value.__module__ == module.__name__:
                for name, member in list(vars(value).items()):
                    if inspect.isfunction(member) and not name.startswith("__"):
                        wrap(value, name, member, f"{short}.{value.__name__}.{name}")
    # a function imported by name into another module of the package is rebound there
    for name, module in list(sys.modules.items()):
        if module is None or not name.startswith("beacon_torch"):
            continue
        for attr, value in list(vars(module).items()):
            if inspect.isfunction(value) and id(value) in wrapped and not getattr(value, "_profiled", False):
                undo.append((module, attr, value))
                setattr(module, attr, wrapped[id(value)])
    try:
        yield
    finally:
        for owner, attr, fn in reversed(undo):
            setattr(owner, attr, fn)


class Block:
    """``horizon`` differentiated actions of ``env_id`` and their backward pass."""

    def __init__(self, env_id: str, compiled: bool, horizon: int) -> None:
        import beacon_torch
        from beacon_torch.training.config import SHACConfig, configure

        cfg = configure(SHACConfig, env_id)
        self.members, self.grad_checkpoint, self.horizon = cfg.num_envs, cfg.grad_checkpoint, horizon
        self.env = beacon_torch.make(
            env_id,
            self.members,
            seed=0,
            compile=compiled,
            differentiable=True,
            grad_checkpoint=cfg.grad_checkpoint,
            params=PARAMS.get(env_id, {}),
        )
        self.env.reset()
        self.generator = torch.Generator().manual_seed(0)

    def __call__(self, marks: list | None = None) -> None:
        env = self.env
        shape = (self.horizon, *env.batch_size, *env.action_spec.shape[1:])
        actions = (0.2 * (2 * torch.rand(shape, generator=self.generator) - 1)).requires_grad_()
        total = 0.0
        for a in actions:
            total = total + env.step(TensorDict({env.action_key: a}, batch_size=env.batch_size))["next", "reward"].sum()
        with torch.profiler.record_function("phase:backward"):
            total.backward()
        env.detach_state()
        if bool(env.step_count.max() >= env.episode_length - self.horizon):
            env.reset()


def _ancestors(event):
    parent = event.cpu_parent
    while parent is not None:
        yield parent
        parent = parent.cpu_parent


def _is_wrapper(name: str) -> bool:
    return name.startswith(WRAPPERS)


def split_eager(events) -> dict[str, float]:
    """Seconds per ``piece/share`` from an eager profile's events."""
    piece_of_seq: dict[int, str] = {}
    out: dict[str, float] = defaultdict(float)
    # the forward operators' pieces first (a backward node names its forward's sequence number)
    for e in events:
        if e.sequence_nr >= 0 and not e.name.startswith("autograd::") and e.name[:1] != "#":
            scope = next((a.name[len(SCOPE) :] for a in _ancestors(e) if a.name.startswith(SCOPE)), "(env code)")
            piece_of_seq.setdefault(e.sequence_nr, scope)
    for e in events:
        if e.name.startswith((SCOPE, "phase:")):
            continue
        seconds = e.self_cpu_time_total * 1e-6
        if e.name.startswith(("autograd::engine", "torch::autograd::AccumulateGrad")):
            out["autograd"] += seconds
            continue
        chain = list(_ancestors(e))
        backward = any(a.name == "phase:backward" for a in chain)
        # the nearest of a piece's scope and a backward node: a checkpointed action's
        # recomputation runs inside the backward node that first needs it, its
        # operators inside their pieces' scopes
        near = next((a for a in chain if a.name.startswith((SCOPE, "autograd::engine::evaluate_function"))), None)
        if near is None:
            out["autograd" if backward else "(env code)/forward"] += seconds
        elif near.name.startswith(SCOPE):
            out[f"{near.name[len(SCOPE) :]}/{'recomputed' if backward else 'forward'}"] += seconds
        else:
            out[f"{piece_of_seq.get(near.sequence_nr, '(env code)')}/backward"] += seconds
    return dict(out)


def split_compiled(events) -> dict[str, float]:
    """Seconds per kind from a compiled profile's events."""
    out: dict[str, float] = defaultdict(float)
    for e in events:
        if e.name.startswith((SCOPE, "phase:")):
            continue
        seconds = e.self_cpu_time_total * 1e-6
        chain = list(_ancestors(e))
        if e.name.startswith("beacon_torch::") or any(a.name.startswith("beacon_torch::") for a in chain):
            out["C kernels"] += seconds
        elif "CompiledFxGraph" in e.name or any("CompiledFxGraph" in a.name for a in chain):
            backward = any(a.name.startswith("CompiledFunctionBackward") for a in chain)
            out["backward graphs" if backward else "forward graphs"] += seconds
        elif _is_wrapper(e.name):
            out["wrappers"] += seconds
        else:
            out["operators outside the graphs"] += seconds
    return dict(out)


def split_kernels(events) -> dict[str, dict]:
    """Seconds and calls per generated kernel of the compiled graphs (inductor names
    each after the operators it fuses), forward or backward, and of every other
    operator the graphs call (``op NAME``: the C kernels, allocations); the graphs'
    own time between them is ``graph code``."""
    out: dict[str, dict] = {}
    for e in events:
        chain = list(_ancestors(e))
        if "CompiledFxGraph" in e.name:
            name = "graph code"
        elif not any("CompiledFxGraph" in a.name for a in chain):
            continue
        elif e.name.startswith("graph_") and "_cpp_fused_" in e.name:
            name = e.name.split("_cpp_fused_", 1)[1]
        else:
            name = f"op {e.name}"
        backward = any(a.name.startswith("CompiledFunctionBackward") for a in chain)
        key = f"{'backward' if backward else 'forward'}: {name}"
        entry = out.setdefault(key, {"seconds": 0.0, "calls": 0})
        entry["seconds"] += e.self_cpu_time_total * 1e-6
        entry["calls"] += 1
    return out


def profile(env_id: str, way: str, horizon: int) -> dict:
    from torch._inductor import config as inductor_config
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    compiled = way != "eager"
    if way == "kernels" and not inductor_config.cpp.enable_kernel_profile:
        raise ValueError("the kernels' profile needs their profiler scopes compiled in: run it alone (--ways kernels)")
    block = Block(env_id, compiled, horizon)
    with contextlib.nullcontext() if compiled else scopes(env_id):
        block()  # compilation, and the first call's allocations
        block()
        # wall time, as the profiler's events are (one thread on an otherwise idle core)
        start = time.perf_counter()
        with torch_profile(activities=[ProfilerActivity.CPU]) as prof:
            block()
        total = time.perf_counter() - start
    if way == "kernels":
        split = split_kernels(prof.events())
        per_action = {
            k: {"seconds": v["seconds"] / horizon, "calls": v["calls"] / horizon}
            for k, v in sorted(split.items(), key=lambda kv: -kv[1]["seconds"])
        }
    else:
        split = (split_compiled if compiled else split_eager)(prof.events())
        split["python"] = max(total - sum(split.values()), 0.0)
        per_action = {k: v / horizon for k, v in sorted(split.items(), key=lambda kv: -kv[1])}
    return dict(
        env=env_id,
        way=way,
        members=block.members,
        grad_checkpoint=block.grad_checkpoint,
        horizon=horizon,
        seconds_per_action=total / horizon,
        split=per_action,
    )


BEGIN, END = (
    "<!-- differentiated transitions by piece: benchmarks/grad_profile.py -->",
    "<!-- end of differentiated transitions by piece -->",
)


def _shares(row: dict, top: int) -> str:
    total = row["seconds_per_action"]
    if row["way"] == "kernels":
        return _kernels(row)
    items = list(row["split"].items())[:top]
    return "; ".join(f"{k} {100 * v / total:.0f} %" for k, v in items)


def _kernels(row: dict) -> str:
    """The generated kernels of an action: forward against backward, the backward's
    share in kernels that hold a slice's backward (a padding, read under index masks),
    and the largest backward kernel."""
    side = {"forward": 0.0, "backward": 0.0}
    kernels, padded = {"forward": 0.0, "backward": 0.0}, 0.0
    for name, entry in row["split"].items():
        kind, what = name.split(": ", 1)
        side[kind] += entry["seconds"]
        if not what.startswith(("op ", "graph code")):
            kernels[kind] += entry["seconds"]
            if kind == "backward" and "slice_backward" in what:
                padded += entry["seconds"]
    ms = lambda seconds: f"{1e3 * seconds:.2f} ms"
    text = (
        f"forward graphs {ms(side['forward'])} (generated kernels {ms(kernels['forward'])}), backward graphs "
        f"{ms(side['backward'])} (kernels {ms(kernels['backward'])}"
    )
    if kernels["backward"]:
        text += f", {100 * padded / kernels['backward']:.0f} % of it in kernels holding a slice's backward"
    text += ")"
    largest = [(n, e) for n, e in row["split"].items() if n.startswith("backward")][:3]
    text += "; the backward's largest: " + ", ".join(
        f"{n.split(': ', 1)[1]} {ms(e['seconds'])} ({e['calls']:g} calls)" for n, e in largest
    )
    return text


def page_table(folder: Path, top: int = 6) -> str:
    """The newest record of each env in ``folder`` as a markdown table: each way's
    largest shares."""
    from beacon_torch import received

    ways: dict[str, dict[str, dict]] = defaultdict(dict)
    measured: dict[str, str] = {}
    for path in sorted(folder.glob("grad-profile-*.json"), key=lambda p: p.name[-20:]):
        record = received.json_file(path, "a differentiated profile record")
        day = "-".join((path.stem[-15:-11], path.stem[-11:-9], path.stem[-9:-7]))
        cpu = str(record.get("machine", "")).split(",")[0].replace("(R)", "").replace(" Processor", "")
        for row in record["rows"]:
            ways[row["env"]][row["way"]] = row
            measured[row["env"]] = f"{day}, {cpu}"
    lines = [
        "| env | members | eager: the largest shares of a differentiated action (piece/part) "
        "| compiled: the same by kind | compiled: its generated kernels, an action | measured |",
        "|---|---|---|---|---|---|",
    ]
    for env_id in [e for e in continuous_envs() if e in ways]:
        cells = [_shares(ways[env_id][w], top) if w in ways[env_id] else "-" for w in ("eager", "compiled", "kernels")]
        members = next(iter(ways[env_id].values()))["members"]
        lines.append(f"| {env_id} | {members} | {' | '.join(cells)} | {measured[env_id]} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", default=continuous_envs())
    parser.add_argument("--horizon", type=int, default=2)
    parser.add_argument("--ways", nargs="+", default=["eager", "compiled"], choices=["eager", "compiled", "kernels"])
    parser.add_argument("--out", type=Path, default=HERE.parent / "results" / "grad_profile")
    parser.add_argument("--page", type=Path, default=None, help="write --out's newest records as this page's table")
    args = parser.parse_args()
    if args.page is not None:
        from beacon_torch.training.report import write_block

        print(write_block(args.page, BEGIN, END, page_table(args.out)))
        return
    if "kernels" in args.ways:
        if args.ways != ["kernels"]:
            parser.error("--ways kernels runs alone: its graphs are compiled with a profiler scope in every kernel")
        from torch._inductor import config as inductor_config

        # set before the first compilation, as the graphs' cache keys then hold it
        inductor_config.cpp.enable_kernel_profile = True
    torch.set_num_threads(1)
    from beacon_torch.files import save_rows

    for env_id in args.envs:
        rows = [profile(env_id, way, args.horizon) for way in args.ways]
        for row in rows:
            print(f"{env_id} {row['way']}: {1e3 * row['seconds_per_action']:.1f} ms an action; {_shares(row, 8)}")
        print(f"written to {save_rows(rows, args.out, f'grad-profile-{env_id}')}", flush=True)


if __name__ == "__main__":
    main()
