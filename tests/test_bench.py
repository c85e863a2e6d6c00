"""``beacon-torch bench``: the throughput measurement and its outputs."""

import csv
import json

import pytest

from beacon_torch import bench, files
from beacon_torch.cli import main


def test_measure_reports_rates_against_the_published_speed():
    m = bench.measure("lorenz-v0", 4, steps=3, repeats=2)
    assert m.transitions_per_s > 0 and m.step_ms > 0
    assert m.published_per_s == 62_300.0
    assert m.speedup == pytest.approx(m.transitions_per_s / 62_300.0)
    assert m.mode == "eager" and m.dtype == "float32" and m.batch == 4
    # variants without a published number of their own use their base env's
    assert bench.measure("mixing-continuous-v0", 1, steps=1, repeats=1).published_per_s == 3.7


def test_warm_up_steps_until_nothing_compiles():
    """Compilation is never timed as speed: a step that compiles on its first three calls
    (three shapes) is warmed up four times, and the fourth call compiled nothing."""
    import torch

    f = torch.compile(lambda x: x * 2 + 1, dynamic=False)
    sizes = iter([3, 4, 5] + [5] * 20)
    calls = []

    def step():
        calls.append(f(torch.ones(next(sizes))))

    assert bench.warm_up(step) == 4 and len(calls) == 4
    assert bench.warm_up(lambda: None) == 1


@pytest.mark.slow(20)
def test_compiled_measurement_is_not_compile_time():
    """A short compiled measurement (5 steps, 2 repeats) in a fresh process times
    compiled steps: the warm-up took the compiling steps, no graph is compiled while
    timing, and the compile time is reported apart."""
    m = bench.measure_in_fresh_process("lorenz-v0", 1, mode="compiled", steps=5, repeats=2)
    assert m.recompiles == 0 and m.warm_up_steps >= 2
    assert m.compile_s > 20 * m.step_ms / 1e3  # compiling takes far longer than a step
    assert m.peak_mb > 0
    # in a shared process no peak is reported: it would be another configuration's
    assert bench.measure("lorenz-v0", 1, steps=2, repeats=1).peak_mb is None


@pytest.mark.slow(15)
def test_each_configuration_reports_its_own_peak_memory():
    """Each configuration runs in a fresh process: a small one measured after a large
    one reports its own peak, not the process's running maximum."""
    large, small = bench.run(
        ["lorenz-v0"], num_envs=[2**20, 1], modes=["eager"], steps=1, repeats=1, echo=lambda line: None
    )
    assert large.peak_mb - large.base_mb > 200  # a million members' states and intermediates
    assert small.peak_mb < large.peak_mb - 200
    assert small.recompiles == 0


def test_measure_rejects_bad_arguments():
    with pytest.raises(ValueError, match="mode"):
        bench.measure("lorenz-v0", 1, mode="fast")
    with pytest.raises(ValueError, match="repeats"):
        bench.measure("lorenz-v0", 1, repeats=0)


def test_bench_command_writes_table_csv_json_and_plot(tmp_path, capsys):
    rc = main(
        [
            "bench",
            "--envs",
            "lorenz-v0",
            "vortex-v0",
            "--num-envs",
            "1",
            "--mode",
            "eager",
            "--steps",
            "2",
            "--repeats",
            "2",
            "--out",
            str(tmp_path),
        ]
    )
    assert rc == 0
    out = capsys.readouterr().out
    assert "transitions/s" in out and "| lorenz-v0 |" in out
    rows = list(csv.DictReader((tmp_path / "results.csv").open()))
    assert {(r["env"], int(r["batch"])) for r in rows} == {(e, b) for e in ("lorenz-v0", "vortex-v0") for b in (1,)}
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["machine"] and len(data["results"]) == 2
    assert (tmp_path / "throughput.png").stat().st_size > 10_000
    md = (tmp_path / "results.md").read_text()
    assert "## Best speed per env" in md and md.count("| lorenz-v0 |") == 2  # best + its row
    again = bench.load(tmp_path / "results.json")
    assert [m.transitions_per_s for m in again] == [float(r["transitions_per_s"]) for r in rows]
    assert all(m.peak_mb > 0 for m in again)  # each measured in its own process


