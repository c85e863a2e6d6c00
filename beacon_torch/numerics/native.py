"""Loop kernels in C, for the recurrences that tensor operations cannot batch away.

The cavities' published transport sweep updates the cells in place one after the other,
each reading the new values of its west and south neighbours. As tensor operations it
is a chain of ``nx + ny - 1`` dependent anti-diagonal steps per substep, whose fixed
cost per operation (a few microseconds) is most of a cavity step at small batches. The
same loop written in C, over the cells with the members innermost, costs what its
arithmetic costs.

The kernel is compiled from the source below with the system's C compiler, once per
process, into a fresh private directory (nothing is read from a shared cache, so no
file that someone else could have written is ever loaded), and called through
``ctypes`` on the tensors' memory. Where there is no compiler, the build fails, the
tensors are not on the CPU, or ``BEACON_TORCH_NATIVE=0``, :func:`applies` says no and
the caller keeps its tensor path. Gradients never go through here: the callers use it
only when autograd has nothing to record.
"""

from __future__ import annotations

import ctypes
import os
import shutil
import subprocess
import tempfile
import threading
import warnings

import torch

# Written as the published loop: x outer, y inner, each cell's new value
# (c + a * west) + b * south, members innermost (the contiguous axis, so the compiler
# vectorises it). No fused multiply-adds, so that the float64 results are the
# published ones to the last bits that plain arithmetic allows.
_SOURCE = r"""
#define SWEEP(NAME, T)                                                              \
void NAME(T *s, const T *a, const T *b, long nx, long ny, long members) {          \
    const long column = (ny + 2) * members;                                         \
    for (long i = 1; i <= nx; ++i) {                                                \
        for (long j = 1; j <= ny; ++j) {                                            \
            T *x = s + i * column + j * members;                                    \
            const T *west = x - column, *south = x - members;                       \
            const T *ai = a + ((i - 1) * ny + (j - 1)) * members;                   \
            const T *bi = b + ((i - 1) * ny + (j - 1)) * members;                   \
            for (long m = 0; m < members; ++m)                                      \
                x[m] = (x[m] + ai[m] * west[m]) + bi[m] * south[m];                 \
        }                                                                           \
    }                                                                               \
}
SWEEP(sweep_f32, float)
SWEEP(sweep_f64, double)
"""

_FLAGS = ("-O3", "-fPIC", "-shared", "-ffp-contract=off", "-fno-fast-math")

_lock = threading.Lock()
_library: ctypes.CDLL | None = None
_tried = False


def _build() -> ctypes.CDLL | None:
    compiler = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        return None
    folder = tempfile.mkdtemp(prefix="beacon-torch-native-")
    source, library = os.path.join(folder, "sweep.c"), os.path.join(folder, "sweep.so")
    with open(source, "w") as f:
        f.write(_SOURCE)
    try:
        subprocess.run([compiler, *_FLAGS, source, "-o", library], check=True, capture_output=True, timeout=120)
        lib = ctypes.CDLL(library)
    except (OSError, subprocess.SubprocessError) as err:
        warnings.warn(f"beacon_torch: the C transport sweep could not be built ({err}); using the slower tensor sweep", RuntimeWarning, stacklevel=3)
        return None
    finally:
        # the loaded library stays mapped after its file is gone
        shutil.rmtree(folder, ignore_errors=True)
    for name, ctype in (("sweep_f32", ctypes.c_float), ("sweep_f64", ctypes.c_double)):
        fn = getattr(lib, name)
        pointer = ctypes.POINTER(ctype)
        fn.argtypes = (pointer, pointer, pointer, ctypes.c_long, ctypes.c_long, ctypes.c_long)
        fn.restype = None
    return lib


def library() -> ctypes.CDLL | None:
    """The compiled kernels, built on the first call of the process (None where they
    cannot be, or ``BEACON_TORCH_NATIVE=0``)."""
    global _library, _tried
    if os.environ.get("BEACON_TORCH_NATIVE", "1") == "0":
        return None
    if not _tried:
        with _lock:
            if not _tried:
                _library = _build()
                _tried = True
    return _library


_KERNELS = {torch.float32: ("sweep_f32", ctypes.c_float), torch.float64: ("sweep_f64", ctypes.c_double)}


def applies(device, dtype) -> bool:
    """Whether :func:`sweep` runs for fields of this device and dtype (building the
    kernel on the first call)."""
    return torch.device(device).type == "cpu" and dtype in _KERNELS and library() is not None


# A custom operator, so that a compiled substep calls the loop inside its graph (no
# graph break): out of place, as the graph's functional form wants.
@torch.library.custom_op("beacon_torch::sweep", mutates_args=())
def sweep(s: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The in-place sweep on a copy of ``s`` (ghosted, ``[nx + 2, ny + 2, B]``, interior
    holding each cell's part from old values): cell ``(i, j)`` becomes
    ``s[i, j] + a * s[i - 1, j] + b * s[i, j - 1]`` with the new values of its west and
    south neighbours, for the interior coefficients ``a``, ``b`` (``[nx, ny, B]``).
    Only where :func:`applies`; never differentiated."""
    nx, ny, members = a.shape
    if s.shape != (nx + 2, ny + 2, members) or b.shape != a.shape or not (s.dtype == a.dtype == b.dtype):
        raise ValueError(f"sweep: the field {tuple(s.shape)} and coefficients {tuple(a.shape)}, {tuple(b.shape)} do not fit")
    # the switch BEACON_TORCH_NATIVE is read where the caller decides (applies), not here
    lib = _library if _tried else library()
    if s.device.type != "cpu" or s.dtype not in _KERNELS or lib is None:
        raise RuntimeError("sweep: the C kernel does not apply here (see native.applies)")
    name, ctype = _KERNELS[s.dtype]
    out, a, b = s.clone(memory_format=torch.contiguous_format), a.contiguous(), b.contiguous()
    pointer = ctypes.POINTER(ctype)
    getattr(lib, name)(*(ctypes.cast(t.data_ptr(), pointer) for t in (out, a, b)), nx, ny, members)
    return out


@sweep.register_fake
def _(s: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.empty_like(s, memory_format=torch.contiguous_format)
