"""The 2-D flows' C kernels alone, in two versions of the package: time a call, and
whether the two give the same results to the last bit.

    .venv/bin/python benchmarks/c_kernels.py BEFORE AFTER [--calls 1000] [--repeats 3] [--out DIR]

``BEFORE`` and ``AFTER`` are source trees of the package (clones or worktrees of two
commits; one tree times that tree alone). Each tree's kernel source
(``beacon_torch.numerics.native``) is built with the flags of this checkout's, and each
kernel (the transport sweep and its reverse, the line solve, the momentum terms'
adjoint) is called on the same random inputs at the cavities' sizes and the batches the
recipes use: the smallest of ``--repeats`` times ``--calls`` calls, one thread, the
trees' calls alternating. Writes a new ``c-kernels-DATE-TIME.json`` (machine, trees and
their commits, each case's times and equality) to ``--out`` and prints a table.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve()
# (kernel, sizes, members, dtype): rayleigh's 50 x 50 cells, mixing's 100 x 100, the
# batches of 8 and 16 the kernels are inlined for and one they are not
CASES = [
    (kernel, sizes, members, dtype)
    for kernel, grids in (
        ("sweep", ((50, 50), (100, 100))),
        ("sweep_adjoint", ((50, 50), (100, 100))),
        ("lines", ((25, 50), (50, 100))),
        ("momentum_adjoint", ((50, 50), (100, 100))),
    )
    for sizes in grids
    for members, dtype in ((8, "float32"), (16, "float32"), (5, "float32"), (8, "float64"))
]


def source(tree: Path) -> str:
    """The C source of the kernels in ``tree``."""
    code = "import sys; from beacon_torch.numerics import native; sys.stdout.write(native._SOURCE)"
    env = {**os.environ, "PYTHONPATH": str(tree)}
    # run from the tree, so that the working directory's package cannot come first
    done = subprocess.run([sys.executable, "-c", code], env=env, cwd=tree, capture_output=True, text=True, check=True)
    return done.stdout


def build(text: str, folder: Path, name: str) -> ctypes.CDLL:
    """``text`` compiled as this checkout's kernels are."""
    from beacon_torch.numerics import native

    c, so = folder / f"{name}.c", folder / f"{name}.so"
    c.write_text(text)
    compiler = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    try:
        native._compile(compiler, (*native._FLAGS, *native._HOST), str(c), str(so))
    except subprocess.CalledProcessError:  # a compiler that does not know this CPU, as native falls back
        native._compile(compiler, native._FLAGS, str(c), str(so))
    return ctypes.CDLL(str(so))


def inputs(kernel: str, sizes: tuple[int, int], members: int, dtype: torch.dtype):
    """``(outputs, inputs, integers)`` of one call, random and fixed by the case."""
    from beacon_torch.numerics.staggered import Uniform, multipliers

    g = torch.Generator().manual_seed(0)
    rand = lambda *shape: torch.randn(shape, generator=g, dtype=dtype)
    nx, ny = sizes
    if kernel == "sweep":
        s, a, b = rand(nx + 2, ny + 2, members), 0.2 * rand(nx, ny, members).abs(), 0.2 * rand(nx, ny, members).abs()
        return [torch.empty_like(s)], [s, a, b], [nx, ny, members]
    if kernel == "sweep_adjoint":
        grad, x = rand(nx + 2, ny + 2, members), rand(nx + 2, ny + 2, members)
        a, b = 0.2 * rand(nx, ny, members).abs(), 0.2 * rand(nx, ny, members).abs()
        return [torch.empty_like(grad), torch.empty_like(a), torch.empty_like(a)], [grad, x, a, b], [nx, ny, members]
    if kernel == "lines":
        modes, n = sizes
        f, lower, inv, upper = rand(modes, n, members), rand(modes, n), 1.0 + rand(modes, n).abs(), rand(n)
        return [torch.empty_like(f)], [f, lower, inv, upper], [modes, n, members]
    u, v = rand(nx + 1, ny + 2, members), rand(nx + 2, ny + 1, members)
    gu, gv, nu = rand(nx - 1, ny, members), rand(nx, ny - 1, members), 0.01 + rand(members).abs()
    cx, cy = multipliers(Uniform(1 / nx), nx, u), multipliers(Uniform(1 / ny), ny, u)
    return [torch.empty_like(u), torch.empty_like(v)], [u, v, gu, gv, nu, cx, cy], [nx, ny, members]


def measure(libraries: list[ctypes.CDLL], calls: int, repeats: int) -> list[dict]:
    rows = []
    for kernel, sizes, members, dtype_name in CASES:
        dtype = getattr(torch, dtype_name)
        outs, ins, integers = inputs(kernel, sizes, members, dtype)
        suffix = "f32" if dtype == torch.float32 else "f64"
        results, best = [], [float("inf")] * len(libraries)
        for repeat in range(repeats):
            for k, lib in enumerate(libraries):
                outputs = [torch.full_like(t, float("nan")) for t in outs]
                args = [ctypes.c_void_p(t.data_ptr()) for t in (*outputs, *ins)]
                args += [ctypes.c_long(i) for i in integers]
                call = getattr(lib, f"{kernel}_{suffix}")
                call(*args)
                if repeat == 0:
                    results.append([t.clone() for t in outputs])
                start = time.perf_counter()
                for _ in range(calls):
                    call(*args)
                best[k] = min(best[k], (time.perf_counter() - start) / calls)
        same = all(torch.equal(a, b) for r in results[1:] for a, b in zip(results[0], r, strict=True))
        rows.append(
            dict(
                kernel=kernel,
                sizes=list(sizes),
                members=members,
                dtype=dtype_name,
                us=[t * 1e6 for t in best],
                equal=same,
            )
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("trees", nargs="+", type=Path, help="BEFORE [AFTER]: source trees of the package")
    parser.add_argument("--calls", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=HERE.parent / "results" / "c_kernels")
    args = parser.parse_args()
    if len(args.trees) > 2:
        parser.error("give one or two source trees")
    from beacon_torch.files import machine, revision

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as folder:
        libraries = [build(source(t.resolve()), Path(folder), f"tree{k}") for k, t in enumerate(args.trees)]
        rows = measure(libraries, args.calls, args.repeats)
    record = dict(
        machine=machine(),
        trees=[str(t) for t in args.trees],
        commits=[revision(t) for t in args.trees],
        calls=args.calls,
        repeats=args.repeats,
        rows=rows,
    )
    print("| kernel | cells | members | dtype | us a call, per tree | equal |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        times = " / ".join(f"{t:.1f}" for t in r["us"])
        cells = f"{r['sizes'][0]} x {r['sizes'][1]}"
        print(f"| {r['kernel']} | {cells} | {r['members']} | {r['dtype']} | {times} | {r['equal']} |")
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / f"c-kernels-{time.strftime('%Y%m%d-%H%M%S')}.json"
    with open(path, "x") as f:  # a new record, never one replaced
        json.dump(record, f, indent=1)
    print(f"written to {path}")


if __name__ == "__main__":
    main()
