"""The conformance kit (``beacon_torch.testing``): every registered env passes every
check, a new env registered from outside the package gets the library's entry points,
and the worked example of docs/adding-an-env.md passes the kit."""

import importlib
import json
import sys
from pathlib import Path

import gymnasium
import pytest
import torch

import beacon_torch
from beacon_torch.envs import burgers
from beacon_torch.envs.burgers import BurgersPhysics
from beacon_torch.registry import ENVS
from beacon_torch.testing import CHECKS, ConformanceError, check_flow_env

from conftest import ALL_ENVS, EXPENSIVE_ENVS

EXAMPLE = Path(__file__).resolve().parents[1] / "docs" / "examples" / "heat.py"
# the longest checks, measured on one core: the cavities compile for about 40 s, and
# their gradients and adapters take tens of seconds
SECONDS = {"compile": 60, "gradients": 30, "adapters": 20}


def cases():
    for env_id in ALL_ENVS:
        for check in CHECKS:
            seconds = SECONDS.get(check, 5) if env_id in EXPENSIVE_ENVS else (20 if check == "compile" else 1)
            yield pytest.param(env_id, check, marks=pytest.mark.slow(seconds=seconds), id=f"{env_id}-{check}")


@pytest.mark.parametrize("env_id, check", list(cases()))
def test_every_env_passes_the_kit(env_id, check):
    found = check_flow_env(env_id, [check])
    assert found[check] == "passed" or found[check].startswith("not applicable")


def unregister(env_id):
    ENVS.pop(env_id, None)
    beacon_torch.registry.ORIGIN.pop(env_id, None)
    gymnasium.registry.pop(f"beacon/{env_id}", None)


@pytest.fixture
def example():
    try:
        # imported afresh, so that it registers its env again
        sys.modules.pop("docs.examples.heat", None)
        yield importlib.import_module("docs.examples.heat")
    finally:
        unregister("heat-v0")
        sys.modules.pop("docs.examples.heat", None)


@pytest.mark.slow(seconds=30)
def test_the_worked_example_passes_every_check(example):
    spec = beacon_torch.registry.env_spec("heat-v0")
    assert spec.physics is example.HeatPhysics and spec.card is example.CARD
    found = check_flow_env("heat-v0")
    assert found == {
        check: "not applicable: the physics draws from the env's generator, per batch"
        if check == "batch_invariance"
        else "passed"
        for check in CHECKS
    }
    env = gymnasium.make("beacon/heat-v0", compile=False)
    assert env.reset(seed=0)[0].shape == (4,)


def test_an_env_without_published_facts_registers_benches_and_is_refused_by_the_protocol(example, tmp_path):
    """The example has no published code and no paper: its card says so (None), the
    benchmark gives its rate without a factor over published code, and the protocol,
    which normalises by a declared reference, refuses it in one line instead of inventing one."""
    import json

    from beacon_torch import bench
    from beacon_torch.training import report

    card = beacon_torch.registry.env_spec("heat-v0").card
    assert (card.published_speed, card.speed_target, card.paper_ppo, card.costly) == (None, None, None, False)
    assert card.scale_reference() is None
    measured = bench.measure("heat-v0", 4, steps=2, repeats=1)
    assert measured.transitions_per_s > 0 and measured.published_per_s is None and measured.speedup is None
    assert "| heat-v0 |" in bench.markdown([measured]) and "| - | - |  |" in bench.markdown([measured])
    summary = {"env": "heat-v0", "algo": "ppo", "uncontrolled": -1.0, "frames": 10, "wall_s_per_seed": 1.0}
    file = tmp_path / "summary.json"
    file.write_text(json.dumps({**summary, "seeds": [{"eval": -0.5}]}))
    with pytest.raises(
        ValueError, match="heat-v0 has no reference on its card \\(paper_ppo or reference\\) to normalise by"
    ):
        report.read(file)


def test_a_registered_variant_gets_make_gymnasium_and_its_base_card():
    import beacon_torch.gym  # gymnasium's ids, registered as envs are

    try:
        spec = beacon_torch.register("burgers-calm-v0", ENVS["burgers-v0"], sigma=0.0)
        assert spec.base_id() == "burgers-v0" and spec.card is burgers.CARD and spec.physics is BurgersPhysics
        env = beacon_torch.make("burgers-calm-v0", 2)
        assert env.env_id == "burgers-calm-v0" and env.params.sigma.tolist() == [0.0, 0.0]
        assert beacon_torch.make("burgers-calm-v0", 1, sigma=0.2).params.sigma.tolist() == [pytest.approx(0.2)]
        assert "beacon/burgers-calm-v0" in gymnasium.registry
        assert beacon_torch.register("burgers-calm-v0", ENVS["burgers-v0"], sigma=0.0) is spec  # again: nothing new
        with pytest.raises(ValueError, match="registered already"):
            beacon_torch.register("burgers-calm-v0", ENVS["burgers-v0"], sigma=0.05)
    finally:
        unregister("burgers-calm-v0")
    assert "burgers-calm-v0" not in beacon_torch.list_envs()