def test_bench_replaces_no_earlier_results(tmp_path, capsys):
    """An output directory with results is refused before anything is measured; the
    default is a new dated directory; a benchmark script's record gets a new dated name."""
    (tmp_path / "results.csv").write_text("mine")
    assert main(["bench", "--envs", "lorenz-v0", "--num-envs", "1", "--out", str(tmp_path)]) == 2
    assert "results.csv exists" in capsys.readouterr().err
    assert (tmp_path / "results.csv").read_text() == "mine"
    first = files.save_rows([{"a": 1}], tmp_path, "single_env")
    (tmp_path / "single_env.json").write_text("mine")
    assert first.name.startswith("single_env-") and first.read_text().count('"a"') == 1
    assert (tmp_path / "single_env.json").read_text() == "mine"


def test_bench_command_reports_bad_input(capsys):
    assert main(["bench", "--envs", "nope-v0"]) == 2
    assert "nope-v0" in capsys.readouterr().err
    assert main(["bench", "--envs", "lorenz-v0", "--num-envs", "0"]) == 2
    assert "--num-envs" in capsys.readouterr().err


def test_a_tree_is_named_by_its_commit_and_whether_it_was_changed(tmp_path):
    import subprocess

    from beacon_torch.files import revision

    assert revision(tmp_path) is None
    git = ["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q"], check=True)
    (tmp_path / "a.py").write_text("x = 1\n")
    subprocess.run([*git, "add", "a.py"], check=True)
    subprocess.run([*git, "commit", "-qm", "a"], check=True)
    head = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
    (tmp_path / "untracked.txt").write_text("not the tree's")
    assert revision(tmp_path) == head
    (tmp_path / "a.py").write_text("x = 2\n")
    assert revision(tmp_path) == head + "+changes"


@pytest.mark.slow(60)
def test_two_trees_compared_step_by_step_name_what_differs(tmp_path):
    """validation/same_steps.py: a tree against itself steps alike, bit for bit; against
    a copy whose lorenz starts elsewhere, every case of lorenz differs from its first
    observation, and the record says which (and at how many members it compared)."""
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    other = tmp_path / "other"
    shutil.copytree(root / "beacon_torch", other / "beacon_torch", ignore=shutil.ignore_patterns("pretrained"))
    lorenz = other / "beacon_torch" / "envs" / "lorenz.py"
    lorenz.write_text(lorenz.read_text().replace("START = (10.0, 10.0, 10.0)", "START = (10.0, 10.0, 10.5)"))
    command = [sys.executable, str(root / "validation" / "same_steps.py")]
    for trees, name in (([root, root], "same"), ([root, other], "other")):
        out = subprocess.run(
            [
                *command,
                *map(str, trees),
                "--envs",
                "lorenz-v0",
                "--members",
                "3",
                "--out",
                str(tmp_path / f"{name}.json"),
            ],
            capture_output=True,
            text=True,
            check=False,
            cwd=tmp_path,
            timeout=600,
        )
        assert out.returncode == 0, out.stderr[-2000:]
    same, other = (json.loads((tmp_path / f"{name}.json").read_text()) for name in ("same", "other"))
    assert same["cases"] == other["cases"] == 4 and same["tensors"] > 20 and same["differ"] == []
    assert same["members"] == other["members"] == 3
    assert "lorenz-v0 eager float64: observation 0" in other["differ"]
    # the copy is no git checkout: its commit is not known
    assert same["commits"][0] == same["commits"][1] and other["commits"][1] is None
    assert {line.split(":")[0] for line in other["differ"]} == {
        f"lorenz-v0 {mode} {dtype}" for mode in ("eager", "compiled") for dtype in ("float32", "float64")
    }


