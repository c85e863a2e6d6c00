"""The cylinder's validation against the Schaefer & Turek (1996) benchmark 2D-2."""

from __future__ import annotations

import numpy as np

from beacon_torch.envs.cylinder.channel import DIAMETER, U_MEAN

# the benchmark's intervals (Schaefer & Turek 1996, unsteady case 2D-2)
SCHAEFER_TUREK = {"cd_max": (3.22, 3.24), "cl_max": (0.99, 1.01), "strouhal": (0.295, 0.305)}


def shedding_figures(time: np.ndarray, drag: np.ndarray, lift: np.ndarray, window: float = 2.0) -> dict[str, float]:
    """The benchmark's figures over the last ``window`` time units of drag and lift
    coefficient histories: ``cd_max``, ``cl_max``, ``cd_mean`` and ``strouhal`` (D f / U,
    the period from the lift's upward crossings of its mean, linearly interpolated)."""
    last = time > time[-1] - window
    t, cd, cl = time[last], drag[last], lift[last]
    s = cl - cl.mean()
    up = np.nonzero((s[:-1] < 0) & (s[1:] >= 0))[0]
    crossings = t[up] - s[up] * (t[up + 1] - t[up]) / (s[up + 1] - s[up])
    period = float(np.diff(crossings).mean()) if len(crossings) > 1 else float("nan")
    return {
        "cd_max": float(cd.max()),
        "cl_max": float(cl.max()),
        "cd_mean": float(cd.mean()),
        "strouhal": DIAMETER / (U_MEAN * period),
    }
