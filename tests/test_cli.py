"""The beacon-torch command."""

import json
import os
import subprocess
import sys

import pytest
from PIL import Image

from beacon_torch.cli import main


def test_run_reports_scores_and_writes_a_plot(tmp_path, capsys):
    assert main(["run", "lorenz-v0", "--num-envs", "4", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "uncontrolled: score 207" in out
    scores = json.loads((tmp_path / "scores.json").read_text())
    assert scores["uncontrolled"]["mean"] == 207.0
    assert scores["random"]["num_envs"] == 4
    with Image.open(tmp_path / "run.png") as im:
        assert im.size[0] > 300


def test_run_with_parameters_and_gif(tmp_path):
    gif = tmp_path / "v.gif"
    args = [
        "run",
        "vortex-v0",
        "--num-envs",
        "2",
        "--out",
        str(tmp_path),
        "--param",
        "w=10",
        "--gif",
        str(gif),
        "--gif-every",
        "200",
    ]
    assert main(args) == 0
    with Image.open(gif) as im:
        assert im.n_frames == 1 + 800 // 200
    assert json.loads((tmp_path / "scores.json").read_text())["params"] == {"w": "10"}


def test_bad_arguments_get_one_line(tmp_path, capsys):
    assert main(["run", "nope-v0", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "unknown env id 'nope-v0'" in err
    assert main(["run", "vortex-v0", "--param", "re=-4", "--out", str(tmp_path)]) == 2
    assert "'re'" in capsys.readouterr().err
    assert main(["run", "vortex-v0", "--param", "re", "--out", str(tmp_path)]) == 2
    assert "NAME=VALUE" in capsys.readouterr().err
    assert main(["run", "vortex-v0", "--num-envs", "0", "--out", str(tmp_path)]) == 2
    assert "--num-envs" in capsys.readouterr().err


def test_list_and_console_script():
    proc = subprocess.run(
        [sys.executable, "-m", "beacon_torch.cli", "list"], capture_output=True, text=True, check=True
    )
    assert "lorenz-v0: 3 discrete actions" in proc.stdout and "rho = 28.0" in proc.stdout
    # defaults as the env resolves them, ranges as make() enforces them
    assert "start = 'published'" in proc.stdout and "start = None" not in proc.stdout
    assert "ctrl_pos = 1.0  [0.024, 99.992]" in proc.stdout


def test_version_module_entry_and_plain_help():
    """``python -m beacon_torch`` is the command; ``--version`` says which; the help's
    descriptions read as text, not reStructuredText."""
    import beacon_torch

    proc = subprocess.run(
        [sys.executable, "-m", "beacon_torch", "--version"], capture_output=True, text=True, check=True
    )
    assert proc.stdout.strip() == f"beacon-torch {beacon_torch.__version__}"
    proc = subprocess.run([sys.executable, "-m", "beacon_torch", "--help"], capture_output=True, text=True, check=True)
    assert "usage: beacon-torch" in proc.stdout and "``" not in proc.stdout


def test_the_package_declares_its_type_hints():
    """PEP 561: a py.typed marker, shipped as package data."""
    from pathlib import Path

    import beacon_torch

    root = Path(beacon_torch.__file__).parent
    assert (root / "py.typed").is_file()
    import tomllib

    project = tomllib.loads((root.parent / "pyproject.toml").read_text())
    assert "py.typed" in project["tool"]["setuptools"]["package-data"]["beacon_torch"]


def test_eval_and_run_show_progress(tmp_path, capsys):
    """Episodes of a slow env take minutes: eval and run show a bar per episode."""
    assert main(["eval", "--pretrained", "ppo/vortex-v0", "--num-envs", "1", "--no-gif", "--out", str(tmp_path)]) == 0
    err = capsys.readouterr().err
    assert "vortex-v0 controlled" in err and "vortex-v0 uncontrolled" in err and "actions" in err
    assert main(["run", "lorenz-v0", "--num-envs", "2", "--out", str(tmp_path)]) == 0
    captured = capsys.readouterr()
    assert "lorenz-v0 uncontrolled" in captured.err and "lorenz-v0 random" in captured.err
    assert "500 steps in float64" in captured.out  # the default dtype, said


def test_help_and_list_answer_without_importing_torch():
    probe = (
        "import contextlib, io, sys\n"
        "from beacon_torch.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    main(['list'])\n"
        "    try:\n"
        "        main(['--help'])\n"
        "    except SystemExit:\n"
        "        pass\n"
        "print('torch' in sys.modules)\n"
    )
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert done.stdout.strip() == "False", done.stdout + done.stderr


def test_the_stored_listing_is_the_envs_own():
    from beacon_torch import cli

    assert cli.LISTING.read_text() == cli.listing(), "run docs/make_env_tables.py"


USER_ENV = """
import beacon_torch
from beacon_torch.envs.lorenz import CARD, LorenzPhysics

beacon_torch.register("heat-v0", LorenzPhysics, CARD)
"""


def test_commands_and_recipes_find_the_users_modules_from_the_working_directory(tmp_path):
    """As ``python -m`` does: the console script and ``python recipes/ppo.py`` run from
    the project folder that holds ``my_envs/heat.py`` import it without PYTHONPATH."""
    from pathlib import Path

    (tmp_path / "my_envs").mkdir()
    (tmp_path / "my_envs" / "__init__.py").write_text("")
    (tmp_path / "my_envs" / "heat.py").write_text(USER_ENV)
    command = Path(sys.executable).parent / "beacon-torch"
    root = Path(__file__).resolve().parents[1]
    for argv in (
        [str(command), "--import", "my_envs.heat", "list"],
        [sys.executable, str(root / "recipes" / "ppo.py"), "--env", "my_envs.heat:heat-v0", "--help"],
    ):
        done = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0 and "heat-v0" in done.stdout, done.stderr


def test_threads_default_to_the_measured_fastest_unless_told(monkeypatch, tmp_path):
    import torch

    from beacon_torch import threads

    monkeypatch.delenv("BEACON_TORCH_THREADS", raising=False)
    steps, training = threads._table()["steps"], threads._table()["training"]
    assert threads.choose(threads.cores(), "lorenz-v0", 1) == (threads.cores(), "given")
    # more threads than cores only wait on each other
    with pytest.raises(ValueError, match=f"threads must be an integer in \\[1, {threads.cores()}\\]"):
        threads.choose(threads.cores() + 1, "lorenz-v0", 1)
    # the nearest measured batch, on a log scale; a variant steps its base env's physics
    assert threads.fastest("lorenz-continuous-v0", 1) == min(steps["lorenz-v0"]["1"], os.cpu_count())
    assert threads.fastest("cylinder-v0", 8) == min(steps["cylinder-v0"]["16"], os.cpu_count())
    assert threads.fastest("burgers-v0", 16, training=True) == min(training["burgers-v0"], os.cpu_count())
    count, why = threads.choose(None, "lorenz-v0", 1)
    assert count == threads.fastest("lorenz-v0", 1) and "stepping 1 member of lorenz-v0" in why
    assert "training on lorenz-v0" in threads.choose(None, "lorenz-v0", 16, training=True)[1]
    monkeypatch.setenv("BEACON_TORCH_THREADS", "1")
    assert threads.choose(None, "cylinder-v0", 64) == (1, "$BEACON_TORCH_THREADS")
    monkeypatch.setenv("BEACON_TORCH_THREADS", "two")
    with pytest.raises(ValueError, match="BEACON_TORCH_THREADS must be an integer in"):
        threads.choose(None, "lorenz-v0", 1)
    with pytest.raises(ValueError, match="threads must be an integer in \\[1, "):
        threads.choose(0)
    before = torch.get_num_threads()
    try:
        assert main(["--threads", "1", "list"]) == 0 and torch.get_num_threads() == before  # list runs nothing
        assert main(["--threads", "1", "run", "lorenz-v0", "--num-envs", "1", "--out", str(tmp_path)]) == 0
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