CALM = """
import beacon_torch
from beacon_torch.registry import ENVS

beacon_torch.register("burgers-calm-v0", ENVS["burgers-v0"], sigma=0.0)
"""


@pytest.mark.slow(seconds=25)
def test_an_env_registered_by_a_module_reaches_other_processes(tmp_path, monkeypatch):
    """An env that a user's module registers is rebuilt in processes that did not import
    it: the command line (``module:env-id`` or ``--import``) and collector workers."""
    import subprocess

    from torchrl.collectors import MultiSyncCollector

    from beacon_torch.training.env import make_collector, make_env

    (tmp_path / "calm_envs.py").write_text(CALM)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    cli = [sys.executable, "-m", "beacon_torch.cli"]
    listed = subprocess.run([*cli, "--import", "calm_envs", "list"], capture_output=True, text=True, check=True)
    assert "burgers-calm-v0:" in listed.stdout
    ran = subprocess.run(
        [*cli, "run", "calm_envs:burgers-calm-v0", "--num-envs", "2", "--out", str(tmp_path / "out")],
        capture_output=True,
        text=True,
    )
    assert ran.returncode == 0, ran.stderr
    scores = json.loads((tmp_path / "out" / "scores.json").read_text())
    assert scores["env"] == "burgers-calm-v0" and scores["random"]["num_envs"] == 2
    try:
        env = make_env("calm_envs:burgers-calm-v0", 2, norm_steps=0)
        assert beacon_torch.registry.qualified_id("burgers-calm-v0") == "calm_envs:burgers-calm-v0"
        collector = make_collector("burgers-calm-v0", env, None, frames_per_batch=8, total_frames=8, collectors=2)
        assert isinstance(collector, MultiSyncCollector)
        try:
            (batch,) = list(collector)
        finally:
            collector.shutdown()
        assert batch.shape[:2] == (2, 2) and torch.isfinite(batch["next", "reward"]).all()
    finally:
        unregister("burgers-calm-v0")
        sys.modules.pop("calm_envs", None)


def test_register_refuses_what_it_cannot_serve():
    with pytest.raises(ValueError, match="lower-case words and a version"):
        beacon_torch.register("Burgers", BurgersPhysics)
    with pytest.raises(TypeError, match="Physics subclass or a registered EnvSpec"):
        beacon_torch.register("thing-v0", dict)
    with pytest.raises(ValueError, match="unknown default"):
        beacon_torch.register("burgers-odd-v0", BurgersPhysics, viscosity=1.0)
    with pytest.raises(ValueError, match="registered already"):
        beacon_torch.register("lorenz-v0", BurgersPhysics)
    untyped = type("UntypedPhysics", (BurgersPhysics,), {"state_type": dict})
    with pytest.raises(TypeError, match="UntypedPhysics declares no state type"):
        beacon_torch.register("untyped-v0", untyped)
    assert "burgers-odd-v0" not in ENVS and "untyped-v0" not in ENVS


def test_the_state_is_the_envs_declared_type(monkeypatch):
    """Every env's state is its NamedTuple, batch first, whatever path made it."""
    for env_id in ALL_ENVS:
        state_type = ENVS[env_id].physics.state_type
        assert issubclass(state_type, tuple) and state_type._fields, env_id
    env = beacon_torch.make("burgers-v0", 2, seed=0)
    env.reset()
    assert type(env.state) is env.physics.state_type and env.state.u.shape[0] == 2
    env.step_members(env.null_action())
    assert type(env.state) is env.physics.state_type
    env.set_state(env.state._asdict())  # a dict of its fields is taken too
    assert type(env.state) is env.physics.state_type
    not_a_state = lambda self, p, generator, mask=None: {"u": torch.zeros(2, 500)}
    monkeypatch.setattr(BurgersPhysics, "initial_state", not_a_state)
    with pytest.raises(TypeError, match="burgers-v0: initial_state returned a dict, not the env's state type"):
        beacon_torch.make("burgers-v0", 2).reset()


def test_the_kit_names_the_env_the_check_and_the_fault(monkeypatch):
    """An env that breaks a promise fails the kit with a message that says which."""
    monkeypatch.setattr(BurgersPhysics, "observe", lambda self, p, state: state.u[:, :5] * torch.rand(()))
    with pytest.raises(ConformanceError, match="burgers-v0: seeding: two envs of seed 123: observations differ"):
        check_flow_env("burgers-v0", ["seeding"])
    with pytest.raises(ValueError, match="unknown check"):
        check_flow_env("burgers-v0", ["speed"])
