"""Construction-time validation of env parameters and options."""

import math

import numpy as np
import pytest
import torch

import beacon_torch


def test_defaults_are_the_papers_tables():
    env = beacon_torch.make("lorenz-v0")
    assert (env.params.sigma, env.params.rho, env.params.beta) == (10.0, 28.0, 8.0 / 3.0)
    env = beacon_torch.make("vortex-v0")
    assert (env.params.re, env.params.w) == (50.0, 50.0)


def test_parameters_are_keyword_arguments():
    env = beacon_torch.make("lorenz-v0", 2, rho=20, beta=np.float64(2.5))
    # a parameter that may differ per member is one value per member inside the env,
    # whether it was given as one number or as a sequence
    assert torch.equal(env.params.rho, torch.tensor([20.0, 20.0]))
    assert torch.equal(env.params.beta, torch.tensor([2.5, 2.5]))
    # grid-fixing parameters stay numbers
    assert beacon_torch.make("shkadov-v0", n_jets=3).params.n_jets == 3


@pytest.mark.parametrize(
    "env_id, kwargs, exc, words",
    [
        ("lorenz-v0", {"rhoo": 3.0}, TypeError, ["rhoo", "sigma, rho, beta"]),
        ("vortex-v0", {"Re": 50.0}, TypeError, ["'Re'", "re, w"]),
        ("lorenz-v0", {"rho": "28"}, TypeError, ["'rho'", "string"]),
        ("lorenz-v0", {"rho": True}, TypeError, ["'rho'", "bool"]),
        ("lorenz-v0", {"sigma": None}, TypeError, ["'sigma'"]),
        ("lorenz-v0", {"sigma": 1 + 2j}, TypeError, ["'sigma'", "real"]),
        ("lorenz-v0", {"rho": math.nan}, ValueError, ["'rho'", "finite"]),
        ("lorenz-v0", {"beta": math.inf}, ValueError, ["'beta'", "finite"]),
        ("lorenz-v0", {"sigma": 0.0}, ValueError, ["'sigma'", "(0, 1000]"]),
        ("lorenz-v0", {"rho": -1.0}, ValueError, ["'rho'", "-1.0"]),
        ("vortex-v0", {"re": 1e9}, ValueError, ["'re'", "10000"]),
        ("vortex-v0", {"w": -0.1}, ValueError, ["'w'", "[0,"]),
        ("vortex-v0", {"a0": 100.0}, ValueError, ["'a0'", "|value|"]),
        ("vortex-v0", {"y0": complex(math.nan, 0)}, ValueError, ["'y0'", "finite"]),
        ("lorenz-v0", {"rho": [28.0, 29.0, 30.0]}, ValueError, ["'rho'", "(2,)", "(3,)"]),
        ("lorenz-v0", {"rho": [28.0, -1.0]}, ValueError, ["'rho'[1]"]),
        ("lorenz-v0", {"rho": [[28.0, 28.0]]}, ValueError, ["'rho'", "(1, 2)"]),
        ("burgers-v0", {"ctrl_pos": 1.9999}, ValueError, ["'ctrl_pos'", "L - 0.008"]),
        ("burgers-v0", {"ctrl_pos": 0.01}, ValueError, ["'ctrl_pos'"]),
        ("burgers-v0", {"L": [2.0, 2.0]}, TypeError, ["'L'", "whole batch"]),
        ("burgers-v0", {"sigma": -0.1}, ValueError, ["'sigma'"]),
        ("burgers-v0", {"u_target": [0.5, 0.0]}, ValueError, ["'u_target'[1]"]),
        ("sloshing-v0", {"g": 0.0}, ValueError, ["'g'"]),
        ("sloshing-v0", {"alpha": float("nan")}, ValueError, ["'alpha'", "finite"]),
        ("sloshing-v0", {"L": 0.0}, ValueError, ["'L'"]),
        ("shkadov-v0", {"n_jets": 2.5}, TypeError, ["'n_jets'", "integer"]),
        ("shkadov-v0", {"n_jets": 0}, ValueError, ["'n_jets'"]),
        ("shkadov-v0", {"n_jets": 50}, ValueError, ["'L0'", "'n_jets'", "580"]),
        ("shkadov-v0", {"jet_pos": 200.0}, ValueError, ["'jet_pos'"]),
        ("shkadov-v0", {"delta": [0.1, 0.2]}, TypeError, ["'delta'"]),
        ("shkadov-v0", {"random_start": -1}, ValueError, ["'random_start'"]),
        ("shkadov-separable-v0", {"jet_space": 1.0}, ValueError, ["'jet_space'"]),
        ("rayleigh-v0", {"n_sgts": 7}, ValueError, ["'n_sgts'", "divide"]),
        ("rayleigh-v0", {"ra": 0.0}, ValueError, ["'ra'"]),
        ("rayleigh-v0", {"ra": [1e4, 1e4]}, TypeError, ["'ra'"]),
        ("mixing-v0", {"side": 2.0}, ValueError, ["'side'"]),
        ("mixing-v0", {"pe": -1.0}, ValueError, ["'pe'"]),
        ("mixing-continuous-v0", {"c0": 0.0}, ValueError, ["'c0'"]),
    ],
)
def test_bad_parameters_raise_naming_the_parameter(env_id, kwargs, exc, words):
    with pytest.raises(exc) as info:
        beacon_torch.make(env_id, 2, **kwargs)
    for word in words:
        assert word in str(info.value), (word, str(info.value))


