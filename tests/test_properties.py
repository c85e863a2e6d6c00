"""Property-based checks (hypothesis): any valid parameters and any actions, box edges
and extreme constants included, give finite observations and rewards or a clean
blow-up termination; any invalid value gives the documented error. Derandomised and
bounded, so that every run checks the same examples in a few seconds per env."""

import dataclasses
import math

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import beacon_torch

from conftest import ALL_ENVS, EXPENSIVE_ENVS, FAST

ENVS = ALL_ENVS
MEMBERS, STEPS = 3, 4
CHECK = settings(max_examples=12, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
# the cavities' steps cost a tenth of a second or more: fewer examples and steps there
# (mixing on the small cavity of the same scheme)
CAVITY_CHECK = settings(CHECK, max_examples=4)


def member_params(env_id: str) -> list:
    """The parameters that may differ per member (the others fix the grid or a start)."""
    fields = dataclasses.fields(beacon_torch.registry.ENVS[env_id].physics.Params)
    return [f for f in fields if f.metadata["per_member"] and f.metadata["kind"] in ("real", "complex")]


def in_range(m) -> st.SearchStrategy:
    low, high = m["low"], m["high"]
    low = low if low is not None else -1e3
    high = high if high is not None else 1e3
    if m["low_open"] or m["high_open"]:
        low, high = low + 1e-6 * max(1.0, abs(low)), high - 1e-6 * max(1.0, abs(high))
    # wide ranges log-uniformly, so that small values are drawn too
    if low > 0 and high / low > 1e3:
        real = st.floats(math.log(low), math.log(high)).map(math.exp)
    else:
        real = st.floats(low, high)
    if m["kind"] == "complex":
        return st.tuples(real, st.floats(0.0, 2 * math.pi)).map(
            lambda rp: complex(rp[0] * math.cos(rp[1]), rp[0] * math.sin(rp[1]))
        )
    return real


def actions(env) -> st.SearchStrategy:
    if env.discrete:
        return st.lists(st.integers(0, env.n_actions - 1), min_size=MEMBERS, max_size=MEMBERS).map(torch.tensor)
    edge = st.sampled_from([-1.0, 1.0, 0.0, -1e6, 1e6])  # beyond the box: clipped
    value = st.one_of(edge, st.floats(-1.0, 1.0))
    size = MEMBERS * math.prod(env.action_shape)
    return st.lists(value, min_size=size, max_size=size).map(
        lambda v: torch.tensor(v).reshape(MEMBERS, *env.action_shape)
    )


@pytest.mark.slow(seconds=20)
@pytest.mark.parametrize("env_id", ENVS)
def test_valid_parameters_and_any_actions_stay_finite_or_end_cleanly(env_id):
    fields = member_params(env_id)
    probe = beacon_torch.make(env_id, MEMBERS, **FAST.get(env_id, {}))
    steps = 2 if env_id in EXPENSIVE_ENVS else STEPS
    strategy = st.tuples(
        st.fixed_dictionaries(
            {f.name: st.lists(in_range(f.metadata), min_size=MEMBERS, max_size=MEMBERS) for f in fields}
        ),
        st.lists(actions(probe), min_size=steps, max_size=steps),
    )

    @(CAVITY_CHECK if env_id in EXPENSIVE_ENVS else CHECK)
    @given(strategy)
    def check(example):
        params, sequence = example
        env = beacon_torch.make(env_id, MEMBERS, seed=0, **FAST.get(env_id, {}), **params)
        td = env.reset()
        ended = torch.zeros(MEMBERS, dtype=torch.bool)
        for action in sequence:
            td[env.action_key] = action
            out = env.step(td)["next"]
            obs, reward = out[env.observation_key], out[env.reward_key]
            assert torch.isfinite(obs).all() and torch.isfinite(reward).all(), params
            terminated = out["terminated"][:, 0]
            fresh = terminated & ~ended
            assert (reward.reshape(MEMBERS, -1)[fresh] == env.physics.blowup_reward).all()
            ended |= terminated
            td = out

    check()


@pytest.mark.parametrize("env_id", ENVS)
def test_values_outside_their_range_are_refused_with_the_documented_error(env_id):
    fields = member_params(env_id)
    if not fields:
        pytest.skip(f"{env_id} has no parameter that may differ per member (test_params covers the others)")

    @CHECK
    @given(st.sampled_from(fields), st.sampled_from(["below", "above", "nan", "inf", "text"]))
    def check(field, how):
        m = field.metadata
        if how == "below" and m["low"] is None or how == "above" and m["high"] is None:
            return
        value = {
            "below": (m["low"] or 0.0) - 1.0 - abs(m["low"] or 0.0),
            "above": (m["high"] or 0.0) * 2 + 1.0,
            "nan": math.nan,
            "inf": math.inf,
            "text": "1",
        }[how]
        if m["kind"] == "complex" and how == "below":
            return  # a modulus has no value below 0
        exc = TypeError if how == "text" else ValueError
        with pytest.raises(exc, match=repr(field.name)):
            beacon_torch.make(env_id, 2, **FAST.get(env_id, {}), **{field.name: value})

    check()
