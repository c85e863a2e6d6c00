"""The conformance kit (``beacon_torch.testing``): every registered env passes every
check, a new env registered from outside the package gets the library's entry points,
and the worked example of docs/adding-an-env.md passes the kit."""

import importlib.util
import sys
from pathlib import Path

import gymnasium
import pytest
import torch

import beacon_torch
from beacon_torch.envs.burgers import BurgersEnv
from beacon_torch.registry import DEFAULTS, ENVS
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
    DEFAULTS.pop(env_id, None)
    gymnasium.registry.pop(f"beacon/{env_id}", None)


@pytest.fixture
def example():
    spec = importlib.util.spec_from_file_location("heat_example", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # as an import would (dataclasses look the module up)
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        unregister("heat-v0")
        sys.modules.pop(spec.name, None)


@pytest.mark.slow(seconds=30)
def test_the_worked_example_passes_every_check(example):
    assert beacon_torch.registry.env_class("heat-v0") is example.HeatEnv
    found = check_flow_env("heat-v0")
    assert found == {
        check: "not applicable: the physics draws from the env's generator, per batch"
        if check == "batch_invariance"
        else "passed"
        for check in CHECKS
    }
    env = gymnasium.make("beacon/heat-v0", compile=False)
    assert env.reset(seed=0)[0].shape == (4,)


def test_a_registered_variant_gets_make_gymnasium_and_its_base_card():
    try:
        cls = beacon_torch.register("burgers-calm-v0", BurgersEnv, sigma=0.0)
        assert cls.base_id() == "burgers-v0" and cls.paper_ppo == BurgersEnv.paper_ppo
        env = beacon_torch.make("burgers-calm-v0", 2)
        assert env.env_id == "burgers-calm-v0" and env.params.sigma.tolist() == [0.0, 0.0]
        assert beacon_torch.make("burgers-calm-v0", 1, sigma=0.2).params.sigma.tolist() == [pytest.approx(0.2)]
        assert "beacon/burgers-calm-v0" in gymnasium.registry
        assert beacon_torch.register("burgers-calm-v0", BurgersEnv, sigma=0.0) is cls  # again: nothing new
        with pytest.raises(ValueError, match="registered already"):
            beacon_torch.register("burgers-calm-v0", BurgersEnv, sigma=0.05)
    finally:
        unregister("burgers-calm-v0")
    assert "burgers-calm-v0" not in beacon_torch.list_envs()


def test_register_refuses_what_it_cannot_serve():
    with pytest.raises(ValueError, match="lower-case words and a version"):
        beacon_torch.register("Burgers", BurgersEnv)
    with pytest.raises(TypeError, match="FlowEnv subclass"):
        beacon_torch.register("thing-v0", dict)
    with pytest.raises(ValueError, match="unknown default"):
        beacon_torch.register("burgers-odd-v0", BurgersEnv, viscosity=1.0)
    with pytest.raises(ValueError, match="registered already"):
        beacon_torch.register("lorenz-v0", BurgersEnv)
    assert "burgers-odd-v0" not in ENVS


def test_the_kit_names_the_env_the_check_and_the_fault(monkeypatch):
    """An env that breaks a promise fails the kit with a message that says which."""
    monkeypatch.setattr(BurgersEnv, "observe", lambda self, state: state["u"][:, :5] * torch.rand(()))
    with pytest.raises(ConformanceError, match="burgers-v0: seeding: two envs of seed 123: observations differ"):
        check_flow_env("burgers-v0", ["seeding"])
    with pytest.raises(ValueError, match="unknown check"):
        check_flow_env("burgers-v0", ["speed"])
