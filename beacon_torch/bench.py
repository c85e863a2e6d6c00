"""Throughput of the environments against the published code's speed.

``beacon-torch bench`` (and ``benchmarks/throughput.py``) measure, per env, batch size,
dtype and mode (eager or compiled): transitions per second, the latency of one step,
the compile time, the compiles left after the warm-up, and the memory. Random actions
from a fixed generator; episodes are reset as they end (TorchRL's
``step_and_maybe_reset``), as a collector does.

The timing is ``torch.utils.benchmark``'s (its timer synchronises CUDA; the threads are
the process's): after a warm-up that steps until a step compiles nothing new, so that
compilation is never counted as speed; graphs compiled during the timed steps are
reported (``recompiles``), not hidden.

Memory: each configuration runs in a fresh process (:func:`run`), so its peak is its
own: on CUDA the peak allocated by torch, on CPU the process's peak resident size
(``peak_mb``, with ``base_mb`` the same process before the env was made).
"""

from __future__ import annotations

import csv
import json
import resource
import statistics
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
import torch.utils.benchmark as benchmark

from beacon_torch import seeds
from beacon_torch.base import make
from beacon_torch.files import create_file, machine, refuse_existing, save_figure
from beacon_torch.files import save_rows as save_rows  # where the benchmark scripts found it
from beacon_torch.registry import env_spec, qualified_id

BATCH_SIZES = (1, 16, 64, 256, 1024)
COSTLY_BATCH_SIZES = (1, 16, 32, 64)
CAVITY_BATCH_SIZES = COSTLY_BATCH_SIZES  # its earlier name
MAX_WARM_UP = 20  # steps; a step that still compiles after these shows in ``recompiles``


def default_batch_sizes(env_id: str) -> tuple[int, ...]:
    return COSTLY_BATCH_SIZES if env_spec(env_id).card.costly else BATCH_SIZES


def default_steps(env_id: str) -> int:
    """Timed steps per repeat: enough to dwarf the timer, few for a costly env."""
    return 2 if env_spec(env_id).card.costly else 20


@dataclass
class Measurement:
    env: str
    batch: int
    dtype: str
    mode: str
    device: str
    transitions_per_s: float
    step_ms: float  # median wall time of one batched step
    compile_s: float  # reset and warm-up minus as many timed steps: compilation
    warm_up_steps: int  # steps until one compiled nothing new
    recompiles: int  # graphs compiled during the timed steps (0 when the compiled code is stable)
    state_mb: float
    peak_mb: float | None  # the configuration's own peak (None: measured in a shared process)
    base_mb: float | None  # the same process before the env was made
    published_per_s: float | None
    speedup: float | None

    def row(self) -> str:
        vs = f"{self.speedup:7.1f}x" if self.speedup is not None else "        "
        peak = f"{self.peak_mb:>9.1f}" if self.peak_mb is not None else f"{'-':>9}"
        return (
            f"{self.env:<22} {self.mode:<8} {self.dtype:<8} {self.batch:>6} {self.transitions_per_s:>14,.1f} {vs}"
            f" {self.step_ms:>10.3f} {self.compile_s:>9.1f} {self.recompiles:>9} {peak}"
        )


HEADER = (
    f"{'env':<22} {'mode':<8} {'dtype':<8} {'batch':>6} {'transitions/s':>14} {'vs pub':>8} "
    f"{'step ms':>10} {'compile s':>9} {'recompile':>9} {'peak MB':>9}"
)


def compiled_graphs() -> int:
    """The graphs dynamo has compiled in this process so far."""
    from torch._dynamo.utils import counters

    return counters["stats"]["unique_graphs"]


def warm_up(step: Callable[[], object], max_steps: int = MAX_WARM_UP) -> int:
    """Call ``step`` until a call compiles nothing new (at most ``max_steps`` calls);
    the number of calls made."""
    for n in range(1, max_steps + 1):
        before = compiled_graphs()
        step()
        if compiled_graphs() == before:
            return n
    return max_steps