def test_params_are_a_value_separate_from_the_options():
    """``params=`` takes the env's ``Params`` (the whole physics) or a dict of some of its
    fields; keywords stay sugar for the same; options never mix with them."""
    from beacon_torch.envs.burgers import BurgersParams

    as_value = beacon_torch.make("burgers-v0", 2, params=BurgersParams(amp=5.0, sigma=0.2), seed=0)
    as_dict = beacon_torch.make("burgers-v0", 2, params={"amp": 5.0, "sigma": 0.2}, seed=0)
    as_keywords = beacon_torch.make("burgers-v0", 2, amp=5.0, sigma=0.2, seed=0)
    for env in (as_value, as_dict, as_keywords):
        assert env.params.amp.tolist() == [5.0, 5.0] and env.params.sigma.tolist() == pytest.approx([0.2, 0.2])
        assert env.params.ctrl_pos == BurgersParams().ctrl_pos
    both = beacon_torch.make("burgers-v0", 2, params={"amp": 5.0}, record_history=True)
    assert both.history.enabled and both.params.amp.tolist() == [5.0, 5.0]
    with pytest.raises(TypeError, match="'amp' given twice"):
        beacon_torch.make("burgers-v0", params={"amp": 5.0}, amp=6.0)
    with pytest.raises(TypeError, match="BurgersParams .*or a dict"):
        beacon_torch.make("burgers-v0", params=("amp", 5.0))
    from beacon_torch.envs.lorenz import LorenzParams

    with pytest.raises(TypeError, match="burgers-v0: params must be a BurgersParams"):
        beacon_torch.make("burgers-v0", params=LorenzParams())
    with pytest.raises(TypeError, match="unknown parameter 'compile'"):
        beacon_torch.make("burgers-v0", params={"compile": True})


def test_num_envs_is_the_batch_and_batch_size_torchrls_name_for_it():
    env = beacon_torch.make("lorenz-v0", num_envs=3)
    assert env.num_envs == 3 and env.batch_size == torch.Size([3])
    assert beacon_torch.make("lorenz-v0", batch_size=5).num_envs == 5  # as TorchRL users write it
    assert beacon_torch.make("lorenz-v0").num_envs == 1
    with pytest.raises(TypeError, match="num_envs or batch_size"):
        beacon_torch.make("lorenz-v0", 2, batch_size=2)


def test_per_member_parameters_become_batch_tensors():
    env = beacon_torch.make("lorenz-v0", 3, dtype=torch.float64, rho=torch.tensor([10.0, 28.0, 99.0]))
    assert isinstance(env.params.rho, torch.Tensor)
    assert env.params.rho.dtype == torch.float64 and env.params.rho.shape == (3,)
    env = beacon_torch.make("vortex-v0", 2, a0=[0.01, 0.02j])
    assert env.params.a0.dtype == torch.complex64


def test_zero_dim_tensors_are_scalars():
    env = beacon_torch.make("lorenz-v0", 4, rho=torch.tensor(20.0))
    assert torch.equal(env.params.rho, torch.full((4,), 20.0))


