"""The steady base flow of cylinder-v0: the drag left when the shedding is gone.

    .venv/bin/python -m beacon_torch.envs.cylinder.base_flow [--time 12] [--chi 5] [--delta 0.1] [--out DIR]

Above Re of about 47 the steady flow past the cylinder is unstable and the wake sheds;
suppressing the shedding brings the flow towards that steady state, whose drag is what
a controller that only stabilises the wake can reach. Selective frequency damping
(Akervik et al., Phys. Fluids 18, 2006) finds it: from the developed shedding at the
default grid (float64), after every step the flow is pulled towards its own low-pass
filtered self, ``u <- u - dt chi (u - ubar)`` and ``ubar <- ubar + dt (u - ubar) /
delta`` (a cut-off well below the shedding's 3 periods per time unit); both are
divergence-free, and at convergence ``u = ubar`` is a steady solution of the
unforced equations. Prints the drag and lift coefficients and the largest
``|u - ubar|`` once per time unit, and writes them with the converged coefficients
against the uncontrolled flow's mean drag to a new dated ``cylinder_base_flow-DATE-TIME.json``.
"""

from __future__ import annotations

import argparse


def main() -> None:
    import numpy as np
    import torch

    from beacon_torch.envs import cylinder
    from beacon_torch.files import save_rows
    from beacon_torch.numerics import frequency_damping
    from beacon_torch.params import resolve_params

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--time", type=float, default=12.0, help="time units of damping")
    parser.add_argument("--chi", type=float, default=5.0, help="the damping's rate")
    parser.add_argument("--delta", type=float, default=0.1, help="the filter's width in time")
    parser.add_argument("--out", default="runs/cylinder_base_flow")
    args = parser.parse_args()
    torch.set_num_threads(1)
    f64, cpu = torch.float64, torch.device("cpu")
    params = resolve_params(cylinder.CylinderParams, {}, batch_size=1, device=cpu, dtype=f64, env_id="cylinder-v0")
    physics = cylinder.CylinderPhysics(params, 1, dtype=f64)
    channel, dt = physics.channel, cylinder.DT
    flow = cylinder.Flow(*(f[None] for f in physics._start(params)))
    mean, steps = [], int(round(1.0 / dt))
    zero = torch.zeros(1, dtype=torch.float64)
    with torch.no_grad():
        # the uncontrolled flow's mean drag over one time unit (three periods) first
        free = flow
        for _ in range(steps):
            free, drag, _ = cylinder.run(free, 1, zero, channel, cylinder.NU)
            mean.append(float(cylinder.coefficient(drag)[0]))
        filtered = flow.u.clone(), flow.v.clone()
        history = []
        for k in range(1, int(round(args.time / dt)) + 1):
            flow, drag, lift = cylinder.run(flow, 1, zero, channel, cylinder.NU)
            report = k % steps == 0
            if report:
                change = max(float((q - bar).abs().max()) for q, bar in zip((flow.u, flow.v), filtered, strict=True))
            (u, v), filtered = frequency_damping((flow.u, flow.v), filtered, dt, args.chi, args.delta)
            flow = flow._replace(u=u, v=v)
            if report:
                row = {
                    "time": k * dt,
                    "cd": float(cylinder.coefficient(drag)[0]),
                    "cl": float(cylinder.coefficient(lift)[0]),
                    "change": change,
                }
                history.append(row)
                print(
                    f"t = {row['time']:.0f}: C_D {row['cd']:.4f}, C_L {row['cl']:+.4f}, |u - ubar| {row['change']:.1e}"
                )
    last = history[-1]
    result = {
        "cells_per_diameter": int(params.cells_per_diameter),
        "chi": args.chi,
        "delta": args.delta,
        "cd_base": last["cd"],
        "cl_base": last["cl"],
        "converged_to": last["change"],
        "cd_mean_uncontrolled": float(np.mean(mean)),
        "reduction": 1.0 - last["cd"] / float(np.mean(mean)),
        "history": history,
    }
    print(
        f"base flow: C_D {result['cd_base']:.4f}, {100 * result['reduction']:.2f} % below the shedding's mean "
        f"{result['cd_mean_uncontrolled']:.4f}"
    )
    print("results:", save_rows([result], args.out, "cylinder_base_flow"))


if __name__ == "__main__":
    main()