def _state_mb(env) -> float:
    return sum(t.numel() * t.element_size() for t in env.state if isinstance(t, torch.Tensor)) / 2**20


def _resident_mb() -> float:
    """The process's peak resident size so far. Linux's ``VmHWM`` belongs to the
    program itself; ``ru_maxrss`` also keeps the peak of the process it was forked from
    (a pytest worker, a notebook), so it is the fallback only."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 2**10  # kB
    except OSError:
        pass
    scale = 2**20 if sys.platform == "darwin" else 2**10  # bytes on macOS, KiB on Linux
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / scale


def measure(
    env_id: str,
    batch: int,
    *,
    dtype: str = "float32",
    mode: str = "eager",
    device: str = "cpu",
    steps: int | None = None,
    repeats: int = 5,
    seed: int = 0,
    own_process: bool = False,
) -> Measurement:
    """Transitions per second of ``env_id`` at ``batch`` members (see the module doc),
    in this process. ``own_process=True`` says the process is fresh and measures nothing
    else, so that its peak memory is the configuration's (:func:`run` does that);
    otherwise no peak is reported."""
    if mode not in ("eager", "compiled"):
        raise ValueError(f"mode must be 'eager' or 'compiled', got {mode!r}")
    if repeats < 1:
        raise ValueError(f"repeats must be a positive integer, got {repeats}")
    steps = steps or default_steps(env_id)
    dev = torch.device(device)
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
    base = _resident_mb()
    start = time.perf_counter()
    env = make(env_id, batch, dtype=dtype, device=device, seed=seed, compile=mode == "compiled", check_actions=False)
    g = seeds.generator(seed, dev)
    box = {"td": env.reset()}

    def step() -> None:
        td = box["td"]
        td[env.action_key] = env.random_action(g)
        _, box["td"] = env.step_and_maybe_reset(td)

    n_warm = warm_up(step)
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)
    warm_s = time.perf_counter() - start
    graphs = compiled_graphs()
    timer = benchmark.Timer(stmt="step()", globals={"step": step}, num_threads=torch.get_num_threads())
    times = [timer.timeit(steps).median for _ in range(repeats)]
    recompiles = compiled_graphs() - graphs
    step_s = statistics.median(times)
    rate = batch / step_s
    peak = None
    if own_process:
        peak = torch.cuda.max_memory_allocated(dev) / 2**20 if dev.type == "cuda" else _resident_mb()
    published = env_spec(env_id).card.published_speed
    return Measurement(
        env=env_id,
        batch=batch,
        dtype=str(dtype).removeprefix("torch."),
        mode=mode,
        device=str(dev),
        transitions_per_s=rate,
        step_ms=1e3 * step_s,
        compile_s=max(0.0, warm_s - n_warm * step_s),
        warm_up_steps=n_warm,
        recompiles=recompiles,
        state_mb=_state_mb(env),
        peak_mb=peak,
        base_mb=base if own_process and dev.type != "cuda" else None,
        published_per_s=published,
        speedup=rate / published if published else None,
    )


def measure_in_fresh_process(env_id: str, batch: int, **kwargs) -> Measurement:
    """:func:`measure` in a new Python process (with this one's thread count), so that
    the peak memory is this configuration's alone. A subprocess, not multiprocessing:
    nothing of the caller's script is imported again there."""
    import subprocess
    import tempfile

    job = {"env_id": qualified_id(env_id), "batch": batch, "threads": torch.get_num_threads(), "kwargs": kwargs}
    with tempfile.TemporaryDirectory() as tmp:
        result = Path(tmp) / "measurement.json"
        done = subprocess.run(
            [sys.executable, "-m", "beacon_torch.bench", json.dumps(job), str(result)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        if done.returncode != 0:
            lines = [line for line in done.stderr.splitlines() if line.strip()]
            said = [line.removeprefix(FAILED) for line in lines if line.startswith(FAILED)]
            if said:
                why = said[-1]
            elif done.returncode < 0:
                why = f"the process was killed by signal {-done.returncode} (out of memory?)"
            else:
                why = lines[-1] if lines else f"exit status {done.returncode}"
            raise ValueError(f"measuring {env_id} at {batch} members failed: {why}")
        m = Measurement(**json.loads(result.read_text()))
    m.env = env_id
    return m


# how a measuring process says why it failed, in one line its parent reports
FAILED = "beacon-torch bench: failed: "


def _measure_job(job: str, result: str) -> None:
    job = json.loads(job)
    torch.set_num_threads(job["threads"])
    try:
        m = measure(job["env_id"], job["batch"], own_process=True, **job["kwargs"])
    except (ValueError, TypeError, RuntimeError, MemoryError, OSError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else ""
        print(f"{FAILED}{type(err).__name__}: {first}", file=sys.stderr)
        sys.exit(2)
    Path(result).write_text(json.dumps(asdict(m)))


def run(
    env_ids: Iterable[str],
    *,
    num_envs: Sequence[int] | None = None,
    dtypes: Sequence[str] = ("float32",),
    modes: Sequence[str] = ("eager", "compiled"),
    device: str = "cpu",
    steps: int | None = None,
    repeats: int = 5,
    echo=print,
    progress=None,
) -> list[Measurement]:
    """Every combination, each in a fresh process (:func:`measure_in_fresh_process`),
    printed as a table while it runs; ``progress`` (a callable taking a line, stderr by
    default) says which one is being measured."""
    if progress is None:
        progress = lambda line: print(line, file=sys.stderr, flush=True)
    env_ids = list(env_ids)
    jobs = [
        (env_id, dtype, mode, batch)
        for env_id in env_ids
        for dtype in dtypes
        for mode in modes
        for batch in num_envs or default_batch_sizes(env_id)
    ]
    echo(f"# {machine()}")
    echo(HEADER)
    results = []
    for k, (env_id, dtype, mode, batch) in enumerate(jobs, 1):
        progress(f"[{k}/{len(jobs)}] measuring {env_id} {mode} {dtype} at {batch} members ...")
        m = measure_in_fresh_process(env_id, batch, dtype=dtype, mode=mode, device=device, steps=steps, repeats=repeats)
        echo(m.row())
        results.append(m)
    return results


def best(results: Sequence[Measurement]) -> dict[str, Measurement]:
    """The fastest float32 measurement of each env."""
    out: dict[str, Measurement] = {}
    for m in results:
        if m.dtype == "float32" and (m.env not in out or m.transitions_per_s > out[m.env].transitions_per_s):
            out[m.env] = m
    return out


OUTPUTS = ("results.csv", "results.json", "results.md", "throughput.png")


def write(results: Sequence[Measurement], out_dir: str | Path) -> dict[str, Path]:
    """``results.csv``, ``results.json``, ``results.md`` and ``throughput.png`` in
    ``out_dir``, which must not hold them yet (:func:`check_out`)."""
    out = Path(out_dir)
    check_out(out)
    out.mkdir(parents=True, exist_ok=True)
    rows = [asdict(m) for m in results]
    paths = {name.split(".")[-1]: out / name for name in OUTPUTS}

    def write_csv(tmp: Path) -> None:
        with tmp.open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)

    create_file(paths["csv"], write_csv)
    text = json.dumps({"machine": machine(), "results": rows}, indent=2)
    create_file(paths["json"], lambda tmp: tmp.write_text(text))
    text = (
        f"Machine: {machine()}\n\n## Best speed per env\n\n{markdown(results)}\n\n## Every "
        f"measurement\n\n{full_table(results)}\n"
    )
    create_file(paths["md"], lambda tmp: tmp.write_text(text))
    plot(results, paths["png"])
    return paths


def check_out(out_dir: str | Path) -> None:
    """Refuse an output directory that already holds results (before measuring)."""
    refuse_existing([Path(out_dir) / name for name in OUTPUTS], "give a new --out")


def load(path: str | Path) -> list[Measurement]:
    """The measurements of a ``results.json`` written by :func:`write`."""
    from beacon_torch import received

    fields = Measurement.__dataclass_fields__
    record = received.json_file(path, "benchmark's results")
    rows = record.get("results") if isinstance(record, dict) else None
    if not isinstance(rows, list) or not all(isinstance(row, dict) for row in rows):
        raise received.BadFile(f"{path}: not a benchmark's results (no list of measurements under 'results')")
    # records written before the warm-up and memory columns existed lack them
    return [Measurement(**{k: row.get(k) for k in fields}) for row in rows]


def plot(results: Sequence[Measurement], path: str | Path) -> None:
    """Throughput against batch size, one panel per env, a line per mode and dtype; the
    published single-environment speed dashed."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    envs = list(dict.fromkeys(m.env for m in results))
    cols = min(4, len(envs))
    rows = (len(envs) + cols - 1) // cols
    fig = Figure(figsize=(3.6 * cols, 3.0 * rows), dpi=100)
    FigureCanvasAgg(fig)
    for k, env_id in enumerate(envs):
        ax = fig.add_subplot(rows, cols, k + 1)
        mine = [m for m in results if m.env == env_id]
        for key in dict.fromkeys((m.mode, m.dtype) for m in mine):
            line = sorted((m for m in mine if (m.mode, m.dtype) == key), key=lambda m: m.batch)
            ax.plot([m.batch for m in line], [m.transitions_per_s for m in line], "o-", label=f"{key[0]} {key[1]}")
        if mine[0].published_per_s:
            ax.axhline(mine[0].published_per_s, color="k", ls="--", lw=1, label="published (1 env)")
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_title(env_id, fontsize=10)
        ax.set_xlabel("batch size")
        if k % cols == 0:
            ax.set_ylabel("transitions / s")
        ax.grid(alpha=0.3, which="both")
        if k == 0:
            ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)


def full_table(results: Sequence[Measurement]) -> str:
    """Every measurement as a Markdown table."""
    lines = [
        "| env | mode | dtype | batch | transitions/s | vs published | step ms | compile s | recompiles | peak MB |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for m in results:
        vs = f"{m.speedup:.2f}x" if m.speedup is not None else "-"
        lines.append(
            f"| {m.env} | {m.mode} | {m.dtype} | {m.batch} | {m.transitions_per_s:,.1f} | {vs} | "
            f"{m.step_ms:.3f} | {m.compile_s:.1f} | {'-' if m.recompiles is None else m.recompiles} | "
            f"{'-' if m.peak_mb is None else f'{m.peak_mb:.0f}'} |"
        )
    return "\n".join(lines)


def markdown(results: Sequence[Measurement]) -> str:
    """The best float32 speed of each env against its target, as a Markdown table."""
    lines = [
        "| env | best transitions/s | at batch | mode | vs published | target | met |",
        "|---|---|---|---|---|---|---|",
    ]
    for env_id, m in best(results).items():
        target = env_spec(env_id).card.speed_target
        # the target is for the best of the default batch sizes: judged only over them
        measured = {r.batch for r in results if r.env == env_id and r.dtype == "float32"}
        judged = set(default_batch_sizes(env_id)) <= measured
        met = "" if target is None or m.speedup is None else ("yes" if m.speedup >= target else "**no**")
        if met and not judged:
            met = f"not judged (measured at {', '.join(map(str, sorted(measured)))} only)"
        vs = f"{m.speedup:.1f}x" if m.speedup is not None else "-"
        tgt = f"{target:g}x" if target else "-"
        lines.append(f"| {env_id} | {m.transitions_per_s:,.1f} | {m.batch} | {m.mode} | {vs} | {tgt} | {met} |")
    return "\n".join(lines)


if __name__ == "__main__":  # one measurement in a fresh process: measure_in_fresh_process
    _measure_job(*sys.argv[1:])
