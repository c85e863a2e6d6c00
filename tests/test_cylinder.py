"""The cylinder wake: its stretched-grid solver, the immersed cylinder and its jets, and
the validation figures against the recorded ones (the conformance kit runs on it with
every env, in test_conformance.py)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import beacon_torch
from beacon_torch.envs import cylinder
from beacon_torch.envs.cylinder import CARD, Channel, CylinderParams, jet_target, rest, run
from beacon_torch.numerics.grid import NEUMANN, ZERO_FACE
from beacon_torch.numerics.poisson import PoissonSolver, laplacian_1d

from conftest import random_policy_file

ROOT = Path(__file__).resolve().parents[1]
F64 = dict(dtype=torch.float64, device="cpu")


@pytest.fixture(scope="module")
def channel() -> Channel:
    return Channel(10, **F64)


def test_zero_face_condition_puts_zero_on_the_end_face():
    # phi = x - 1 on cells of [0, 1] vanishes on the face x = 1 and has unit slope: its
    # second difference is zero but for the Neumann end's row
    n, h = 8, 1.0 / 8
    x = (torch.arange(n, dtype=torch.float64) + 0.5) * h
    lap = laplacian_1d(n, h, NEUMANN, ZERO_FACE) @ (x - 1.0)
    assert torch.allclose(lap[1:], torch.zeros(n - 1, dtype=torch.float64), atol=1e-9)
    with pytest.raises(ValueError, match="zero_face"):
        laplacian_1d(n, h, NEUMANN, "open")


def test_stretched_solver_on_a_uniform_grid_is_the_uniform_one():
    nx, ny, h = 12, 10, 0.1
    widths = lambda n: torch.full((n,), h, dtype=torch.float64)
    lx, ly = laplacian_1d(nx, h, NEUMANN, NEUMANN), laplacian_1d(ny, h, NEUMANN, ZERO_FACE)
    uniform = PoissonSolver(nx, ny, h, h, (NEUMANN, NEUMANN, NEUMANN, ZERO_FACE), **F64)
    stretched = PoissonSolver.stretched(lx, widths(nx), ly, widths(ny), **F64)
    rhs = torch.randn(nx, ny, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    assert torch.allclose(stretched.solve(rhs), uniform.solve(rhs), atol=1e-12)


def test_channel_pressure_solve_inverts_its_operator(channel):
    rhs = torch.randn(channel.nx, channel.ny, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    phi = channel.solve(rhs)
    back = channel.solver.apply(phi.transpose(0, 1).contiguous()).transpose(0, 1)
    assert torch.allclose(back, rhs, atol=1e-9 * rhs.abs().max())
    # the gradient and divergence the steps use compose to that operator
    u = torch.cat((torch.zeros_like(phi[:1]), channel.x_gradient(phi)), 0)
    v = torch.nn.functional.pad(channel.y_gradient(phi), (0, 0, 1, 1))
    assert torch.allclose(channel.divergence(u, v), rhs, atol=1e-9 * rhs.abs().max())


def test_grid_is_uniform_around_the_cylinder_and_stretches_gently(channel):
    for axis in (channel.x, channel.y):
        ratio = axis.widths[1:] / axis.widths[:-1]
        assert ratio.max() < cylinder.GROWTH + 0.01 and ratio.min() > 1 / (cylinder.GROWTH + 0.01)
        fine = (axis.centres > 0.14) & (axis.centres < 0.26)
        assert torch.allclose(axis.widths[fine], torch.full_like(axis.widths[fine], channel.h))
    assert torch.isclose(channel.x.faces[-1], torch.tensor(cylinder.LENGTH, dtype=torch.float64))
    assert torch.isclose(channel.y.faces[-1], torch.tensor(cylinder.HEIGHT, dtype=torch.float64))
    # the default channel's y grid is mirror-symmetric, so the solve folds its products
    assert Channel(40, **F64).solver.x.folded


def test_steps_keep_the_flow_divergence_free_and_the_jets_carry_their_rate(channel):
    flow = rest(2, channel, torch.float64, "cpu")
    target = torch.tensor([0.0, cylinder.Q_MAX], dtype=torch.float64)
    with torch.no_grad():
        flow, drag, lift = run(flow, 40, target, channel, cylinder.NU)
    u, v = flow.u.movedim(0, -1), flow.v.movedim(0, -1)
    # every fluid cell conserves mass; the body's cells only each half of them together
    div = channel.divergence(u, v)
    assert (div * channel.fluid_cells).abs().max() < 1e-9
    area = (channel.dx_cells * channel.dy_cells)[..., None]
    assert (div[..., None] * channel.groups[:, :, None] * area).sum((0, 1)).abs().max() < 1e-14
    dy = channel.y.widths[:, None]
    inflow, outflow = (u[0] * dy).sum(0), (u[-1] * dy).sum(0)
    # zero net mass flux of the jets: what comes in goes out, with or without them
    assert torch.allclose(inflow, outflow, rtol=1e-10)
    assert abs(float(inflow[0]) - 4.0 * cylinder.U_MAX * cylinder.HEIGHT / 6.0) < 1e-3
    # the jets' stream carries exactly a unit flow rate across each row of v faces
    stream = channel.body_v.inside.reshape(channel.nx, channel.ny + 1)  # per unit rate
    rows = (stream * channel.x.widths[:, None]).sum(0)
    assert torch.allclose(rows[rows > 0], torch.ones_like(rows[rows > 0]), rtol=1e-12)
    # the jets' rate relaxes towards the target by a tenth a step
    assert flow.q[0] == 0.0 and math.isclose(float(flow.q[1]), cylinder.Q_MAX * (1 - 0.9**40), rel_tol=1e-12)
    assert torch.isfinite(drag).all() and torch.isfinite(lift).all()


def test_boundary_gives_the_first_fluid_faces_the_wall_distance_to_second_order():
    # the distance from the wall, r - R, vanishes on it and grows linearly along the
    # normal: the forcing must give each first fluid face its own distance, with the
    # error of the bilinear reads only (second order), and the faces inside the body 0
    errors = []
    for cells in (20, 40):
        channel = Channel(cells, **F64)
        boundary = channel.body_u
        x, y = channel.x.faces[:, None] - cylinder.CENTRE[0], channel.y.centres[None, :] - cylinder.CENTRE[1]
        distance = (torch.hypot(x, y) - cylinder.RADIUS)[..., None]
        forced = boundary(distance, torch.zeros(1, 1, **F64))
        first = boundary.targets
        errors.append(float((forced.reshape(-1)[first] - distance.reshape(-1)[first]).abs().max()))
        assert bool((distance.reshape(-1)[first] >= 0).all())
        inside = (distance < 0).reshape(-1)
        assert forced.reshape(-1)[inside].abs().max() == 0
        untouched = boundary.free[:, 0] == 1
        assert torch.equal(forced.reshape(-1)[untouched], distance.reshape(-1)[untouched])
    # halving the cells divides it by about 4 (a first-order wall, by 2)
    assert errors[1] < 0.005 * channel.h and errors[0] / errors[1] > 3


def test_boundary_gives_the_jets_their_velocity_at_the_wall(channel):
    # the jets' faces: with the flow at rest, the first fluid faces above the top jet
    # move outwards with it, those beside it not at all
    channel = Channel(40, **F64)
    boundary = channel.body_v
    at_rest = torch.zeros(channel.nx, channel.ny + 1, 1, **F64)
    forced = boundary(at_rest, torch.full((1, 1), 1e-2, **F64)).reshape(-1)
    first = boundary.targets
    x = channel.x.centres[first // (channel.ny + 1)] - cylinder.CENTRE[0]
    y = channel.y.faces[first % (channel.ny + 1)] - cylinder.CENTRE[1]
    on_jets = x.abs() < 0.5 * cylinder.RADIUS * cylinder.JET_WIDTH
    assert (forced[first][on_jets & (y > 0)] > 0).all() and (forced[first][on_jets & (y < 0)] > 0).all()
    assert forced[first][~on_jets].abs().max() < 1e-12
    # the wall velocity itself carries each jet's rate through its 10 degrees
    theta = np.linspace(0.0, 2.0 * math.pi, 200_001)
    normal = cylinder.wall_velocity(theta)
    top = (theta > 0.25 * math.pi) & (theta < 0.75 * math.pi)
    assert np.trapezoid(normal[top], theta[top]) * cylinder.RADIUS == pytest.approx(1.0, rel=1e-6)
    assert np.trapezoid(normal, theta) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.slow(seconds=40)
def test_steady_wake_at_re_20_has_the_benchmarks_drag():
    """The steady case 2D-1 of Schaefer and Turek (Re = 20; here nu = 5e-3 with the mean
    inflow of 1): the drag coefficient 5.5795 is approached at second order in the cell
    size (at 40 cells: 5.5819, recorded on the env's page)."""
    drag = {}
    for cells in (10, 20):
        _, history = cylinder.developed_shedding(cells, time=2.0, nu=5e-3, dt=2.5e-4)
        assert abs(history["drag"][-1] - history["drag"][-400]) < 1e-5  # steady
        drag[cells] = history["drag"][-1]
    reference = 5.5795
    assert abs(drag[20] / reference - 1) < 0.004
    assert (drag[10] - reference) / (drag[20] - reference) > 3.5


def test_actions_map_to_opposite_jets():
    a = torch.tensor([[1.0, -1.0], [0.3, 0.3], [-1.0, 1.0]])
    assert torch.allclose(jet_target(a), torch.tensor([1e-2, 0.0, -1e-2]))


def test_probes_are_the_published_layout(channel):
    assert cylinder.N_PROBES == 151
    # a linear pressure field is read exactly by the bilinear probes
    x, y = channel.x.centres[:, None], channel.y.centres[None, :]
    p = (2.0 * x - 3.0 * y)[None]
    points = cylinder.PROBES + np.array(cylinder.CENTRE)
    expected = torch.from_numpy(2.0 * points[:, 0] - 3.0 * points[:, 1])
    assert torch.allclose(channel.pressure_probes(p)[0], expected, atol=1e-12)


def recorded(cells: int, dt: float) -> dict:
    """The latest recorded validation row of a resolution and time step."""
    rows = []
    for path in sorted((ROOT / "validation" / "results" / "cylinder").glob("cylinder_validation-*.json")):
        rows += [r for r in json.loads(path.read_text())["rows"] if r["cells_per_diameter"] == cells and r["dt"] == dt]
    assert rows, f"no recorded validation of {cells} cells per diameter"
    return rows[-1]


def test_page_shows_the_recorded_validation_and_the_parameters():
    from beacon_torch.envs.cylinder import schaefer_turek as validation
    from beacon_torch.params import markdown

    paths = sorted((ROOT / "validation" / "results" / "cylinder").glob("cylinder_validation-*.json"))
    page = (ROOT / "docs" / "envs" / "cylinder.md").read_text()
    assert validation.table(json.loads(paths[-1].read_text())["rows"]) in page
    assert markdown(CylinderParams) in page
    assert (ROOT / "docs" / "img" / "cylinder-validation.png").exists()


def test_the_normalised_scores_one_is_the_recorded_base_flow_after_the_recorded_transient():
    """The card's reference is the newest record of validation/wake_reference.py,
    which the script computes again from the two records it names: the best policy's
    first actions (the transient, while the drag excess is above a tenth of the
    shedding's) and then the steady base flow's reward, which is below the 8 % at
    every action of Rabault et al. and above every recorded policy's score."""
    folder = ROOT / "validation" / "results" / "cylinder"
    record = json.loads(sorted(folder.glob("cylinder_reference-*.json"))[-1].read_text())["rows"][0]
    assert CARD.reference.score == record["reference"] and CARD.paper_ppo is None
    # the base flow is a validation's record, the policies' drags an experiment's
    rooms = [folder, ROOT / "experiments" / "results" / "cylinder"]
    inputs = [
        json.loads(next(r / name for r in rooms if (r / name).is_file()).read_text()) for name in record["records"]
    ]
    from validation import wake_reference

    again = wake_reference.reference(*inputs)
    assert again.pop("env") == "cylinder-v0" and again == {k: v for k, v in record.items() if k != "records"}
    assert 0 < record["transient_actions"] < cylinder.EPISODE_LENGTH
    held = cylinder.DRAG_OFFSET - cylinder.coefficient(torch.tensor(1.0)).item() ** -1 * record["cd_base"]
    assert record["held_reward_per_action"] == pytest.approx(held, rel=1e-12)
    rabault = cylinder.EPISODE_LENGTH * cylinder.PUBLISHED_REDUCTION * cylinder.DRAG_OFFSET
    assert max(p["score"] for p in record["policies"]) < record["reference"] < rabault


@pytest.mark.slow(seconds=30)
def test_validation_figures_of_the_default_grid_are_the_recorded_ones():
    """From the developed start of the default grid (the recorded run's last state),
    2.4 more shedding periods in float64 give the recorded figures."""
    record = recorded(CylinderParams().cells_per_diameter, cylinder.DT)
    physics, params = beacon_torch.functional("cylinder-v0", 1, dtype=torch.float64)
    channel, flow = physics.channel, cylinder.Flow(*(f[None] for f in physics._start(params)))
    zero = torch.zeros(1, dtype=torch.float64)
    steps = 1600
    drag, lift = np.empty(steps), np.empty(steps)
    with torch.no_grad():
        for k in range(steps):
            flow, fd, fl = run(flow, 1, zero, channel, cylinder.NU)
            drag[k], lift[k] = float(fd[0]), float(fl[0])
    time = cylinder.DT * np.arange(1, steps + 1)
    coefficient = lambda f: cylinder.coefficient(torch.from_numpy(f)).numpy()
    got = cylinder.shedding_figures(time, coefficient(drag), coefficient(lift), window=0.8)
    for key, tolerance in (("cd_max", 1e-3), ("cl_max", 2e-3), ("cd_mean", 1e-3), ("strouhal", 1e-2)):
        assert got[key] == pytest.approx(record[key], rel=tolerance), key


@pytest.mark.slow(seconds=40)
def test_control_benchmark_runs_a_policy_past_its_episode_beside_no_control(tmp_path):
    """experiments/wake_control.py: a policy file acts for two episodes' worth of
    actions on the grid it was trained on; the flow goes on across the episode's end,
    and the member without control is the uncontrolled flow itself."""
    from experiments import wake_control as control

    params = {"cells_per_diameter": 10}
    policy = random_policy_file(tmp_path / "policy.pt", "cylinder-v0", params)
    row = control.control(str(policy), 2, compile=False)
    assert row["params"] == params and row["env"] == "cylinder-v0" and len(row["per_action"]["drag"]) == 160
    # the rewards are the env's, Rabault et al.'s drag and lift penalty
    drag, lift = (np.array(row["per_action"][key]) for key in ("drag", "lift"))
    force = cylinder.U_MEAN**2 * cylinder.DIAMETER / 2.0
    expected = cylinder.DRAG_OFFSET - force * drag - cylinder.LIFT_PENALTY * force * np.abs(lift)
    np.testing.assert_allclose(row["per_action"]["reward"], expected, rtol=1e-5, atol=1e-5)

    # a separate env of the run's shape, both members uncontrolled: the run's second
    # member does the same arithmetic in the same batched operations, so it agrees to
    # the last bit on any processor (an env of one member would agree to float32's
    # rounding only, which 160 actions of shedding grow)
    free = beacon_torch.make("cylinder-v0", 2, cells_per_diameter=10)
    free.reset()
    drag = []
    for _ in range(2):
        for _ in range(free.episode_length):
            free.step_members(free.null_action())
            drag.append(float(cylinder.coefficient(free.state.drag)[1]))
        free.set_state(free.state, 0)
    assert row["per_action"]["uncontrolled_drag"] == drag
    jets = np.array(row["per_action"]["jet"])
    assert np.abs(jets).max() <= 1.0 and np.abs(jets).max() > 0.05
    # the reductions are against the run's own uncontrolled member (which matches the
    # separate env above to float32 rounding only, and a reduction is one minus a ratio
    # of drags near each other, so that rounding grows a hundredfold in it)
    first, last = np.array(row["per_action"]["drag"][:80]), np.array(row["per_action"]["drag"][80:])
    free_first, free_last = (
        np.array(row["per_action"]["uncontrolled_drag"][part]) for part in (slice(80), slice(80, 160))
    )
    assert row["reduction_episode"] == pytest.approx(1 - first.mean() / free_first.mean(), rel=1e-9)
    assert row["reduction_second_half"] == pytest.approx(1 - last.mean() / free_last.mean(), rel=1e-9)


@pytest.mark.parametrize("planted", ["file", "link"])
def test_the_control_and_learning_figures_never_replace_a_file(tmp_path, planted, monkeypatch):
    """experiments/wake_control.py --plot and experiments/learning.py
    --figure refuse a figure's name that is taken, by a file or a link (dangling
    included), before any work, and leave it as it was."""
    from experiments import learning
    from experiments import wake_control as control

    figure, target = tmp_path / "figure.png", tmp_path / "elsewhere.png"
    if planted == "file":
        figure.write_bytes(b"mine")
    else:
        figure.symlink_to(target)  # dangling: nothing may be created through it
    record = tmp_path / "record.json"
    record.write_text(json.dumps({"rows": [{"policy": "p", "per_action": {"drag": [3.0]}}]}))
    with pytest.raises(FileExistsError, match="figure.png exists"):
        control.plot(str(record), str(figure))
    monkeypatch.setattr("sys.argv", ["learning.py", str(tmp_path / "no-run"), "--figure", str(figure)])
    with pytest.raises(FileExistsError, match="figure.png exists"):
        learning.main()
    if planted == "file":
        assert figure.read_bytes() == b"mine"
    else:
        assert figure.is_symlink() and not target.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["figure.png", "record.json"])


