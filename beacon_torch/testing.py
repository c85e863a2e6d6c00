"""The conformance kit: what every env must pass, in one call.

    from beacon_torch.testing import check_flow_env

    check_flow_env("burgers-v0")                      # every check
    check_flow_env("my-env-v0", checks=["specs", "blow_up"])

An env registered with :func:`beacon_torch.register` (or any of the package's) is
checked on small batches with the cheap parameters its card declares
(``test_settings``), in float64 wherever numbers are compared. Each check raises
:class:`ConformanceError` naming the env, the check and what went wrong;
:func:`check_flow_env` returns what each check found (``"passed"`` or why it does not
apply). The package's test suite runs every check on every registered env.

The checks (:data:`CHECKS`, in the order they run):

``specs``
    TorchRL's ``check_env_specs`` at batch 1 and 4 (float64 too but for the cavities),
    and the specs' documented types: a bounded action in ``[-1, 1]`` or a categorical
    one, an unbounded observation, ``[batch, 1]`` done flags.
``seeding``
    the same seed gives the same episode; ``set_seed`` re-seeds the env's own generator.
``batch_invariance``
    (deterministic physics) a member of a batch follows the same trajectory as that
    member alone: bit for bit, but for the cavities, whose Poisson solve is a matrix
    product over the batch whose rounding depends on the batch size (to round-off).
``partial_reset``
    a reset of some members leaves the others' state, counters and observation as they
    were, and starts the reset ones afresh.
``blow_up``
    a member pushed to absurd values ends its episode with ``blowup_reward`` and a
    finite observation; the others go on bit for bit as in a batch without it.
``gradients``
    (continuous actions) the card's gradient check: the derivatives of the summed
    rewards with respect to the actions and to its parameter equal central differences;
    every other differentiable parameter's derivative is finite and agrees with central
    differences too.
``compile``
    a compiled env follows the eager one within round-off over a whole episode (three
    actions of a cavity).
``adapters``
    the gymnasium env passes gymnasium's checker and steps bit for bit as the TorchRL
    env; the gymnasium and Stable-Baselines3 vector envs step as the batched env.
``render``
    a frame is an RGB image, and the drawing of an episode changes it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from beacon_torch import seeds
from beacon_torch.base import FlowEnv, make
from beacon_torch.core.state import map_state
from beacon_torch.registry import ENVS, EnvSpec, env_spec

F64 = torch.float64
# compiled code may fuse or reorder floating-point operations: trajectories of a few
# float64 steps agree to round-off, well inside this
ROUND_OFF = dict(rtol=1e-10, atol=1e-12)
# relative agreement of autograd with central differences of relative step 1e-6
GRADIENT_REL = 1e-5


class ConformanceError(AssertionError):
    """An env failed a conformance check."""


CHECKS: dict[str, Callable[[EnvSpec], str]] = {}


def _check(fn: Callable[[EnvSpec], str | None]) -> Callable:
    CHECKS[fn.__name__.removeprefix("check_")] = fn
    return fn


def check_flow_env(env: str | EnvSpec, checks: list[str] | None = None) -> dict[str, str]:
    """Run the conformance ``checks`` (all by default) on ``env``, an env id or a
    registered id's :class:`~beacon_torch.registry.EnvSpec`; returns ``{check: "passed"
    or why it does not apply}`` and raises :class:`ConformanceError` at the first
    failure."""
    spec = env_spec(env) if isinstance(env, str) else env
    if not isinstance(spec, EnvSpec):
        raise TypeError(f"check_flow_env needs an env id or a registered EnvSpec, got {env!r}")
    if ENVS.get(spec.env_id) is not spec:
        raise ValueError(
            f"{spec.env_id!r} is not registered as given: beacon_torch.register it first (the adapters find envs by id)"
        )
    unknown = sorted(set(checks or ()) - set(CHECKS))
    if unknown:
        raise ValueError(f"unknown check(s) {unknown}; the checks are {list(CHECKS)}")
    found = {}
    for name in checks or CHECKS:
        try:
            found[name] = CHECKS[name](spec) or "passed"
        except ConformanceError:
            raise
        except AssertionError as err:
            raise ConformanceError(f"{spec.env_id}: {name}: {err}") from err
        except Exception as err:  # the env itself failed: a conformance failure too, named
            first = str(err).strip().splitlines()[0] if str(err).strip() else ""
            raise ConformanceError(f"{spec.env_id}: {name}: the env raised {type(err).__name__}: {first}") from err
    return found


# ---------------------------------------------------------------- helpers
@contextlib.contextmanager
def quiet_torchrl():
    """TorchRL's logger at warnings only, within the block."""
    logger = logging.getLogger("torchrl")
    level = logger.level
    logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        logger.setLevel(level)