def test_the_c_kernels_are_timed_per_tree_and_compared_bit_for_bit(tmp_path):
    """benchmarks/c_kernels.py: each tree's kernel source built and called on the same
    inputs; a tree against itself gives the same results in every case, and a new
    record names the trees and the times."""
    import subprocess
    import sys
    from pathlib import Path

    import torch

    from beacon_torch.numerics import native

    if not native.applies("cpu", torch.float64):
        pytest.skip("no C compiler")
    root = Path(__file__).resolve().parents[1]
    command = [sys.executable, str(root / "benchmarks" / "c_kernels.py"), str(root), str(root), "--calls", "1"]
    command += ["--repeats", "1", "--out", str(tmp_path)]
    out = subprocess.run(command, capture_output=True, text=True, check=False, cwd=tmp_path, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    (record,) = [json.loads(p.read_text()) for p in tmp_path.glob("c-kernels-*.json")]
    kernels = {row["kernel"] for row in record["rows"]}
    assert kernels == {"sweep", "sweep_adjoint", "lines", "momentum_adjoint"} and len(record["trees"]) == 2
    assert all(row["equal"] and len(row["us"]) == 2 and min(row["us"]) > 0 for row in record["rows"])


@pytest.mark.slow(20)
def test_two_trees_timed_block_by_block_give_a_ratio_per_case(tmp_path):
    """benchmarks/revisions.py --interleaved: the two processes' blocks of each case
    alternate, the same steps each; the record keeps every round's blocks and the
    median ratio of adjacent blocks."""
    import statistics
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    command = [sys.executable, str(root / "benchmarks" / "revisions.py"), str(root), str(root), "--interleaved"]
    command += ["--envs", "lorenz-v0", "vortex-v0", "--batches", "1", "2", "--modes", "eager", "--rounds", "2"]
    command += ["--seconds", "0.01", "--blocks", "3", "--out", str(tmp_path)]
    out = subprocess.run(command, capture_output=True, text=True, check=False, cwd=tmp_path, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    (record,) = tmp_path.glob("revisions-*.json")
    rows = json.loads(record.read_text())["rows"]
    assert [(r["env"], r["batch"]) for r in rows] == [
        ("lorenz-v0", 1),
        ("lorenz-v0", 2),
        ("vortex-v0", 1),
        ("vortex-v0", 2),
    ]
    for row in rows:
        assert row["interleaved"] and all(len(side) == 2 for side in row["blocks"].values())
        assert all(len(blocks) == 3 for side in row["blocks"].values() for blocks in side)
        before, after = (sum(row["blocks"][side], []) for side in ("before", "after"))
        pairs = [a / b for b, a in zip(before, after, strict=True)]
        assert row["ratio"] == pytest.approx(statistics.median(pairs)) and row["ratio"] > 0


def test_the_gradient_norm_is_recorded_per_horizon(tmp_path):
    """experiments/gradient_horizons.py: a row per horizon (its norm, finite, blow-ups,
    CPU time) and the figure beside the record; lorenz's default reward counts sign
    changes and gives no gradient, its smooth one does."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    command = [sys.executable, str(root / "experiments" / "gradient_horizons.py"), "--envs", "lorenz-continuous-v0"]
    command += ["--members", "2", "--horizons", "1", "8", "--out", str(tmp_path)]
    for params in ([], ["--param", "reward_width=1.0"]):
        out = subprocess.run(command + params, capture_output=True, text=True, check=False, timeout=600)
        assert out.returncode == 0, out.stderr[-2000:]
    records = sorted(tmp_path.glob("gradient-horizons-*.json"))
    assert len(records) == 2 and all(r.with_suffix(".png").is_file() for r in records)
    plain, smooth = sorted(
        (json.loads(r.read_text())["rows"] for r in records), key=lambda rows: len(rows[0]["params"])
    )
    assert [r["horizon"] for r in smooth] == [1, 8] and all(r["finite"] and r["blown_up"] == 0 for r in smooth)
    assert all(r["norm"] == 0 for r in plain) and all(r["norm"] > 0 for r in smooth)


def test_every_horizon_of_a_record_starts_from_the_same_states_as_a_fresh_env():
    """The env and policy are built once per env and every horizon restarts from their
    saved starts: a horizon measured after others equals one measured first on an env
    built anew, on a stochastic env (burgers' inflow noise) with its generator."""
    from experiments import gradient_horizons as horizons

    shared = horizons.Start("burgers-v0", 2, seed=3)
    after = [shared.norm(h)["norm"] for h in (2, 5, 5)]
    fresh = horizons.Start("burgers-v0", 2, seed=3).norm(5)["norm"]
    assert after[1] == after[2] == fresh and after[0] != fresh
    assert horizons.Start("burgers-v0", 2, seed=4).norm(5)["norm"] != fresh


def test_a_time_budget_leaves_out_the_longer_horizons_and_says_which(capsys):
    """With a budget, a horizon whose time predicted from the last measured one would
    overrun it is not started, nor any longer one, and the record keeps what was measured."""
    from experiments import gradient_horizons as horizons

    started = []

    def measure(h):
        started.append(h)
        return dict(horizon=h, norm=1.0, blown_up=0, cpu_s=float(h), wall_s=float(h))

    rows = horizons.horizons_within("x", [8, 1, 2, 4, 16], measure, budget_s=10.0)
    # 1 + 2 + 4 = 7 s spent; 8 more predicted from the 4's 4 s would make 15
    assert started == [1, 2, 4] and [r["horizon"] for r in rows] == [1, 2, 4]
    assert "horizons [8, 16] left out" in capsys.readouterr().out
    started.clear()
    assert len(horizons.horizons_within("x", [1, 2, 4, 8, 16], measure, budget_s=None)) == 5


def test_the_knee_of_the_gradient_norm_sets_the_horizons_the_recipes_differentiate():
    """The knee is the last horizon before a doubling multiplies the norm tenfold past
    what shorter horizons gave (a late start-up below 8 actions aside); the default
    horizon is the knee's power of two, at most 32. On the recorded envs, the page shows
    the newest records and the actor-critic never differentiates past the knee."""
    from pathlib import Path

    from experiments import gradient_horizons as horizons

    rows = lambda norms: [
        dict(env="x", horizon=h, norm=n, finite=n == n and n != float("inf"), members=8) for h, n in norms.items()
    ]
    assert horizons.knee(rows({1: 1e-7, 4: 1e-7, 8: 1e-2, 16: 2e-2, 32: 0.1, 64: 5.0})) == 32
    assert horizons.knee(rows({1: 1.0, 8: 2.0, 16: 1.0, 32: 3.0})) is None
    assert horizons.knee(rows({8: 1.0, 16: float("inf")})) == 8
    assert horizons.default_horizon(rows({1: 1.0, 8: 2.0, 16: 1.0, 200: 3.0})) == 32
    assert horizons.default_horizon(rows({1: 1.0, 8: 1.0, 16: 1.0, 24: 100.0})) == 16

    root = Path(__file__).resolve().parents[1]
    records = horizons.newest(root / "experiments" / "results" / "gradient_horizons")
    assert {"lorenz-continuous-v0", "burgers-v0", "shkadov-v0"} <= set(records)
    page = (root / "docs" / "gradients.md").read_text()
    assert horizons.page_table(records) in page
    from beacon_torch.training.config import SHACConfig, configure

    assert {"rayleigh-v0", "mixing-continuous-v0", "cylinder-v0"} <= set(records)
    for env_id, measured in records.items():
        if horizons.reaches_episode(measured):
            assert configure(SHACConfig, env_id).horizon <= horizons.default_horizon(measured), env_id
        else:  # cut short by its time budget: no bound on the horizons it left out, and the table says so
            assert f"| {env_id} | 1 to {max(r['horizon'] for r in measured)} (time budget) |" in page
    short = rows({1: 1.0, 2: 1.0, 4: 1.0})
    for row in short:
        row["env"] = "burgers-v0"
    assert not horizons.reaches_episode(short) and horizons.reaches_episode(short + [dict(short[0], horizon=200)])


def test_the_performance_page_shows_the_recorded_cost_of_differentiated_transitions():
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    from benchmarks import grad_cost as cost

    table = cost.page_table(root / "benchmarks" / "results" / "grad_cost")
    assert "| burgers-v0 | 64 |" in table and "| shkadov-v0 | 16 |" in table
    assert table in (root / "docs" / "measurements.md").read_text()
    from benchmarks import grad_profile

    profiles = grad_profile.page_table(root / "benchmarks" / "results" / "grad_profile")
    assert "| burgers-v0 | 64 |" in profiles and "backward graphs" in profiles
    assert profiles in (root / "docs" / "measurements.md").read_text()


def test_a_differentiated_transition_is_split_by_piece(tmp_path):
    """benchmarks/grad_profile.py on lorenz: eagerly, the integrator's forward and
    backward shares are told apart (a backward operator goes to the piece of the forward
    one it differentiates), the rest is autograd's and Python's; compiled, the graphs and
    their wrappers, every split summing to the block's time; and the generated kernels of
    both passes."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    command = [sys.executable, str(root / "benchmarks" / "grad_profile.py"), "--envs", "lorenz-continuous-v0"]
    for ways, out in ((["eager", "compiled"], tmp_path / "pieces"), (["kernels"], tmp_path / "kernels")):
        done = subprocess.run(
            command + ["--ways", *ways, "--out", str(out)], capture_output=True, text=True, timeout=600
        )
        assert done.returncode == 0, done.stderr[-2000:]
    (record,) = (tmp_path / "pieces").glob("grad-profile-lorenz-continuous-v0-*.json")
    eager, compiled = json.loads(record.read_text())["rows"]
    (record,) = (tmp_path / "kernels").glob("grad-profile-lorenz-continuous-v0-*.json")
    (kernels,) = json.loads(record.read_text())["rows"]
    assert (eager["way"], compiled["way"], kernels["way"]) == ("eager", "compiled", "kernels")
    assert {"envs.lorenz.lorenz_rhs/forward", "envs.lorenz.lorenz_rhs/backward", "autograd"} <= set(eager["split"])
    assert {"forward graphs", "backward graphs", "wrappers"} <= set(compiled["split"])
    for row in (eager, compiled):
        assert sum(row["split"].values()) == pytest.approx(row["seconds_per_action"], rel=1e-6)
    # the generated kernels of both passes, each with its time and calls an action
    sides = {name.split(":")[0] for name in kernels["split"]}
    assert sides == {"forward", "backward"}, kernels["split"]
    assert all(v["seconds"] > 0 and v["calls"] > 0 for v in kernels["split"].values())
    assert sum(v["seconds"] for v in kernels["split"].values()) < kernels["seconds_per_action"]


def test_the_cost_of_a_differentiated_transition_is_measured_beside_the_forward_one(tmp_path):
    """benchmarks/grad_cost.py on lorenz: a record per env, the forward's time and the
    differentiated one's ratio to it, per round, with the kernel's time and the page
    faults of each way and the free heap it kept."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    command = [sys.executable, str(root / "benchmarks" / "grad_cost.py"), "--envs", "lorenz-continuous-v0"]
    command += ["--rounds", "2", "--horizon", "2", "--kinds", "forward", "eager", "--out", str(tmp_path)]
    command += ["--keep-free", "12345"]
    out = subprocess.run(command, capture_output=True, text=True, check=False, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    (record,) = tmp_path.glob("grad-cost-lorenz-continuous-v0-*.json")
    (row,) = json.loads(record.read_text())["rows"]
    # at the actor-critic's batch
    from beacon_torch.training.config import SHACConfig, configure

    assert row["members"] == configure(SHACConfig, "lorenz-continuous-v0").num_envs == 16
    assert len(row["rounds"]["eager"]) == 2
    assert row["forward_s"] > 0 and row["eager_ratio"] > 1
    assert len(row["system_s"]["eager"]) == len(row["page_faults"]["forward"]) == 2
    assert all(0 <= s <= t for s, t in zip(row["system_s"]["eager"], row["rounds"]["eager"], strict=True))
    assert row["keep_free"] == 12345
    # each way in a process of its own, as a collector's forward steps run
    assert row["apart"] is True


def test_the_kept_way_differentiates_without_recomputing_the_actions():
    """grad_cost's ``kept`` way: the env the actor-critic recomputes (mixing) compiled
    and differentiable with each action's graph kept whole; its ``compiled`` way
    recomputes, as the recipe does."""
    from benchmarks import grad_cost as cost

    kept = cost.Way("mixing-continuous-v0", 2, "kept", True, 1)
    recomputed = cost.Way("mixing-continuous-v0", 2, "compiled", True, 1)
    assert kept.env.differentiable and not kept.env.grad_checkpoint
    assert recomputed.env.grad_checkpoint


def test_the_comparison_reads_when_each_pair_reached_the_paper_score_from_its_curves():
    """experiments/comparison.py: with its seeds' curves, a pair reached normalised 1.0
    where the mean of its last points first does (transitions and minutes there); without
    them (published before curves were kept), within its budget if its final score is 1
    or more; the gradients page shows the table of the recorded pairs."""
    from pathlib import Path

    from experiments import comparison

    # burgers: 0 at -3.378 (no control), 1 at the paper's -1.75
    frames = list(range(0, 10_000, 100))
    rising = [-3.378 + 1.628 * min(1.0, f / 5000) * 1.05 for f in frames]
    curve = {"frames": frames, "score": rising, "wall_s": [f / 100 for f in frames]}
    summary = {
        "algo": "shac",
        "env": "burgers-v0",
        "frames": 10_000,
        "wall_s_per_seed": 100.0,
        "uncontrolled": -3.378,
        "seeds": [{"seed": "seed0", "eval": -1.7, "curve": curve}, {"seed": "seed1", "eval": -1.6, "curve": curve}],
    }
    reached, minutes = comparison.to_one(summary)
    at = int(reached.replace(",", ""))
    # 1.05 x the way from no control to the paper's score at 5,000: 1.0 at 4,762, and
    # the window of 5 grid points (about 100 transitions each) reaches it a little later
    assert 4_762 <= at <= 5_300 and float(minutes) == pytest.approx(at / 100 / 60, abs=0.05)  # one decimal
    flat = dict(summary, seeds=[dict(s, curve=dict(curve, score=[-3.0] * len(frames))) for s in summary["seeds"]])
    assert comparison.to_one(flat) == ("not reached", "-")
    final_only = dict(summary, seeds=[{"seed": "seed0", "eval": -1.7}])
    assert comparison.to_one(final_only) == ("within 10,000 (final only)", "within 1.7")
    assert comparison.to_one(dict(final_only, seeds=[{"seed": "seed0", "eval": -3.0}]))[0] == "not reached (final only)"

    root = Path(__file__).resolve().parents[1]
    assert comparison.table() in (root / "docs" / "gradients.md").read_text()
    # on the paper's scale only: an env beyond it, without the paper's score, is left to its page
    assert "cylinder-v0" in comparison.scored_envs() and "pinball-v0" not in comparison.scored_envs()


def test_the_memory_of_a_differentiated_horizon_is_recorded_per_env(tmp_path):
    """benchmarks/grad_memory.py --peak on lorenz: a record with the process's resident
    memory before a horizon, its peak during it (at least what it was before) and what
    the horizon held, with the recipe's settings and a finite gradient."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    command = [sys.executable, str(root / "benchmarks" / "grad_memory.py"), "--peak", "--envs", "lorenz-continuous-v0"]
    command += ["--members", "2", "--horizon", "3", "--out", str(tmp_path)]
    # a file of another's where a record could be named: left as it was
    planted = tmp_path / "peak-planted.json"
    planted.write_text("theirs")
    out = subprocess.run(command, capture_output=True, text=True, check=False, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    assert planted.read_text() == "theirs"
    (record,) = set(tmp_path.glob("peak-*.json")) - {planted}
    (row,) = json.loads(record.read_text())["rows"]
    assert (row["env"], row["members"], row["horizon"]) == ("lorenz-continuous-v0", 2, 3)
    assert row["rss_before"] > 0 and row["peak"] >= row["rss_before"] and row["held"] == row["peak"] - row["rss_before"]
    assert row["finite"] is True and row["grad_checkpoint"] is False


@pytest.mark.slow(seconds=80)
def test_the_actor_critics_settings_are_tried_alone_and_tabled(tmp_path):
    """experiments/shac_ablation.py on burgers, a trial of one update (2,048 transitions): the defaults
    and SAPO's settings together each train a seed, are scored normalised from the own
    start and the test set, recorded with the run's wall time and tabled; a second call
    finds the finished run and only scores it again."""
    import numpy as np
    import torch

    from beacon_torch.files import save_rows
    from experiments import shac_ablation as ablation

    runs, out = tmp_path / "runs", tmp_path / "records"
    rows = [ablation.run("burgers-v0", v, 0, runs, frames=2048) for v in ("defaults", "sapo")]
    for row in rows:
        assert row["frames"] == 2048 and row["wall_s"] > 0
        assert all(np.isfinite(row[k]) for k in ("own_normalised", "test_normalised"))
        save_rows([row], out, f"ablation-burgers-v0-{row['variant']}")
    state = torch.load(runs / "burgers-v0" / "sapo" / "seed0" / "checkpoint.pt", weights_only=True)
    assert state["config"]["actor"] == "stochastic" and state["config"]["critics"] == 2
    again = ablation.run("burgers-v0", "sapo", 0, runs, frames=2048)
    assert again["wall_s"] == rows[1]["wall_s"] and again["own_score"] == rows[1]["own_score"]
    table = ablation.page_table(out)
    assert "| burgers-v0 | defaults: the defaults |" in table and "actor=stochastic" in table
    # the loop without its critic, at the actor-critic's settings for the env
    ablation.run("burgers-v0", "critic-less-squash-margin", 0, runs, frames=2048)
    state = torch.load(runs / "burgers-v0" / "critic-less-squash-margin" / "seed0" / "checkpoint.pt", weights_only=True)
    assert state["algo"] == "grad" and "critic" not in state["modules"]
    assert state["config"]["num_envs"] == 64 and state["config"]["horizon"] == 32
    assert state["config"]["squash_margin"] == 0.01 and not state["config"]["stagger"]
    assert state["config"]["lr"] == 2e-3 and state["config"]["init_scale"] == 1.0
    # and the actor-critic at the loop's settings for the env, its critic closing the horizons
    ablation.run("burgers-v0", "grad-settings-value-weight-0.1", 0, runs, frames=2048)
    state = torch.load(
        runs / "burgers-v0" / "grad-settings-value-weight-0.1" / "seed0" / "checkpoint.pt", weights_only=True
    )
    assert state["algo"] == "shac" and "critic" in state["modules"] and state["config"]["value_weight"] == 0.1
    assert state["config"]["num_envs"] == 16 and state["config"]["squash_margin"] == 0.01 and state["config"]["stagger"]
    assert state["config"]["lr"] == 5e-3 and state["config"]["init_scale"] == 0.01
    # the defaults' updates with the policy's gradient split logged, summarised by quarter
    row = ablation.run("burgers-v0", "gradient-split", 0, runs, frames=4096)
    split = row["gradient_split"]
    assert set(split) == {"ratio", "cosine", "share"} and all(len(v) == 1 for v in split.values()), split
    assert -1 <= split["cosine"][0] <= 1 and 0 <= split["share"][0] <= 1 and split["ratio"][0] >= 0
    save_rows([row], out, "ablation-burgers-v0-gradient-split")
    assert "| burgers-v0 | gradient-split: the defaults | 1 |" in ablation.split_table(out)


def test_the_gradients_page_shows_the_recorded_trials_of_the_actor_critics_settings():
    """Every variant of the settings' trials has a record on burgers at the recipe's
    budget, and the page's table is the one its script writes from the records."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    from experiments import shac_ablation as ablation

    folder = root / "experiments" / "results" / "shac_ablation"
    table = ablation.page_table(folder)
    page = (root / "docs" / "gradients.md").read_text()
    assert table in page and ablation.split_table(folder) in page
    # the gradient's split is recorded on the envs the actor-critic trains, rayleigh-v0 among them
    split = [line for line in ablation.split_table(folder).splitlines() if "gradient-split" in line]
    assert {line.split(" | ")[0][2:] for line in split} >= {"burgers-v0", "vortex-v0", "sloshing-v0", "rayleigh-v0"}
    rows = [line.split(" | ") for line in table.splitlines() if line.startswith("| burgers-v0 |")]
    # each at the recipe's budget of burgers-v0, a tenth of PPO's 500,000 transitions
    counts = [[int(n.replace(",", "")) for n in row[5].split(" or ")] for row in rows]
    assert len(rows) >= 9 and all(min(c) >= 50_000 for c in counts), rows
