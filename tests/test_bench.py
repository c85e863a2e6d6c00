"""``beacon-torch bench``: the throughput measurement and its outputs."""

import csv
import json

import pytest

from beacon_torch import bench
from beacon_torch.cli import main


def test_measure_reports_rates_against_the_published_speed():
    m = bench.measure("lorenz-v0", 4, steps=3, repeats=2)
    assert m.transitions_per_s > 0 and m.step_ms > 0
    assert m.published_per_s == 62_300.0
    assert m.speedup == pytest.approx(m.transitions_per_s / 62_300.0)
    assert m.mode == "eager" and m.dtype == "float32" and m.batch == 4
    # variants without a published number of their own use their base env's
    assert bench.measure("mixing-continuous-v0", 1, steps=1, repeats=1).published_per_s == 3.7


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
            "8",
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
    assert {(r["env"], int(r["batch"])) for r in rows} == {(e, b) for e in ("lorenz-v0", "vortex-v0") for b in (1, 8)}
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["machine"] and len(data["results"]) == 4
    assert (tmp_path / "throughput.png").stat().st_size > 10_000
    md = (tmp_path / "results.md").read_text()
    assert "## Best speed per env" in md and md.count("| lorenz-v0 |") == 3  # best + 2 rows
    again = bench.load(tmp_path / "results.json")
    assert [m.transitions_per_s for m in again] == [float(r["transitions_per_s"]) for r in rows]


def test_bench_command_reports_bad_input(capsys):
    assert main(["bench", "--envs", "nope-v0"]) == 2
    assert "nope-v0" in capsys.readouterr().err
    assert main(["bench", "--envs", "lorenz-v0", "--num-envs", "0"]) == 2
    assert "--num-envs" in capsys.readouterr().err