def _make(spec: EnvSpec, batch: int, **kwargs: Any) -> FlowEnv:
    return make(spec.env_id, batch, **{**spec.card.test_settings, **kwargs})


def _steps(spec: EnvSpec) -> int:
    """Actions a check runs: a few of a costly env (seconds each), more elsewhere."""
    return 3 if spec.card.costly else 12


def _rollout(env: FlowEnv, actions: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Observations, rewards and terminations along ``actions`` from a reset."""
    env.reset_members()
    out = [env.step_members(a) for a in actions]
    return tuple(torch.stack([o[i] for o in out]) for i in range(3))


def _actions(env: FlowEnv, n: int, seed: int = 0) -> list[torch.Tensor]:
    g = seeds.generator(seed)
    return [env.random_action(g) for _ in range(n)]


def _same(what: str, got: tuple, expected: tuple) -> None:
    """Two rollouts (:func:`_rollout`) agree bit for bit."""
    for part, x, y in zip(("observations", "rewards", "terminations"), got, expected, strict=True):
        _equal(f"{what}: {part}", x, y)


def _equal(what: str, got: torch.Tensor, expected: torch.Tensor) -> None:
    if not torch.equal(got, expected):
        diff = (got.double() - expected.double()).abs().max().item() if got.shape == expected.shape else "shapes differ"
        raise AssertionError(f"{what} differ (largest difference {diff})")


# ---------------------------------------------------------------- the checks
@_check
def check_specs(spec: EnvSpec) -> None:
    from torchrl.data import Bounded, Categorical, Unbounded
    from torchrl.envs.utils import check_env_specs

    for dtype in (torch.float32,) if spec.card.costly else (torch.float32, F64):
        for batch in (1, 4):
            with quiet_torchrl():  # its "check_env_specs succeeded!", once per call
                check_env_specs(_make(spec, batch, dtype=dtype, seed=0), break_when_any_done="both")
    env = _make(spec, 4)
    assert isinstance(env.full_observation_spec[env.observation_key], Unbounded), (
        "the observation spec must be unbounded"
    )
    reward = env.full_reward_spec[env.reward_key]
    assert reward.shape[0] == 4 and reward.shape[-1] == 1 and reward.dtype == env.dtype, (
        f"the reward spec must be [batch, ..., 1] of the env's dtype, got {tuple(reward.shape)} {reward.dtype}"
    )
    action = env.full_action_spec[env.action_key]
    assert action.shape == (4, *env.action_shape), (
        f"action spec shape {tuple(action.shape)}, expected {(4, *env.action_shape)}"
    )
    if env.discrete:
        assert isinstance(action, Categorical) and action.space.n == env.n_actions, (
            "a discrete action spec must be categorical over n_actions"
        )
    else:
        assert isinstance(action, Bounded) and action.space.low.min() == -1 and action.space.high.max() == 1, (
            "a continuous action spec must be bounded in [-1, 1]"
        )
    for key in ("done", "terminated", "truncated"):
        assert env.full_done_spec[key].shape == (4, 1) and env.full_done_spec[key].dtype == torch.bool, (
            f"{key} must be [batch, 1] bool"
        )


@_check
def check_seeding(spec: EnvSpec) -> None:
    a, b = _make(spec, 3, dtype=F64, seed=123), _make(spec, 3, dtype=F64, seed=123)
    actions = _actions(a, _steps(spec), seed=9)
    first = _rollout(a, actions)
    _same("two envs of seed 123", first, _rollout(b, actions))
    a.set_seed(5)
    b.set_seed(5)
    _equal(
        "the generators after set_seed(5)",
        torch.rand(3, generator=a.rng, dtype=F64),
        torch.rand(3, generator=b.rng, dtype=F64),
    )
    a.set_seed(123)
    _same("an episode after set_seed(123) and the first one", _rollout(a, actions), first)


@_check
def check_batch_invariance(spec: EnvSpec) -> str | None:
    if not spec.physics.deterministic:
        return "not applicable: the physics draws from the env's generator, per batch"
    one, three = _make(spec, 1, dtype=F64, seed=0), _make(spec, 3, dtype=F64, seed=0)
    actions = _actions(three, _steps(spec), seed=5)
    alone = _rollout(one, [a[1:2] for a in actions])
    member = tuple(x[:, 1:2] for x in _rollout(three, actions))
    if not spec.card.costly:
        _same("member 1 of 3 and the same member alone", alone, member)
        return None
    for part, x, y in zip(("observations", "rewards", "terminations"), alone, member, strict=True):
        try:
            torch.testing.assert_close(x, y, **ROUND_OFF)
        except AssertionError as err:
            raise AssertionError(
                f"member 1 of 3 and the same member alone: {part} differ beyond round-off: {err}"
            ) from None
    return None


@_check
def check_partial_reset(spec: EnvSpec) -> None:
    env = _make(spec, 4, dtype=F64, seed=1)
    start = env.reset_members().clone()
    like = env.physics.state_like(env.params)
    if like is not None:  # what a state given before a reset is checked against
        fields = lambda state: {k: (tuple(v.shape), v.dtype) for k, v in state._asdict().items()}
        assert fields(like) == fields(env.state), f"state_like gives {fields(like)}, a start {fields(env.state)}"
    for a in _actions(env, 5):
        env.step_members(a)
    before = {k: v.clone() for k, v in env.state._asdict().items()}
    obs_before = env.observation.clone()
    mask = torch.tensor([True, False, True, False])
    obs = env.reset_members(mask)
    for key, value in env.state._asdict().items():
        _equal(f"state.{key} of the members not reset", value[~mask], before[key][~mask])
    _equal("the observations of the members not reset", obs[~mask], obs_before[~mask])
    assert env.step_count.tolist() == [0, 5, 0, 5], f"step counts after the reset: {env.step_count.tolist()}"
    if spec.physics.deterministic:
        _equal("the reset members' observations and the first start's", obs[mask], start[mask])
    assert torch.isfinite(obs).all(), "a reset gave non-finite observations"


@_check
def check_blow_up(spec: EnvSpec) -> None:
    env, ref = _make(spec, 3, dtype=F64, seed=7), _make(spec, 3, dtype=F64, seed=7)
    actions = _actions(env, 1)
    ref_obs, ref_rew, ref_term = _rollout(ref, actions)
    env.reset_members()
    # every number of member 1 absurd: its next step overflows or leaves its bounds
    state = map_state(torch.clone, env.state)
    for v in state:
        if v.is_floating_point():
            v[1] = 1e150
    env.set_state(state)
    obs, reward, terminated, truncated = env.step_members(actions[0])
    assert bool(terminated[1]), "member 1, pushed to 1e150, did not end its episode"
    assert (reward[1] == env.physics.blowup_reward).all(), (
        f"member 1's reward {reward[1].tolist()} is not blowup_reward {env.physics.blowup_reward}"
    )
    assert torch.isfinite(obs).all() and torch.isfinite(reward).all(), "a blown-up member left non-finite values"
    keep = [0, 2]
    assert not terminated[keep].any(), "the other members ended too"
    _equal("the other members' observations", obs[keep], ref_obs[0][keep])
    _equal("the other members' rewards", reward[keep], ref_rew[0][keep])
    # the blown-up member starts again on a reset
    again = env.reset_members(torch.tensor([False, True, False]))
    assert torch.isfinite(again).all() and not env.step_members(actions[0])[2][1], (
        "the member did not start again after its reset"
    )


@_check
def check_gradients(spec: EnvSpec) -> str | None:
    from beacon_torch.gradcheck import check, check_env

    if spec.physics.discrete or spec.card.gradcheck is None:
        return "not applicable: discrete actions"
    case = dataclasses.replace(
        spec.card.gradcheck,
        params={**spec.card.test_settings, **spec.card.gradcheck.params},
        steps=1 if spec.card.costly else spec.card.gradcheck.steps,
    )
    derivatives = dict(check_env(spec.env_id, case))
    defaults = {f.name: f for f in dataclasses.fields(spec.physics.Params)}
    for name, f in defaults.items():
        if not f.metadata.get("differentiable") or name == case.param:
            continue
        value = case.params.get(name, spec.physical_defaults().get(name, f.default))

        def one(**kwargs):
            return make(spec.env_id, 1, dtype=F64, seed=3, **{**case.params, **kwargs})

        try:
            derivatives[name] = check(one, name, float(value), warmup=case.warmup, steps=case.steps)[name]
        except RuntimeError as err:
            if "not have been used in the graph" not in str(err):
                raise
            raise AssertionError(
                f"d(reward)/d({name}): the steps do not use the parameter (read only at set-up or "
                f"at a reset?); declare it differentiable=False"
            ) from None
    for name, d in derivatives.items():
        assert np.isfinite(d.autograd), f"d(reward)/d({name}) is not finite"
        flat = abs(d.central) < 1e-10 and abs(d.autograd) < 1e-10
        assert flat or d.relative_error < GRADIENT_REL, (
            f"d(reward)/d({name}): autograd {d.autograd:.10g}, central differences {d.central:.10g}"
        )
        if name in ("actions", case.param):
            assert not flat, f"d(reward)/d({name}) is zero: the check's direction is flat and checks nothing"
    return None


@_check
def check_compile(spec: EnvSpec) -> None:
    eager = _make(spec, 2, dtype=F64, seed=3)
    compiled = _make(spec, 2, dtype=F64, seed=3, compile=True)
    # a whole episode, but for the cavities (an eager cavity episode takes minutes)
    actions = _actions(eager, 3 if spec.card.costly else spec.physics.episode_length, seed=1)
    for what, c, e in zip(
        ("observations", "rewards", "terminations"), _rollout(compiled, actions), _rollout(eager, actions), strict=True
    ):
        try:
            torch.testing.assert_close(c, e, **ROUND_OFF)
        except AssertionError as err:
            raise AssertionError(f"compiled and eager {what} differ beyond round-off: {err}") from None
    assert compiled.physics.kernels._cache, "the compiled env's step did not go through torch.compile"


@_check
def check_adapters(spec: EnvSpec) -> None:
    from gymnasium.utils.env_checker import check_env

    from beacon_torch.gym import BeaconGymEnv, BeaconVectorEnv, team_reward
    from beacon_torch.sb3 import BeaconVecEnv

    settings = spec.card.test_settings
    single = BeaconGymEnv(spec.env_id, render_mode="rgb_array", compile=False, **settings)
    check_env(single, skip_render_check=False)
    obs, _ = single.reset(seed=3)
    ref = _make(spec, 1, seed=3)
    _equal("the gymnasium env's first observation", torch.as_tensor(obs), ref.reset_members()[0])
    single.action_space.seed(0)
    for _ in range(_steps(spec)):
        action = single.action_space.sample()
        obs, reward, terminated, truncated, _ = single.step(action)
        o, r, t, u = ref.step_members(torch.as_tensor(np.asarray(action))[None])
        _equal("the gymnasium env's observation", torch.as_tensor(obs), o[0])
        assert reward == float(team_reward(ref, r)[0]) and (terminated, truncated) == (bool(t[0]), bool(u[0])), (
            "the gymnasium env's reward or flags differ"
        )
    # the vector envs: float64, so that their rewards compare with the batched env's
    gym_vector = BeaconVectorEnv(spec.env_id, 3, dtype="float64", compile=False, **settings)
    sb3_vector = BeaconVecEnv(spec.env_id, 3, dtype="float64", seed=4, compile=False, **settings)
    for name, venv in (("gymnasium's vector env", gym_vector), ("the Stable-Baselines3 vector env", sb3_vector)):
        batched = _make(spec, 3, dtype=F64, seed=4)
        obs = venv.reset(seed=4)[0] if venv is gym_vector else venv.reset()
        _equal(f"{name}: first observations", torch.as_tensor(obs), batched.reset_members())
        for a in _actions(batched, 3, seed=2):
            out = venv.step(a.numpy())
            o, r, _, _ = batched.step_members(a)
            team = team_reward(batched, r)
            _equal(f"{name}: observations", torch.as_tensor(out[0]), o)
            assert np.allclose(out[1], team.astype(out[1].dtype), rtol=1e-6, atol=0), (
                f"{name}: rewards {out[1]} against {team}"
            )
        venv.close()


@_check
def check_render(spec: EnvSpec) -> None:
    env = _make(spec, 2, record_history=True, seed=0)
    env.reset_members()
    first = env.render()
    assert isinstance(first, np.ndarray) and first.dtype == np.uint8 and first.ndim == 3 and first.shape[2] == 3, (
        "render() must give an RGB uint8 image"
    )
    for a in _actions(env, _steps(spec)):
        env.step_members(a)
    frame = env.render()
    assert frame.shape == first.shape, "frames of one env differ in size"
    assert (frame != first).any(), "the frame did not change over an episode's first actions"
