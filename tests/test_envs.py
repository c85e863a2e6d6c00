"""Behaviour of the batched TorchRL environments that users rely on."""

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical, Unbounded
from torchrl.envs.utils import check_env_specs

import beacon_torch
from beacon_torch import evaluate

from conftest import DETERMINISTIC_ENVS, EXPENSIVE_ENVS, FAST, make, run_actions


@pytest.mark.parametrize("batch_size", [1, 8])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_check_env_specs(env_id, batch_size, dtype):
    if env_id in EXPENSIVE_ENVS and dtype == torch.float64:
        pytest.skip("float32 covers the specs of the 2-D cavities; float64 runs in test_scores.py")
    env = make(env_id, batch_size, dtype=dtype, seed=0)
    check_env_specs(env, break_when_any_done="both")


def test_specs_have_the_documented_types_and_shapes(env_id):
    env = make(env_id, 5)
    obs_spec = env.full_observation_spec[env.observation_key]
    assert isinstance(obs_spec, Unbounded) and math.prod(obs_spec.shape) // 5 == env.n_obs
    reward_spec = env.full_reward_spec[env.reward_key]
    assert reward_spec.shape[0] == 5 and reward_spec.shape[-1] == 1 and reward_spec.dtype == torch.float32
    action_spec = env.full_action_spec[env.action_key]
    assert action_spec.shape == (5, *env.action_shape)
    if env.discrete:
        assert isinstance(action_spec, Categorical) and action_spec.space.n == env.n_actions
    else:
        assert isinstance(action_spec, Bounded)
        assert action_spec.space.low.min() == -1 and action_spec.space.high.max() == 1
    for key in ("done", "terminated", "truncated"):
        assert env.full_done_spec[key].shape == (5, 1)
        assert env.full_done_spec[key].dtype == torch.bool


def test_episode_truncates_at_its_length(cheap_env_id):
    env_id = cheap_env_id
    env = make(env_id, 3)
    r = evaluate.episode(env, evaluate.random_policy(env))
    n = env.episode_length
    assert r.shape == (3, n)
    assert r["next", "truncated"][:, -1].all() and r["next", "done"][:, -1].all()
    assert not r["next", "done"][:, :-1].any()
    assert not r["next", "terminated"].any()
    assert torch.isfinite(r["next", env.observation_key]).all() and torch.isfinite(r["next", env.reward_key]).all()
    assert env.step_count.tolist() == [n] * 3


def test_rollout_keeps_going_with_auto_reset(cheap_env_id):
    env = make(cheap_env_id, 2)
    n = env.episode_length
    torch.manual_seed(0)  # rollout's random actions come from the global generator
    r = env.rollout(n + 3, break_when_any_done=False)
    assert r.shape == (2, n + 3)
    # random actions may blow a member up (sloshing's tank spills now and then): each
    # member counts the steps since its own last end, whichever way that episode ended
    done = r["next", "done"][..., 0]
    assert done[:, n - 1].all() or r["next", "terminated"].any()
    last_end = torch.where(done, torch.arange(n + 3), -1).amax(1)
    assert env.step_count.tolist() == (n + 2 - last_end).tolist()
    # the step after an end starts from the reset observation
    if env.deterministic:
        first = env.reset()[env.observation_key]
        for b, t in done[:, :-1].nonzero().tolist():
            torch.testing.assert_close(r[env.observation_key][b, t + 1], first[b])


def test_partial_reset_resets_only_the_masked_members(env_id):
    env = make(env_id, 4, dtype=torch.float64, seed=1)
    td = env.reset()
    start = td[env.observation_key].clone()
    g = torch.Generator().manual_seed(0)
    for _ in range(7):
        td[env.action_key] = env.random_action(g)
        td = env.step(td)["next"]
    before = {k: v.clone() for k, v in env.state.items()}
    obs_before = td[env.observation_key].clone()
    mask = torch.tensor([True, False, True, False])
    out = env.reset(td.clone().set("_reset", mask[:, None]))
    for k, v in env.state.items():
        torch.testing.assert_close(v[~mask], before[k][~mask], rtol=0, atol=0)
    assert env.step_count.tolist() == [0, 7, 0, 7]
    torch.testing.assert_close(out[env.observation_key][~mask], obs_before[~mask], rtol=0, atol=0)
    torch.testing.assert_close(env.observation[~mask], obs_before[~mask], rtol=0, atol=0)
    if "random_start" in FAST.get(env_id, {}):
        # a new random start: a fresh state, not the one left by the episode
        assert not torch.equal(env.observation[mask], obs_before[mask])
    else:
        torch.testing.assert_close(out[env.observation_key][mask], start[mask], rtol=0, atol=0)
    assert not out["done"].any()


