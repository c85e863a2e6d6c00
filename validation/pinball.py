"""pinball-v0's validation: the steady flow at Re 30 against HydroGym's recorded
forces, the Reynolds numbers of the first two bifurcations against Deng et al.'s, the
levels' flows and their references.

    .venv/bin/python validation/pinball.py steady [--cells 10 20 30] [--setups ...]
    .venv/bin/python validation/pinball.py thresholds [--cells 10 20] [--hopf RE ...] [--pitchfork RE ...]
    .venv/bin/python validation/pinball.py pitchfork [--cells 10 20] [--developed RE ...] [--time 400]
    .venv/bin/python validation/pinball.py base [--cells 10 20] [--re 30 100 130] [--time 300] [--chi 0]
    .venv/bin/python validation/pinball.py regimes [--cells 10 20] [--re 100 130]
    .venv/bin/python validation/pinball.py page

HydroGym's pinball test solves the steady flow at Re 30 on its fine mesh by Newton's
method and records each cylinder's drag and lift coefficients (front, top, bottom):
C_D = (1.451, 1.566, 1.566), C_L = (0, 0.521, -0.521). Its mesh puts the front
cylinder at the origin of the box [-6, 20] x [-6, 6] (so the inflow is 6 D ahead of
it, 4.7 D in Deng et al.'s box, where the origin lies between the rear cylinders), and
the mesh file of that test's time puts the rear cylinders 1.5 x 1.866 R behind the
front one, not the triangle's 1.5 x 1.732 R. Each set-up here starts from the free
stream and runs in float64 at Re 30 without control until the drag changes by less
than 1e-6 over a time unit (or ``--time`` units):

- ``hydrogym-mesh``: HydroGym's box and its mesh's cylinders (the reference's set-up);
- ``hydrogym-box``: HydroGym's box with the equilateral triangle;
- ``pinball-v0``: the env's own box and triangle (Deng et al.'s).

Prints each set-up's coefficients beside the reference and writes them to a new dated
``pinball_steady-DATE-TIME.json`` in ``--out`` (validation/results/pinball/).

``thresholds``: the bifurcations of the steady symmetric flow (Deng et al.: a Hopf
bifurcation near Re 18, a pitchfork near Re 68, both breaking the mirror symmetry; the
sweeps here show the pitchfork to be the periodic flow's, not the steady one's, which
``pitchfork`` measures). At each Re of a sweep,
the steady symmetric solution (the mirror-symmetric grid keeps a flow started from the
free stream symmetric, so it settles there whether or not it is stable) is disturbed
by turning the front cylinder at 1e-6 for one time unit, an antisymmetric kick, and the
front cylinder's lift (zero on the symmetric flow) followed in the linear regime:

- the Hopf mode is the leading oscillating one: its growth rate is that of the lift's
  oscillation (a two-mode fit of the delayed signal, dynamic mode decomposition);
- the pitchfork mode is a real one, which the Hopf mode's faster growth hides: the run
  is repeated with selective frequency damping (Akervik et al. 2006: every step the flow
  is pulled towards its own low-pass filtered self), which damps oscillating modes but
  leaves a real eigenvalue's sign as it is (the damped system's determinant changes sign
  with it), and the growth rate is that of the lift's steady drift (a one-mode fit).

Each threshold is where the growth rate changes sign, interpolated linearly between the
sweep's neighbours. Writes ``pinball_thresholds-DATE-TIME.json``.

``pitchfork``: the developed flows' mean asymmetry over a sweep of Re (one batch of
members, each from the asymmetric developed flow at Re 100) and the threshold where
the supercritical normal form puts its zero. Writes ``pinball_pitchfork-DATE-TIME.json``.

``base``: each level's reference, the steady symmetric flow (mirror-symmetric marching
from the developed flow) and its drag beside the uncontrolled flow's mean. Writes
``pinball_base-DATE-TIME.json``.

``regimes``: the developed flows at the levels' Reynolds numbers (the env's start, then
``--time`` units): mean forces, the front lift's Strouhal number and spectrum, and the
leading Lyapunov exponent from a twin trajectory 1e-8 away (in the velocity's 2-norm
over the faces), its distance restored every time unit: about zero for a periodic or
quasi-periodic flow, positive for a chaotic one. Writes ``pinball_regimes-DATE-TIME.json``.

``page``: writes the newest records' tables to the env's page. Each run is its own
process.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import math
import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "validation" / "results" / "pinball"
BEGIN, END = "<!-- steady: validation/pinball.py -->", "<!-- end of the steady -->"
THRESHOLDS_BEGIN = "<!-- thresholds: validation/pinball.py -->"
THRESHOLDS_END = "<!-- end of the thresholds -->"
PITCHFORK_BEGIN = "<!-- pitchfork: validation/pinball.py -->"
PITCHFORK_END = "<!-- end of the pitchfork -->"
BASE_BEGIN, BASE_END = "<!-- base flows: validation/pinball.py -->", "<!-- end of the base flows -->"
REGIMES_BEGIN, REGIMES_END = "<!-- regimes: validation/pinball.py -->", "<!-- end of the regimes -->"

RE = 30.0
# HydroGym's test_steady (fine mesh): front, top, bottom
HYDROGYM = {"drag": (1.451, 1.566, 1.566), "lift": (0.0, 0.521, -0.521)}
SETUPS = ("hydrogym-mesh", "hydrogym-box", "pinball-v0")


def geometry(setup: str):
    """The cylinders and the box's x range of a set-up, in the env's coordinates."""
    from beacon_torch.envs.pinball.flow import CYLINDERS, RADIUS, X_RANGE
    from beacon_torch.numerics.bodies import Circle

    if setup == "pinball-v0":
        return CYLINDERS, X_RANGE
    rear = 1.5 * (1.866 if setup == "hydrogym-mesh" else math.sqrt(3.0)) * RADIUS
    cylinders = (Circle(-rear, 0.0, RADIUS), *CYLINDERS[1:])
    # HydroGym's box is [-6, 20] from the front cylinder's centre
    return cylinders, (-6.0 - rear, 20.0 - rear)


def time_step(cells: int, re: float = RE) -> float:
    """The time step of a grid at ``re``: the env's, or less where that leaves the
    grid-scale diffusion 8 nu dt / h^2 above 1/2."""
    from beacon_torch.envs.pinball.flow import DT

    h = 1.0 / cells
    return min(DT, 0.5 * h * h * re / 8.0)


def measure(setup: str, cells: int, time: float) -> dict:
    import numpy as np
    import torch

    from beacon_torch.envs.pinball.flow import Box, coefficient, rest, run

    torch.set_num_threads(1)
    cylinders, x_range = geometry(setup)
    box = Box(cells, cylinders=cylinders, x_range=x_range, dtype=torch.float64, device="cpu")
    dt = time_step(cells)
    flow = rest(1, box, torch.float64, "cpu")
    still = torch.zeros(1, 3, dtype=torch.float64)
    per_unit = int(round(1.0 / dt))
    history, change = [], float("inf")
    with torch.no_grad():
        for k in range(int(time)):
            flow, loads = run(flow, per_unit, still, box, 1.0 / RE, dt)
            drag, lift = coefficient(loads[0, 0]).numpy(), coefficient(loads[0, 1]).numpy()
            if history:
                change = float(np.abs(drag - history[-1]["drag"]).max())
            history.append({"time": k + 1.0, "drag": drag.tolist(), "lift": lift.tolist()})
            if change < 1e-6:
                break
    last = history[-1]
    return {
        "setup": setup,
        "cells_per_diameter": cells,
        "dt": dt,
        "cells": box.nx * box.ny,
        "time": last["time"],
        "last_change": change,
        "drag": last["drag"],
        "lift": last["lift"],
        "history": history,
    }


KICK = 1e-6  # the front cylinder's angular velocity for the first time unit
SAMPLE = 0.5  # time units between the lift's samples
# selective frequency damping: the damping rate and the filter's width in time
SFD_CHI, SFD_DELTA = 1.0, 5.0


def mirrored(flow):
    """The flow's mirror-symmetric part about y = 0 (the grid is mirror-symmetric: u, p
    and the x-tendency are even in y, v and the y-tendency odd)."""
    even = lambda f: 0.5 * (f + f.flip(-1))
    odd = lambda f: 0.5 * (f - f.flip(-1))
    return flow._replace(u=even(flow.u), v=odd(flow.v), p=even(flow.p), hu=even(flow.hu), hv=odd(flow.hv))


def symmetric_base(box, re: float, dt: float, start=None, time: float = 200.0):
    """The steady symmetric flow at ``re``: from ``start`` (or the free stream) until the
    drag changes by less than 1e-8 over a time unit, kept mirror-symmetric after every
    time unit (the round-off's asymmetry would otherwise grow where the flow is
    unstable)."""
    import numpy as np
    import torch

    from beacon_torch.envs.pinball.flow import rest, run

    flow = rest(1, box, torch.float64, "cpu") if start is None else start
    still = torch.zeros(1, 3, dtype=torch.float64)
    previous = None
    with torch.no_grad():
        for _ in range(int(time)):
            flow, loads = run(mirrored(flow), int(round(1.0 / dt)), still, box, 1.0 / re, dt)
            drag = loads[0, 0].numpy()
            if previous is not None and np.abs(drag - previous).max() < 1e-8:
                break
            previous = drag
    return mirrored(flow)


def antisymmetric_lift(box, re: float, dt: float, base, time: float, damped: bool):
    """The front cylinder's lift coefficient every ``SAMPLE`` time units after the kick,
    with selective frequency damping or without."""
    import numpy as np
    import torch

    from beacon_torch.envs.pinball.flow import coefficient, run
    from beacon_torch.numerics import frequency_damping

    flow, per_sample = base, int(round(SAMPLE / dt))
    filtered = base.u.clone(), base.v.clone()
    lift = []
    with torch.no_grad():
        for k in range(int(round(time / SAMPLE))):
            kick = KICK if k * SAMPLE < 1.0 else 0.0
            target = torch.tensor([[kick, 0.0, 0.0]], dtype=torch.float64)
            total = 0.0
            for _ in range(per_sample):
                flow, loads = run(flow, 1, target, box, 1.0 / re, dt)
                total += float(loads[0, 1, 0])
                if damped:
                    (u, v), filtered = frequency_damping((flow.u, flow.v), filtered, dt, SFD_CHI, SFD_DELTA)
                    flow = flow._replace(u=u, v=v)
            lift.append(float(coefficient(torch.tensor(total / per_sample))))
    return np.array(lift)


def growth(signal, rank: int, skip: float, delays: int = 12) -> complex:
    """The leading eigenvalue (growth rate + i angular frequency, per time unit) of a
    ``rank``-mode fit of ``signal`` after ``skip`` time units (dynamic mode
    decomposition of its delay embedding)."""
    import numpy as np

    s = signal[int(round(skip / SAMPLE)) :]
    s = s / np.abs(s).max()
    hankel = np.stack([s[i : len(s) - delays + i] for i in range(delays)])
    x, y = hankel[:, :-1], hankel[:, 1:]
    u, sv, vh = np.linalg.svd(x, full_matrices=False)
    u, sv, vh = u[:, :rank], sv[:rank], vh[:rank]
    a = u.T @ y @ vh.T / sv
    rates = np.log(np.linalg.eigvals(a).astype(complex)) / SAMPLE
    return complex(max(rates, key=lambda z: z.real))


def sweep(cells: int, kind: str, reynolds: list[float], time: float) -> dict:
    """The growth rates of the Hopf (``kind`` "hopf") or the pitchfork mode over a
    sweep of Re, one grid, in one process."""
    import torch

    from beacon_torch.envs.pinball.flow import Box

    torch.set_num_threads(1)
    box = Box(cells, dtype=torch.float64, device="cpu")
    rows, base = [], None
    for re in sorted(reynolds):
        dt = time_step(cells, re)
        base = symmetric_base(box, re, dt, start=base)
        lift = antisymmetric_lift(box, re, dt, base, time, damped=kind == "pitchfork")
        rate = growth(lift, 2 if kind == "hopf" else 1, skip=0.4 * time)
        rows.append({"re": re, "dt": dt, "rate": rate.real, "frequency": abs(rate.imag), "lift": lift.tolist()})
    return {"kind": kind, "cells_per_diameter": cells, "time": time, "points": rows}


def threshold(points: list[dict]) -> float:
    """The Re where the growth rate changes sign, linear between the sweep's neighbours
    (nan if it does not change sign in the sweep)."""
    for a, b in zip(points, points[1:], strict=False):
        if a["rate"] < 0 <= b["rate"]:
            return a["re"] - a["rate"] * (b["re"] - a["re"]) / (b["rate"] - a["rate"])
    return float("nan")


PITCHFORK_SAMPLE = 0.25  # time units between the lift's samples in the developed sweep
PITCHFORK_FROM = 100.0  # the developed flow every member of the sweep starts from


def whole_periods(front, total, window: int):
    """The mean of ``total`` over the whole shedding periods (between the first and the
    last upward zero crossing of the front lift's fluctuation) in its last ``window``
    samples, and the periods' mean length in samples (nan where it has not shed)."""
    import numpy as np

    f, t = front[-window:], total[-window:]
    f = f - f.mean()
    up = np.flatnonzero((f[:-1] < 0) & (f[1:] >= 0))
    if len(up) < 3 or np.abs(f).max() < 1e-6:
        return float(t.mean()), float("nan")
    return float(t[up[0] : up[-1]].mean()), float((up[-1] - up[0]) / (len(up) - 1))


def pitchfork(cells: int, reynolds: list[float], time: float) -> dict:
    """The developed flows' mean asymmetry over a sweep of Re, one batch of members on
    one grid: each member starts from the asymmetric developed flow at Re 100 and runs
    uncontrolled at its own Re for ``time`` units; the asymmetry is the mean of the
    three cylinders' summed lift coefficient over the last 100 units' whole shedding
    periods (zero for a flow whose mean is mirror-symmetric), its drift the change
    from the 100 units before."""
    import numpy as np
    import torch

    from beacon_torch.envs.pinball.env import developed_start
    from beacon_torch.envs.pinball.flow import DT, Box, Flow, coefficient, run

    torch.set_num_threads(1)
    res = sorted(reynolds)
    box = Box(cells, dtype=torch.float64, device="cpu")
    start = developed_start(cells, PITCHFORK_FROM)
    flow = Flow(*(f.expand(len(res), *f.shape).clone() for f in start))
    nu = 1.0 / torch.tensor(res, dtype=torch.float64)
    still = torch.zeros(len(res), 3, dtype=torch.float64)
    per_sample = int(round(PITCHFORK_SAMPLE / DT))
    lift = []
    with torch.no_grad():
        for _ in range(int(round(time / PITCHFORK_SAMPLE))):
            flow, loads = run(flow, per_sample, still, box, nu, DT)
            lift.append(coefficient(loads[:, 1]).numpy())
    lift = np.array(lift)  # [samples, member, cylinder]
    window = int(round(100.0 / PITCHFORK_SAMPLE))
    rows = []
    for m, re in enumerate(res):
        front, total = lift[:, m, 0], lift[:, m].sum(-1)
        last, period = whole_periods(front, total, window)
        before, _ = whole_periods(front[:-window], total[:-window], window)
        units = int(round(1.0 / PITCHFORK_SAMPLE))
        rows.append(
            {
                "re": re,
                "asymmetry": last,
                "drift": last - before,
                "strouhal": float(1.0 / (period * PITCHFORK_SAMPLE)) if period == period else 0.0,
                # one value per time unit: the summed lift's course
                "lift_history": total[: len(total) // units * units].reshape(-1, units).mean(1).tolist(),
            }
        )
    return {
        "kind": "pitchfork-developed",
        "cells_per_diameter": cells,
        "time": time,
        "from_re": PITCHFORK_FROM,
        "points": rows,
    }


def settled(point: dict) -> bool:
    """Whether a sweep point's asymmetry has settled: it drifted by less than a tenth of
    itself over the last 100 units, or there is none left (under 1e-3)."""
    return abs(point["drift"]) < 0.1 * abs(point["asymmetry"]) or abs(point["asymmetry"]) + abs(point["drift"]) < 1e-3


def pitchfork_threshold(points: list[dict]) -> float:
    """The pitchfork's Re from the supercritical normal form: the squared asymmetry of
    the settled asymmetric flows grows linearly with Re from the threshold. A least
    squares line through the settled points whose square is at least a twentieth of the
    sweep's largest; its zero (nan with fewer than two such points)."""
    import numpy as np

    steady = [p for p in points if settled(p)]
    top = max((p["asymmetry"] ** 2 for p in steady), default=0.0)
    fit = [p for p in steady if p["asymmetry"] ** 2 >= top / 20]
    if len(fit) < 2:
        return float("nan")
    slope, intercept = np.polyfit([p["re"] for p in fit], [p["asymmetry"] ** 2 for p in fit], 1)
    return float(-intercept / slope)


def base_flows(cells: int, reynolds: list[float], time: float, chi: float = 0.0) -> dict:
    """Each level's reference: the steady symmetric base flow at each Re, with its
    cylinders' drag beside the uncontrolled flow's mean. Two batches of one member per
    Re start from the levels' developed flows: one runs uncontrolled (its mean forces
    over the last half of ``time``), the other is made mirror-symmetric every time unit,
    which removes the antisymmetric shedding modes, the unstable ones, and leaves the
    symmetric remains of the shedding to leave the box. With ``chi`` > 0 it is also
    damped towards its own low-pass filtered self every step (selective frequency
    damping, filter width ``SFD_DELTA``), which also damps unstable symmetric modes but
    holds those remains back (measured at Re 100 on 10 cells: 120 time units leave the
    flow 5e-2 from its filtered self with ``chi`` 1, 1e-3 without). ``unit_change`` is
    the last time unit's largest change of the velocity, which a steady flow brings to
    zero."""
    import numpy as np
    import torch

    from beacon_torch.envs.pinball.env import developed_start
    from beacon_torch.envs.pinball.flow import DT, Box, Flow, coefficient, run
    from beacon_torch.numerics import frequency_damping

    torch.set_num_threads(1)
    res = sorted(reynolds)
    box = Box(cells, dtype=torch.float64, device="cpu")
    starts = [developed_start(cells, re) for re in res]
    free = Flow(*(torch.stack(f) for f in zip(*starts, strict=True)))
    damped = filtered = mirrored(free)
    nu = 1.0 / torch.tensor(res, dtype=torch.float64)
    still = torch.zeros(len(res), 3, dtype=torch.float64)
    per_unit, units = int(round(1.0 / DT)), int(round(time))
    free_loads, history = [], []
    with torch.no_grad():
        for k in range(units):
            free, loads = run(free, per_unit, still, box, nu, DT)
            free_loads.append(coefficient(loads[:, :2]).numpy())
            before = damped = mirrored(damped)
            if chi > 0:
                filtered, loads = mirrored(filtered), 0.0
                for _ in range(per_unit):
                    damped, step_loads = run(damped, 1, still, box, nu, DT)
                    loads = loads + step_loads / per_unit
                    (u, v), (u_bar, v_bar) = frequency_damping(
                        (damped.u, damped.v), (filtered.u, filtered.v), DT, chi, SFD_DELTA
                    )
                    damped, filtered = damped._replace(u=u, v=v), filtered._replace(u=u_bar, v=v_bar)
            else:
                damped, loads = run(damped, per_unit, still, box, nu, DT)
            change = torch.maximum(
                (damped.u - before.u).abs().flatten(1).amax(1), (damped.v - before.v).abs().flatten(1).amax(1)
            )
            forces = coefficient(loads[:, :2]).numpy()
            history.append({"time": k + 1.0, "drag": forces[:, 0].tolist(), "unit_change": change.tolist()})
    mean = np.array(free_loads[units // 2 :]).mean(0)  # [Re, drag and lift, cylinder]
    rows = []
    for m, re in enumerate(res):
        drag_base, drag_free = forces[m, 0], mean[m, 0]
        rows.append(
            {
                "re": re,
                "drag_base": drag_base.tolist(),
                "lift_base": forces[m, 1].tolist(),
                "unit_change": history[-1]["unit_change"][m],
                # the summed drag's change over the last 10 time units
                "drag_drift": float(sum(history[-1]["drag"][m]) - sum(history[-11]["drag"][m])),
                "drag_mean_uncontrolled": drag_free.tolist(),
                "lift_mean_uncontrolled": mean[m, 1].tolist(),
                "reduction": float(1.0 - drag_base.sum() / drag_free.sum()),
                "history": [
                    {"time": h["time"], "drag": h["drag"][m], "unit_change": h["unit_change"][m]} for h in history
                ],
            }
        )
    return {"cells_per_diameter": cells, "time": time, "sfd": [chi, SFD_DELTA], "levels": rows}


# Deng et al. 2020's thresholds
DENG = {"hopf": 18.0, "pitchfork": 68.0}


def threshold_table(rows: list[dict]) -> str:
    """The growth rates of each sweep and the thresholds against Deng et al.'s, as
    markdown."""
    lines = []
    for kind, name in (("hopf", "Hopf"), ("pitchfork", "pitchfork")):
        sweeps = sorted((r for r in rows if r["kind"] == kind), key=lambda r: r["cells_per_diameter"])
        if not sweeps:
            continue
        res = sorted({p["re"] for r in sweeps for p in r["points"]})
        label = f"{name} (damped)" if kind == "pitchfork" else name
        lines += [
            f"| {label}: growth rate at Re | " + " | ".join(f"{re:g}" for re in res) + " | threshold | Deng et al. |",
            "|---|" + "---|" * (len(res) + 2),
        ]
        for r in sweeps:
            rate = {p["re"]: p["rate"] for p in r["points"]}
            cells = [f"{rate[re]:+.4f}" if re in rate else "" for re in res]
            found = threshold(r["points"])
            where = f"{found:.1f} ({100 * (found / DENG[kind] - 1):+.1f} %)" if found == found else "none in the sweep"
            lines.append(
                f"| {r['cells_per_diameter']} cells per D | " + " | ".join(cells) + f" | {where} | {DENG[kind]:g} |"
            )
        lines.append("")
    return "\n".join(lines).strip()


def pitchfork_table(rows: list[dict]) -> str:
    """The developed flows' mean asymmetry over the sweep and the threshold against
    Deng et al.'s, as markdown (an asymmetry that has not settled marked *)."""
    res = sorted({p["re"] for r in rows for p in r["points"]})
    lines = [
        "| developed flow: mean summed C_L at Re | "
        + " | ".join(f"{re:g}" for re in res)
        + " | threshold | Deng et al. |",
        "|---|" + "---|" * (len(res) + 2),
    ]
    for r in sorted(rows, key=lambda r: r["cells_per_diameter"]):
        point = {p["re"]: p for p in r["points"]}
        cells = []
        for re in res:
            p = point.get(re)
            cells.append("" if p is None else f"{abs(p['asymmetry']):.4f}" + ("" if settled(p) else "*"))
        found = pitchfork_threshold(r["points"])
        where = f"{found:.1f} ({100 * (found / DENG['pitchfork'] - 1):+.1f} %)" if found == found else "none found"
        lines.append(
            f"| {r['cells_per_diameter']} cells per D | " + " | ".join(cells) + f" | {where} | {DENG['pitchfork']:g} |"
        )
    return "\n".join(lines)


LYAPUNOV_SIZE = 1e-8  # the twin's distance in the velocity's 2-norm, restored every time unit
REGIME_SAMPLE = 0.1


def regime(cells: int, re: float, time: float) -> dict:
    """The developed flow at ``re`` (the env's start: 400 time units from the free
    stream, the front cylinder kicked in the first) followed for ``time`` more units
    with a twin a tiny distance away: each cylinder's mean drag and lift, the front
    lift's spectrum and dominant frequency (the Strouhal number f D / U), and the
    leading Lyapunov exponent (the twin's distance restored every time unit, the mean
    of the logarithm of its growth)."""
    import numpy as np
    import torch

    from beacon_torch.envs.pinball.env import DEVELOP_TIME, KICK, developed_start
    from beacon_torch.envs.pinball.flow import DT, Box, Flow, coefficient, developed, run
    from beacon_torch.numerics.bodies import stable

    torch.set_num_threads(1)
    # the env's own time step and start where the env takes them (shipped, cached or
    # computed once), a smaller step's own development elsewhere
    if stable(1.0 / cells, 1.0 / re, DT):
        dt, start = DT, developed_start(cells, float(re))
    else:
        dt = time_step(cells, re)
        start, _ = developed(cells, 1.0 / re, time=DEVELOP_TIME, dt=dt, kick=KICK)
    box = Box(cells, dtype=torch.float64, device="cpu")
    # the twin: the front cylinder's rotation nudged for one step's worth of time
    pair = Flow(*(torch.stack((f, f)) for f in start))
    nudge = torch.tensor([[0.0, 0.0, 0.0], [1e-6, 0.0, 0.0]], dtype=torch.float64)
    still = torch.zeros(2, 3, dtype=torch.float64)
    per_sample, per_unit = int(round(REGIME_SAMPLE / dt)), int(round(1.0 / REGIME_SAMPLE))
    drag, lift, logs = [], [], []
    with torch.no_grad():
        pair, _ = run(pair, 1, nudge, box, 1.0 / re, dt)
        for k in range(int(round(time / REGIME_SAMPLE))):
            pair, loads = run(pair, per_sample, still, box, 1.0 / re, dt)
            drag.append(coefficient(loads[0, 0]).numpy())
            lift.append(coefficient(loads[0, 1]).numpy())
            if (k + 1) % per_unit == 0:
                gap = [f[1] - f[0] for f in pair]
                distance = float(torch.sqrt((gap[0] ** 2).sum() + (gap[1] ** 2).sum()))
                if k + 1 > per_unit:  # the first unit only aligns the twin
                    logs.append(float(np.log(distance / LYAPUNOV_SIZE)))
                scale = LYAPUNOV_SIZE / distance
                pair = Flow(*(torch.stack((f[0], f[0] + scale * g)) for f, g in zip(pair, gap, strict=True)))
    drag, lift = np.array(drag), np.array(lift)
    signal = lift[:, 0] - lift[:, 0].mean()
    power = np.abs(np.fft.rfft(signal * np.hanning(len(signal)))) ** 2
    frequency = np.fft.rfftfreq(len(signal), REGIME_SAMPLE)
    peak = int(np.argmax(power[1:])) + 1
    return {
        "cells_per_diameter": cells,
        "re": re,
        "dt": dt,
        "time": time,
        "drag_mean": drag.mean(0).tolist(),
        "lift_mean": lift.mean(0).tolist(),
        "lift_amplitude": (lift.max(0) - lift.min(0)).tolist(),
        "strouhal": float(frequency[peak]),
        "lyapunov": float(np.mean(logs)),
        "lyapunov_error": float(np.std(logs) / np.sqrt(len(logs))),
        "spectrum": {
            "frequency": frequency[: len(frequency) // 4].tolist(),
            "power": power[: len(power) // 4].tolist(),
        },
        "front_lift": lift[:, 0].tolist(),
    }


def regime_table(rows: list[dict]) -> str:
    """The developed flows' figures, as markdown."""
    lines = [
        "| Re | cells per D | mean C_D (front, top, bottom) | mean C_L (front, top, bottom) | St of the front lift "
        "| leading Lyapunov exponent |",
        "|---|---|---|---|---|---|",
    ]
    for r in sorted(rows, key=lambda r: (r["re"], r["cells_per_diameter"])):
        three = lambda v: ", ".join(f"{x:+.3f}" for x in v)
        lines.append(
            f"| {r['re']:g} | {r['cells_per_diameter']} | {three(r['drag_mean'])} | {three(r['lift_mean'])} | "
            f"{r['strouhal']:.4f} | {r['lyapunov']:+.4f} ± {r['lyapunov_error']:.4f} |"
        )
    return "\n".join(lines)


def base_table(rows: list[dict]) -> str:
    """Each level's steady symmetric flow beside its uncontrolled mean, as markdown."""
    lines = [
        "| Re | cells per D | base flow C_D (front, top, bottom) | sum | uncontrolled mean C_D | sum | reduction "
        "| base flow: sum's change over its last 10 units, largest change of u over the last unit |",
        "|---|---|---|---|---|---|---|---|",
    ]
    levels = [(r["cells_per_diameter"], level) for r in rows for level in r["levels"]]
    for cells, level in sorted(levels, key=lambda x: (x[1]["re"], x[0])):
        three = lambda v: ", ".join(f"{x:.4f}" for x in v)
        base, free = level["drag_base"], level["drag_mean_uncontrolled"]
        lines.append(
            f"| {level['re']:g} | {cells} | {three(base)} | {sum(base):.4f} | {three(free)} | {sum(free):.4f} "
            f"| {100 * level['reduction']:.1f} % | {level['drag_drift']:+.1e}, {level['unit_change']:.0e} |"
        )
    return "\n".join(lines)


def table(rows: list[dict]) -> str:
    """The rows against HydroGym's forces, as markdown."""
    ref_d, ref_l = HYDROGYM["drag"], HYDROGYM["lift"]
    lines = [
        "| set-up | cells per D | dt | C_D front | C_D top | C_D bottom | C_L top | C_L bottom |",
        "|---|---|---|---|---|---|---|---|",
        f"| HydroGym (fine mesh, Newton) | | | {ref_d[0]} | {ref_d[1]} | {ref_d[2]} | {ref_l[1]} | {ref_l[2]} |",
    ]
    order = {s: i for i, s in enumerate(SETUPS)}
    for r in sorted(rows, key=lambda r: (order[r["setup"]], r["cells_per_diameter"])):
        pct = lambda v, ref: f"{v:.4f} ({100 * (v / ref - 1):+.1f} %)"
        drag = [pct(v, ref) for v, ref in zip(r["drag"], ref_d, strict=True)]
        lift = [pct(v, ref) for v, ref in zip(r["lift"][1:], ref_l[1:], strict=True)]
        lines.append(f"| {r['setup']} | {r['cells_per_diameter']} | {r['dt']:g} | " + " | ".join(drag + lift) + " |")
    return "\n".join(lines)


def main() -> None:
    from beacon_torch import received
    from beacon_torch.files import save_rows
    from beacon_torch.training.report import write_block

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("what", choices=("steady", "thresholds", "pitchfork", "base", "regimes", "page"))
    parser.add_argument("--re", type=float, nargs="+", default=[30.0, 100.0, 130.0], help="regimes: Re of each run")
    parser.add_argument("--cells", type=int, nargs="+", default=[10, 20], help="cells across a diameter")
    parser.add_argument("--setups", nargs="+", default=list(SETUPS), choices=SETUPS)
    parser.add_argument("--time", type=float, default=None, help="time units of each run (steady: the most)")
    parser.add_argument("--hopf", type=float, nargs="*", default=[14.0, 17.0, 20.0, 23.0], help="Re of the sweep")
    parser.add_argument("--pitchfork", type=float, nargs="*", default=[56.0, 64.0, 72.0, 80.0], help="Re")
    parser.add_argument(
        "--developed", type=float, nargs="+", default=[60.0, 64.0, 68.0, 72.0, 76.0, 80.0, 84.0, 88.0], help="Re"
    )
    parser.add_argument("--chi", type=float, default=0.0, help="base: the damping's rate (0: none)")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--out", type=Path, default=RECORDS)
    parser.add_argument("--page", type=Path, default=ROOT / "docs" / "envs" / "pinball.md")
    args = parser.parse_args()
    if args.what == "steady":
        runs = [(s, c) for s in args.setups for c in args.cells]
        with concurrent.futures.ProcessPoolExecutor(min(args.workers, len(runs))) as pool:
            rows = list(pool.map(measure, *zip(*runs, strict=True), [args.time or 80.0] * len(runs)))
        print("results:", save_rows(rows, args.out, "pinball_steady"))
    elif args.what == "thresholds":
        runs = [
            (c, k, res) for c in args.cells for k, res in (("hopf", args.hopf), ("pitchfork", args.pitchfork)) if res
        ]
        with concurrent.futures.ProcessPoolExecutor(min(args.workers, len(runs))) as pool:
            rows = list(pool.map(sweep, *zip(*runs, strict=True), [args.time or 80.0] * len(runs)))
        print("results:", save_rows(rows, args.out, "pinball_thresholds"))
    elif args.what == "pitchfork":
        with concurrent.futures.ProcessPoolExecutor(min(args.workers, len(args.cells))) as pool:
            runs = [pool.submit(pitchfork, c, args.developed, args.time or 400.0) for c in args.cells]
            rows = [r.result() for r in runs]
        print("results:", save_rows(rows, args.out, "pinball_pitchfork"))
    elif args.what == "base":
        with concurrent.futures.ProcessPoolExecutor(min(args.workers, len(args.cells))) as pool:
            runs = [pool.submit(base_flows, c, args.re, args.time or 200.0, args.chi) for c in args.cells]
            rows = [r.result() for r in runs]
        print("results:", save_rows(rows, args.out, "pinball_base"))
    elif args.what == "regimes":
        runs = [(c, re) for c in args.cells for re in args.re]
        with concurrent.futures.ProcessPoolExecutor(min(args.workers, len(runs))) as pool:
            rows = list(pool.map(regime, *zip(*runs, strict=True), [args.time or 200.0] * len(runs)))
        print("results:", save_rows(rows, args.out, "pinball_regimes"))
    for name, begin, end, make in (
        ("pinball_steady", BEGIN, END, table),
        ("pinball_thresholds", THRESHOLDS_BEGIN, THRESHOLDS_END, threshold_table),
        ("pinball_pitchfork", PITCHFORK_BEGIN, PITCHFORK_END, pitchfork_table),
        ("pinball_base", BASE_BEGIN, BASE_END, base_table),
        ("pinball_regimes", REGIMES_BEGIN, REGIMES_END, regime_table),
    ):
        records = sorted(args.out.glob(f"{name}-*.json"))
        if records:
            rows = received.json_file(records[-1], "a pinball validation record")["rows"]
            print(make(rows))
            print(write_block(args.page, begin, end, make(rows)))


if __name__ == "__main__":
    main()