@pytest.mark.parametrize(
    "kwargs, exc, words",
    [
        ({"batch_size": 0}, ValueError, ["batch_size", "positive"]),
        ({"batch_size": -3}, ValueError, ["batch_size"]),
        ({"batch_size": (2, 3)}, ValueError, ["batch_size", "1-D"]),
        ({"batch_size": 2.5}, TypeError, ["batch_size"]),
        ({"batch_size": True}, TypeError, ["batch_size"]),
        ({"dtype": torch.float16}, ValueError, ["dtype", "float32", "float64"]),
        ({"dtype": "double-ish"}, ValueError, ["dtype"]),
    ],
)
def test_bad_options_raise(kwargs, exc, words):
    with pytest.raises(exc) as info:
        beacon_torch.make("lorenz-v0", **kwargs)
    for word in words:
        assert word in str(info.value)


def test_unknown_env_id_lists_the_known_ones():
    with pytest.raises(ValueError, match="unknown env id 'lorenz-v9'.*lorenz-v0"):
        beacon_torch.make("lorenz-v9")


def test_list_envs():
    assert beacon_torch.list_envs() == [
        "burgers-v0",
        "cylinder-v0",
        "ks-v0",
        "lorenz-continuous-v0",
        "lorenz-v0",
        "mixing-continuous-v0",
        "mixing-v0",
        "pinball-chaotic-v0",
        "pinball-periodic-v0",
        "pinball-v0",
        "rayleigh-separable-v0",
        "rayleigh-v0",
        "rbc2d-easy-ma-v0",
        "rbc2d-easy-v0",
        "rbc2d-hard-ma-v0",
        "rbc2d-hard-v0",
        "rbc2d-medium-ma-v0",
        "rbc2d-medium-v0",
        "shkadov-separable-v0",
        "shkadov-v0",
        "sloshing-v0",
        "vortex-v0",
    ]


@pytest.mark.parametrize("dtype", ["float32", "float64", torch.float32, torch.float64, "torch.float64"])
def test_dtype_spellings(dtype):
    env = beacon_torch.make("vortex-v0", 2, dtype=dtype)
    td = env.rollout(3)
    assert td["observation"].dtype == env.dtype == td["next", "reward"].dtype


# ---------------------------------------------------------------- start states
STARTS = {
    "sloshing-v0": {"L": 3.0},
    "shkadov-v0": {"L0": 140.0},
    "shkadov-separable-v0": {"n_jets": 4},
    "rayleigh-v0": {"H": 1.2},
}


@pytest.mark.parametrize("env_id", sorted(STARTS))
def test_published_start_is_the_default_and_a_new_grid_falls_back_to_the_generator(env_id):
    assert beacon_torch.make(env_id).params.start == "published"
    assert beacon_torch.make(env_id, start="generated").params.start == "generated"
    changed = STARTS[env_id]
    assert beacon_torch.make(env_id, **changed).params.start == "generated"
    (name,) = changed
    with pytest.raises(ValueError, match=f"parameter '{name}' .* differs from the published start"):
        beacon_torch.make(env_id, start="published", **changed)
    with pytest.raises(ValueError, match="parameter 'start' must be one of 'published', 'generated'"):
        beacon_torch.make(env_id, start="stored")


def test_the_published_start_is_the_stored_state_and_its_file_is_read_once(monkeypatch):
    from beacon_torch import cache, starts

    monkeypatch.setattr(cache, "_memory", {})  # a process that has read no start yet
    reads = []
    parse = starts._table
    monkeypatch.setattr(starts, "_table", lambda *args: reads.append(args) or parse(*args))
    env = beacon_torch.make("sloshing-v0", 2, dtype=torch.float64)
    env.reset()
    table = starts.published_table("sloshing", 200, 3)
    assert table.shape == (200, 3)
    assert torch.equal(env.state.h[1], table[:, 1]) and torch.equal(env.state.q[0], table[:, 2])
    for _ in range(3):
        beacon_torch.make("sloshing-v0", 4).reset()
    assert reads == [("sloshing", 200, 3)]
    # a caller that edits what it got does not edit the shared copy
    table[:] = 0.0
    assert starts.published_table("sloshing", 200, 3).abs().max() > 0


def test_published_rayleigh_start_has_the_published_nusselt_number():
    from beacon_torch.envs.rayleigh import nusselt

    for start in ("published", "generated"):
        env = beacon_torch.make("rayleigh-v0", 1, dtype=torch.float64, start=start)
        env.reset()
        assert nusselt(env.state.theta, env.physics.dy).item() == pytest.approx(2.16, rel=0.01)