def test_the_learning_comparison_refuses_runs_of_different_envs(tmp_path, monkeypatch):
    """experiments/learning.py compares runs on one env: runs trained on different envs
    or parameters get one line naming both, before any episode is stepped."""
    from experiments import learning

    trained = {"a": ("cylinder-v0", {}), "b": ("pinball-v0", {"re": 100.0})}
    monkeypatch.setattr(learning, "curve", lambda run: {"env": trained[run.name][0], "params": trained[run.name][1]})
    monkeypatch.setattr("sys.argv", ["learning.py", "a", "b", "--figure", str(tmp_path / "f.png")])
    with pytest.raises(SystemExit, match="different envs or parameters.*cylinder-v0.*pinball-v0"):
        learning.main()
    assert list(tmp_path.iterdir()) == []


def test_the_learning_comparison_carries_an_earlier_records_curves(tmp_path, monkeypatch, capsys):
    """experiments/learning.py --carry: an earlier record's curves go ahead of the new
    run's, set the levels, and are kept in the new record naming where they came from;
    a record whose curves are not series of finite numbers is one line, before any
    episode is stepped."""
    import beacon_torch.episodes
    from experiments import learning

    def curve(algo, scores):
        n = len(scores)
        return {"algo": algo, "env": "cylinder-v0", "params": {}, "seeds": 1, "transitions": list(range(n)),
                "minutes": [0.5 * k for k in range(n)], "score": scores, "spread": [0.0] * n}  # fmt: skip

    earlier = tmp_path / "earlier.json"
    earlier.write_text(json.dumps({"rows": [{"levels": []}, curve("ppo", [-10.0, -6.0, -2.0])]}))
    monkeypatch.setattr(learning, "curve", lambda run: curve("shac", [-10.0, -4.0, -3.0]))
    monkeypatch.setattr(beacon_torch.episodes, "episode", lambda env, policy: None)
    monkeypatch.setattr(beacon_torch.episodes, "scores", lambda rollout: torch.tensor([-10.0]))
    figure, out = tmp_path / "f.png", tmp_path / "out"
    argv = ["learning.py", "new", "--carry", str(earlier), "--figure", str(figure), "--out", str(out)]
    monkeypatch.setattr("sys.argv", argv)
    learning.main()
    (record,) = out.glob("cylinder_learning-*.json")
    levels, ppo, shac = json.loads(record.read_text())["rows"]
    assert (ppo["algo"], ppo["record"], shac["algo"]) == ("ppo", "earlier.json", "shac") and "record" not in shac
    # halfway from no control (-10) to the carried curve's final score (-2): -6
    half = {row["algo"]: row["transitions"] for row in levels["levels"] if row["fraction"] == 0.5}
    assert half == {"ppo": 1, "shac": 1} and figure.is_file()
    capsys.readouterr()
    bad = curve("ppo", [-10.0, float("nan")])
    for rows, message in (
        ([{"levels": []}, bad], "curve 0: its transitions, minutes, score, spread are not series of finite numbers"),
        ([{"levels": []}, {**bad, "env": 3}], "curve 0 names no algorithm and env"),
        ([], "not a record of experiments/learning.py"),
    ):
        earlier.write_text(json.dumps({"rows": rows}))
        argv = ["learning.py", "new", "--carry", str(earlier), "--figure", str(tmp_path / "g.png")]
        monkeypatch.setattr("sys.argv", argv)
        with pytest.raises(SystemExit):
            learning.main()
        assert message in capsys.readouterr().err
    assert not (tmp_path / "g.png").exists()
