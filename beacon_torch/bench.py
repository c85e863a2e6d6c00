"""Throughput of the environments against the published code's speed.

``beacon-torch bench`` (and ``benchmarks/throughput.py``) measure, per env, batch size,
dtype and mode (eager or compiled): transitions per second (the median of several
timed repeats after a warm-up that includes any compilation), the latency of one step
at batch 1, the compile time and the memory. Random actions from a fixed generator;
episodes are reset as they end (TorchRL's ``step_and_maybe_reset``), as a collector does.

Memory: on CUDA the peak allocated by torch during the measurement; on CPU the bytes of
the env's state tensors and the process's peak resident size so far (the CPU allocator
has no per-measurement peak).
"""

from __future__ import annotations

import csv
import json
import platform
import resource
import statistics
import time
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from beacon_torch.files import save_figure
from beacon_torch.registry import env_class, make

BATCH_SIZES = (1, 16, 64, 256, 1024)
CAVITY_BATCH_SIZES = (1, 16, 32, 64)


def default_batch_sizes(env_id: str) -> tuple[int, ...]:
    return CAVITY_BATCH_SIZES if env_class(env_id).family == "cavity" else BATCH_SIZES


def default_steps(env_id: str) -> int:
    """Timed steps per repeat: enough to dwarf the timer, few for the costly cavities."""
    return 2 if env_class(env_id).family == "cavity" else 20


@dataclass
class Measurement:
    env: str
    batch: int
    dtype: str
    mode: str
    device: str
    transitions_per_s: float
    step_ms: float  # median wall time of one batched step
    compile_s: float  # the first step minus a later one: compilation (shkadov compiles at reset)
    state_mb: float
    peak_mb: float
    published_per_s: float | None
    speedup: float | None

    def row(self) -> str:
        vs = f"{self.speedup:7.1f}x" if self.speedup is not None else "        "
        return (
            f"{self.env:<22} {self.mode:<8} {self.dtype:<8} {self.batch:>6} {self.transitions_per_s:>14,.1f} {vs}"
            f" {self.step_ms:>10.3f} {self.compile_s:>9.1f} {self.peak_mb:>9.1f}"
        )


HEADER = (
    f"{'env':<22} {'mode':<8} {'dtype':<8} {'batch':>6} {'transitions/s':>14} {'vs pub':>8} "
    f"{'step ms':>10} {'compile s':>9} {'peak MB':>9}"
)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _state_mb(env) -> float:
    return sum(t.numel() * t.element_size() for t in env.state if isinstance(t, torch.Tensor)) / 2**20


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
) -> Measurement:
    """Transitions per second of ``env_id`` at ``batch`` members (see the module doc)."""
    if mode not in ("eager", "compiled"):
        raise ValueError(f"mode must be 'eager' or 'compiled', got {mode!r}")
    if repeats < 1:
        raise ValueError(f"repeats must be a positive integer, got {repeats}")
    steps = steps or default_steps(env_id)
    dev = torch.device(device)
    env = make(env_id, batch, dtype=dtype, device=device, seed=seed, compile=mode == "compiled", check_actions=False)
    g = torch.Generator(device=dev).manual_seed(seed)
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
    td = env.reset()

    def step(td):
        td[env.action_key] = env.random_action(g)
        _, td = env.step_and_maybe_reset(td)
        return td

    _sync(dev)
    start = time.perf_counter()
    td = step(td)  # the warm-up step compiles
    _sync(dev)
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(steps):
            td = step(td)
        _sync(dev)
        times.append((time.perf_counter() - start) / steps)
    step_s = statistics.median(times)
    rate = batch / step_s
    if dev.type == "cuda":
        peak = torch.cuda.max_memory_allocated(dev) / 2**20
    else:
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux
    published = env_class(env_id).published_speed
    return Measurement(
        env=env_id,
        batch=batch,
        dtype=str(dtype).removeprefix("torch."),
        mode=mode,
        device=str(dev),
        transitions_per_s=rate,
        step_ms=1e3 * step_s,
        compile_s=max(0.0, first - step_s),
        state_mb=_state_mb(env),
        peak_mb=peak,
        published_per_s=published,
        speedup=rate / published if published else None,
    )


def machine() -> str:
    """A one-line description of where the numbers come from."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    text = f"{cpu}, {torch.get_num_threads()} threads, torch {torch.__version__}, Python {platform.python_version()}"
    if torch.cuda.is_available():
        text += f", GPU {torch.cuda.get_device_name()}"
    return text


def save_rows(rows: list[dict], out: str | Path, name: str) -> Path:
    """``rows`` with the machine they were measured on, as ``out/name.json``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{name}.json"
    path.write_text(json.dumps({"machine": machine(), "rows": rows}, indent=1))
    return path


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
) -> list[Measurement]:
    """Every combination, printed as a table while it runs."""
    echo(f"# {machine()}")
    echo(HEADER)
    results = []
    for env_id in env_ids:
        for dtype in dtypes:
            for mode in modes:
                for batch in num_envs or default_batch_sizes(env_id):
                    m = measure(env_id, batch, dtype=dtype, mode=mode, device=device, steps=steps, repeats=repeats)
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


def write(results: Sequence[Measurement], out_dir: str | Path) -> dict[str, Path]:
    """``results.csv``, ``results.json``, ``results.md`` and ``throughput.png`` in
    ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = [asdict(m) for m in results]
    paths = {
        "csv": out / "results.csv",
        "json": out / "results.json",
        "md": out / "results.md",
        "png": out / "throughput.png",
    }
    with paths["csv"].open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    paths["json"].write_text(json.dumps({"machine": machine(), "results": rows}, indent=2))
    paths["md"].write_text(
        f"Machine: {machine()}\n\n## Best speed per env\n\n{markdown(results)}\n\n## Every "
        f"measurement\n\n{full_table(results)}\n"
    )
    plot(results, paths["png"])
    return paths


def load(path: str | Path) -> list[Measurement]:
    """The measurements of a ``results.json`` written by :func:`write`."""
    return [Measurement(**row) for row in json.loads(Path(path).read_text())["results"]]


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
        "| env | mode | dtype | batch | transitions/s | vs published | step ms | compile s | peak MB |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for m in results:
        vs = f"{m.speedup:.2f}x" if m.speedup is not None else "-"
        lines.append(
            f"| {m.env} | {m.mode} | {m.dtype} | {m.batch} | {m.transitions_per_s:,.1f} | {vs} | "
            f"{m.step_ms:.3f} | {m.compile_s:.1f} | {m.peak_mb:.0f} |"
        )
    return "\n".join(lines)


def markdown(results: Sequence[Measurement]) -> str:
    """The best float32 speed of each env against its target, as a Markdown table."""
    lines = [
        "| env | best transitions/s | at batch | mode | vs published | target | met |",
        "|---|---|---|---|---|---|---|",
    ]
    for env_id, m in best(results).items():
        target = env_class(env_id).speed_target
        met = "" if target is None or m.speedup is None else ("yes" if m.speedup >= target else "**no**")
        vs = f"{m.speedup:.1f}x" if m.speedup is not None else "-"
        tgt = f"{target:g}x" if target else "-"
        lines.append(f"| {env_id} | {m.transitions_per_s:,.1f} | {m.batch} | {m.mode} | {vs} | {tgt} | {met} |")
    return "\n".join(lines)