@pytest.mark.parametrize("env_id", DETERMINISTIC_ENVS)
def test_members_are_independent(env_id):
    """A member's trajectory does not depend on what the other members do."""
    env1 = make(env_id, 1, dtype=torch.float64, seed=0)
    env3 = make(env_id, 3, dtype=torch.float64, seed=0)
    g = torch.Generator().manual_seed(5)
    actions3 = [env3.random_action(g) for _ in range(5 if env_id in EXPENSIVE_ENVS else 20)]
    obs3, rew3 = run_actions(env3, actions3)
    obs1, rew1 = run_actions(env1, [a[1:2] for a in actions3])
    torch.testing.assert_close(obs1[0], obs3[1], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(rew1[0], rew3[1], rtol=1e-12, atol=1e-12)


def test_same_seed_same_rollout_and_generator_is_per_instance(cheap_env_id):
    env_id = cheap_env_id
    a = make(env_id, 4, seed=123)
    b = make(env_id, 4, seed=123)
    ra = evaluate.episode(a, evaluate.random_policy(a, seed=9))
    rb = evaluate.episode(b, evaluate.random_policy(b, seed=9))
    assert (ra == rb).all()
    # the env's generator is its own and set_seed re-seeds it
    x = torch.rand(3, generator=a.rng)
    a.set_seed(5)
    b.set_seed(5)
    y = torch.rand(3, generator=a.rng)
    assert torch.equal(y, torch.rand(3, generator=b.rng))
    assert not torch.equal(x, y)
    # and the rollout after a re-seed repeats
    a.set_seed(123)
    rc = evaluate.episode(a, evaluate.random_policy(a, seed=9))
    assert (ra == rc).all()


def test_step_before_reset_is_an_error(env_id):
    env = make(env_id, 2)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(TensorDict({env.action_key: env.null_action()}, batch_size=[2]))


# ---------------------------------------------------------------- bad actions
def _step(env, action):
    env.reset()
    if action.shape[:1] != env.batch_size:
        # a TensorDict of the env's batch cannot even hold such an action; the env's
        # checker still names the expected shape for callers that bypass TensorDicts
        return env.check_action(action)
    return env.step(TensorDict({env.action_key: action}, batch_size=env.batch_size))


@pytest.mark.parametrize(
    "env_id, action, exc, words",
    [
        ("lorenz-v0", torch.tensor([1, 1, 1]), ValueError, ["shape (2,)", "[0, 2]", "(3,)"]),
        ("lorenz-v0", torch.tensor([[1], [1]]), ValueError, ["shape (2,)"]),
        ("lorenz-v0", torch.tensor([1.0, 0.0]), TypeError, ["integer", "float32"]),
        ("lorenz-v0", torch.tensor([True, False]), TypeError, ["integer", "bool"]),
        ("lorenz-v0", torch.tensor([3, 0]), ValueError, ["[0, 2]", "[3, 0]"]),
        ("lorenz-v0", torch.tensor([0, -1]), ValueError, ["[0, 2]"]),
        ("vortex-v0", torch.zeros(2, 3), ValueError, ["(2, 2)", "[-1, 1]", "(2, 3)"]),
        ("vortex-v0", torch.zeros(2), ValueError, ["(2, 2)"]),
        ("vortex-v0", torch.zeros(2, 2, dtype=torch.int64), TypeError, ["floating", "int64"]),
        ("vortex-v0", torch.tensor([[0.0, float("nan")], [0.0, 0.0]]), ValueError, ["NaN", "(2, 2)"]),
        ("lorenz-continuous-v0", torch.tensor([[float("inf")], [0.0]]), ValueError, ["inf", "(2, 1)"]),
        ("burgers-v0", torch.zeros(2, 5), ValueError, ["(2, 1)", "(2, 5)"]),
        ("burgers-v0", torch.zeros(2, 1, dtype=torch.int32), TypeError, ["floating", "int32"]),
        ("sloshing-v0", torch.tensor([[float("nan")], [0.0]]), ValueError, ["NaN", "(2, 1)"]),
        ("shkadov-v0", torch.zeros(2, 4), ValueError, ["(2, 5)", "(2, 4)"]),
        ("shkadov-separable-v0", torch.zeros(2, 5), ValueError, ["(2, 5, 1)", "(2, 5)"]),
        ("shkadov-separable-v0", torch.full((2, 5, 1), float("inf")), ValueError, ["inf"]),
        ("rayleigh-v0", torch.zeros(2, 5), ValueError, ["(2, 10)", "(2, 5)"]),
        ("rayleigh-v0", torch.full((2, 10), float("nan")), ValueError, ["NaN"]),
        ("mixing-v0", torch.tensor([4, 0]), ValueError, ["[0, 3]"]),
        ("mixing-v0", torch.zeros(2, 2), TypeError, ["integer"]),
        ("mixing-continuous-v0", torch.zeros(2, 4), ValueError, ["(2, 2)", "(2, 4)"]),
    ],
)
def test_bad_actions_name_the_expected_shape_and_range(env_id, action, exc, words):
    env = make(env_id, 2)
    with pytest.raises(exc) as info:
        _step(env, action)
    for word in words:
        assert word in str(info.value), (word, str(info.value))


def test_missing_action_is_an_error():
    env = beacon_torch.make("vortex-v0", 2)
    env.reset()
    with pytest.raises(KeyError, match="action"):
        env.step(TensorDict({}, batch_size=[2]))


@pytest.mark.parametrize("env_id", ["vortex-v0", "lorenz-continuous-v0"])
def test_out_of_range_continuous_actions_are_clipped(env_id):
    env = make(env_id, 2, dtype=torch.float64)
    n = env.n_actions
    big = torch.tensor([[5.0] * n, [-7.0] * n], dtype=torch.float64)
    edge = big.clamp(-1, 1)
    obs_big, rew_big = run_actions(env, [big] * 5)
    obs_edge, rew_edge = run_actions(env, [edge] * 5)
    assert torch.equal(obs_big, obs_edge) and torch.equal(rew_big, rew_edge)


def test_other_float_precisions_are_accepted():
    env = beacon_torch.make("vortex-v0", 2, dtype=torch.float32)
    out = _step(env, torch.zeros(2, 2, dtype=torch.float64))
    assert out["next", "observation"].dtype == torch.float32


# ---------------------------------------------------------------- blow-up
# a parameter that makes one member's explicit scheme overflow within a few steps
BLOWUPS = {
    "lorenz-v0": ("rho", 1e6, 60),
    "lorenz-continuous-v0": ("rho", 1e6, 60),
    "burgers-v0": ("amp", 1e8, 5),
    "sloshing-v0": ("amp", 1e6, 5),
    "shkadov-v0": ("amp", 1e8, 5),
    "shkadov-separable-v0": ("amp", 1e8, 5),
}


@pytest.mark.parametrize("env_id", sorted(BLOWUPS))
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_blow_up_ends_that_member_only(env_id, dtype):
    """One member with an extreme parameter blows up: it terminates with the penalty,
    keeps a finite observation, and the others go on bit for bit as in a batch without
    it."""
    name, extreme, steps = BLOWUPS[env_id]
    default = getattr(make(env_id).params, name)[0].item()  # one value per member
    values = [default, default, extreme, default]
    env = make(env_id, 4, dtype=dtype, seed=7, **{name: values})
    ref = make(env_id, 4, dtype=dtype, seed=7)
    g = torch.Generator().manual_seed(0)
    actions = [env.random_action(g) for _ in range(steps)]

    td = env.reset()
    done_at = None
    rewards, obs = [], []
    for i, a in enumerate(actions):
        td[env.action_key] = a
        out = env.step(td)["next"]
        assert torch.isfinite(out[env.observation_key]).all() and torch.isfinite(out[env.reward_key]).all()
        if out["terminated"][2, 0] and done_at is None:
            done_at = i
            assert (out[env.reward_key][2] == env.blowup_reward).all()
            assert out["done"][2, 0]
        assert not out["terminated"][[0, 1, 3]].any()
        rewards.append(out[env.reward_key].clone())
        obs.append(out[env.observation_key].clone())
        td = out
    assert done_at is not None, f"the {name}={extreme:g} member never blew up"

    ref_obs, ref_rew = run_actions(ref, actions)
    keep = [0, 1, 3]
    assert torch.equal(torch.stack(obs, 1)[keep], ref_obs[keep])
    assert torch.equal(torch.stack(rewards, 1)[keep], ref_rew[keep])


def test_blown_member_can_be_reset_and_continue():
    env = beacon_torch.make("lorenz-v0", 2, dtype=torch.float64, rho=[28.0, 1e6])
    r = env.rollout(200, break_when_any_done=False)
    term = r["next", "terminated"][1, :, 0]
    assert term.any()
    assert torch.isfinite(r["next", "observation"]).all()
    # after each termination the rollout reset the member: its next observation is the start
    first = int(term.nonzero()[0])
    torch.testing.assert_close(r["observation"][1, first + 1], r["observation"][1, 0])


# ---------------------------------------------------------------- devices
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_runs_on_cuda(env_id):
    env = make(env_id, 8, device="cuda")
    r = env.rollout(10)
    assert r.device.type == "cuda"
    check_env_specs(env)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_step_has_no_host_device_synchronisation_on_cuda(cheap_env_id):
    """With the action checks off (a trusted training loop), a step never waits for the
    device: no .item(), no boolean indexing, no host-side decision on device values."""
    env = make(cheap_env_id, 8, device="cuda", check_actions=False)
    g = torch.Generator(device="cuda").manual_seed(0)
    td = env.reset()
    td[env.action_key] = env.random_action(g)
    env.step(td)  # first-touch allocations
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(3):  # the env's own step, without TorchRL's bookkeeping around it
            td[env.action_key] = env.random_action(g)
            env._step(td)
    finally:
        torch.cuda.set_sync_debug_mode("default")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_compiled_path_on_cuda():
    eager = make("burgers-v0", 16, device="cuda", dtype=torch.float64, seed=1)
    compiled = make("burgers-v0", 16, device="cuda", dtype=torch.float64, seed=1, compile=True)
    g = torch.Generator(device="cuda").manual_seed(0)
    actions = [eager.random_action(g) for _ in range(3)]
    from conftest import run_actions

    torch.testing.assert_close(run_actions(compiled, actions), run_actions(eager, actions), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize(
    "env_id, params, push",
    [
        # the tank pushed one way spills within a few actions
        ("sloshing-v0", {}, 1.0),
        # the jets cannot spill the film from inside the box at the published amplitude;
        # a thousandfold amplitude does at once
        ("shkadov-v0", {"amp": 1e3, "random_start": 3}, 1.0),
    ],
)
def test_a_blowup_never_pays(env_id, params, push):
    env = beacon_torch.make(env_id, 2, dtype=torch.float64, seed=0, **params)
    constant = torch.full((2, env.n_actions), push, dtype=torch.float64)
    rollout = evaluate.episode(env, lambda td: td.set("action", constant))
    assert rollout["next", "terminated"].any(-2).all(), "no member left the physical bounds"
    blown = evaluate.scores(rollout)
    calm = beacon_torch.make(env_id, 2, dtype=torch.float64, seed=0, **{k: v for k, v in params.items() if k != "amp"})
    uncontrolled = evaluate.scores(evaluate.episode(calm, evaluate.null_policy(calm)))
    assert (blown <= env.blowup_reward).all() and (blown < uncontrolled).all()


def test_every_env_declares_its_card():
    """What benchmarks, reports and tests know of an env comes from its class: a family,
    the published speed and the speed aimed at, the paper's PPO score, a gradient check
    of a differentiable parameter wherever the actions are continuous; a variant is
    measured against its base env, whose card it inherits."""
    import dataclasses
    import math

    from beacon_torch.base import GradCheck

    envs = beacon_torch.registry.ENVS
    assert beacon_torch.registry.base_envs() == ["lorenz-v0", "vortex-v0", "burgers-v0", "sloshing-v0", "shkadov-v0", "rayleigh-v0", "mixing-v0"]
    assert {e: envs[e].base_id() for e in envs if envs[e].base_id() != e} == {
        "lorenz-continuous-v0": "lorenz-v0",
        "shkadov-separable-v0": "shkadov-v0",
        "mixing-continuous-v0": "mixing-v0",
    }
    assert EXPENSIVE_ENVS == {"rayleigh-v0", "mixing-v0", "mixing-continuous-v0"}
    for env_id, cls in envs.items():
        assert cls.family in ("ode", "1-D", "cavity"), env_id
        assert cls.published_speed > 0 and cls.speed_target > 0 and math.isfinite(cls.paper_ppo), env_id
        base = envs[cls.base_id()]
        assert (cls.published_speed, cls.paper_ppo, cls.family) == (base.published_speed, base.paper_ppo, base.family), env_id
        assert (cls.gradcheck is None) == cls.discrete, env_id
        if cls.gradcheck is not None:
            assert isinstance(cls.gradcheck, GradCheck)
            fields = {f.name: f for f in dataclasses.fields(cls.Params)}
            assert fields[cls.gradcheck.param].metadata["differentiable"], env_id
        cls.Params(**cls.test_settings)  # parameters the env knows, in range


def test_an_env_missing_a_physics_hook_is_refused_when_built():
    """The hooks an env must supply are abstract: a class without one cannot be built,
    and the error names what is missing (rather than failing at the first step)."""
    from beacon_torch.envs.burgers import BurgersEnv

    class Incomplete(beacon_torch.base.FlowEnv):
        env_id = "incomplete-v0"
        Params = BurgersEnv.Params
        episode_length = 10
        sizes = BurgersEnv.sizes
        initial_state = BurgersEnv.initial_state
        observe = BurgersEnv.observe

    with pytest.raises(TypeError, match="advance"):
        Incomplete(1)
