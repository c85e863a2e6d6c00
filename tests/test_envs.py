"""Behaviour of the batched TorchRL environments that users rely on."""

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

import beacon_torch
from beacon_torch import episodes
from beacon_torch.core.card import COMPUTED, PAPER_PPO, PHYSICAL_LIMIT, PUBLISHED_RESULT
from beacon_torch.envs.rbc2d import LEVELS as RBC2D_LEVELS

from conftest import EXPENSIVE_ENVS, make, run_actions


def test_episode_truncates_at_its_length(cheap_env_id):
    env_id = cheap_env_id
    env = make(env_id, 3)
    r = episodes.episode(env, episodes.random_policy(env))
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
    if env.physics.deterministic:
        first = env.reset()[env.observation_key]
        for b, t in done[:, :-1].nonzero().tolist():
            torch.testing.assert_close(r[env.observation_key][b, t + 1], first[b])


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
            assert (out[env.reward_key][2] == env.physics.blowup_reward).all()
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
    rollout = episodes.episode(env, lambda td: td.set("action", constant))
    assert rollout["next", "terminated"].any(-2).all(), "no member left the physical bounds"
    blown = episodes.scores(rollout)
    calm = beacon_torch.make(env_id, 2, dtype=torch.float64, seed=0, **{k: v for k, v in params.items() if k != "amp"})
    uncontrolled = episodes.scores(episodes.episode(calm, episodes.null_policy(calm)))
    assert (blown <= env.physics.blowup_reward).all() and (blown < uncontrolled).all()


# where each "= 1" beyond the paper's PPO comes from (None: no reference yet, and the
# protocol refuses the env's scores in one line)
SOURCES = {
    "cylinder-v0": COMPUTED,
    "ks-v0": PHYSICAL_LIMIT,
    "rayleigh-separable-v0": PUBLISHED_RESULT,
    "pinball-periodic-v0": PUBLISHED_RESULT,
    "pinball-v0": None,
    "pinball-chaotic-v0": None,
    # FluidGym's levels: its best result at each level
    **{f"rbc2d-{level}{layout}-v0": PUBLISHED_RESULT for level in RBC2D_LEVELS for layout in ("", "-ma")},
}


def test_every_env_declares_its_card():
    """What benchmarks, reports and tests know of an env comes from its card: a family
    and a cost, the published speed and the speed aimed at where published code is run
    here, a reference score, a gradient check of a differentiable parameter wherever
    the actions are continuous, a frame; a variant is measured against its base env,
    whose card it shares or changes."""
    import dataclasses

    from beacon_torch.core.card import Card, GradCheck

    envs = beacon_torch.registry.ENVS
    assert beacon_torch.registry.base_envs() == [
        "lorenz-v0",
        "vortex-v0",
        "burgers-v0",
        "sloshing-v0",
        "shkadov-v0",
        "rayleigh-v0",
        "mixing-v0",
        "cylinder-v0",
        "ks-v0",
        "pinball-v0",
        "rbc2d-easy-v0",
    ]
    assert {e: envs[e].base_id() for e in envs if envs[e].base_id() != e} == {
        "lorenz-continuous-v0": "lorenz-v0",
        "shkadov-separable-v0": "shkadov-v0",
        "rayleigh-separable-v0": "rayleigh-v0",
        "mixing-continuous-v0": "mixing-v0",
        "pinball-periodic-v0": "pinball-v0",
        "pinball-chaotic-v0": "pinball-v0",
        # the harder levels are the easy one's variants; each layout of agents its level's
        "rbc2d-medium-v0": "rbc2d-easy-v0",
        "rbc2d-hard-v0": "rbc2d-easy-v0",
        "rbc2d-easy-ma-v0": "rbc2d-easy-v0",
        "rbc2d-medium-ma-v0": "rbc2d-medium-v0",
        "rbc2d-hard-ma-v0": "rbc2d-hard-v0",
    }
    assert EXPENSIVE_ENVS == {
        "rayleigh-v0",
        "rayleigh-separable-v0",
        "mixing-v0",
        "mixing-continuous-v0",
        "cylinder-v0",
        "pinball-v0",
        "pinball-periodic-v0",
        "pinball-chaotic-v0",
        "rbc2d-easy-v0",  # the harder levels are outside the behaviour tests' matrix
        "rbc2d-easy-ma-v0",
    }
    # what the gradient-based recipes and their benchmarks cover
    assert beacon_torch.registry.continuous_envs() == [
        "lorenz-continuous-v0",
        "vortex-v0",
        "burgers-v0",
        "sloshing-v0",
        "shkadov-v0",
        "rayleigh-v0",
        "mixing-continuous-v0",
        "cylinder-v0",
        "ks-v0",
        "pinball-v0",
        "pinball-periodic-v0",
        "pinball-chaotic-v0",
        "rbc2d-easy-v0",
        "rbc2d-medium-v0",
        "rbc2d-hard-v0",
    ]
    for env_id, spec in envs.items():
        assert isinstance(spec.card, Card) and callable(spec.card.frame), env_id
        assert spec.card.family in ("ode", "1-D", "2-D"), env_id
        assert spec.card.costly == (spec.card.family == "2-D"), env_id  # of these envs, the 2-D flows
        # beyond BEACON and on the cylinder (no paper's PPO for its set-up), no "= 1" is
        # a PPO score of the paper
        beyond = spec.env_id in ("ks-v0", "rayleigh-separable-v0") or spec.base_id() == "pinball-v0"
        beyond = beyond or spec.env_id.startswith("rbc2d-")
        no_paper = beyond or spec.base_id() == "cylinder-v0"
        assert spec.card.paper_ppo is None if no_paper else math.isfinite(spec.card.paper_ppo), env_id
        source = None if spec.card.scale_reference() is None else spec.card.scale_reference().source
        assert source == SOURCES.get(spec.env_id, PAPER_PPO), env_id
        if beyond or spec.base_id() == "cylinder-v0":  # no published code run here
            assert spec.card.published_speed is None and spec.card.speed_target is None
        else:
            assert spec.card.published_speed > 0 and spec.card.speed_target > 0, env_id
        base = envs[spec.base_id()]
        # a variant is measured against its base's card; Vignon's channel is a case of
        # its own on rayleigh's solver
        card = (
            (base.card.published_speed, base.card.paper_ppo) if spec.env_id != "rayleigh-separable-v0" else (None, None)
        )
        assert (spec.card.published_speed, spec.card.paper_ppo, spec.card.family, spec.card.costly) == (
            *card,
            base.card.family,
            base.card.costly,
        ) or (spec is base), env_id
        assert (spec.card.gradcheck is None) == spec.physics.discrete, env_id
        if spec.card.gradcheck is not None:
            assert isinstance(spec.card.gradcheck, GradCheck)
            fields = {f.name: f for f in dataclasses.fields(spec.physics.Params)}
            assert fields[spec.card.gradcheck.param].metadata["differentiable"], env_id
        spec.physics.Params(**spec.card.test_settings)  # parameters the env knows, in range


def test_a_physics_missing_a_hook_is_refused_when_built():
    """The hooks a physics must supply are abstract: an env of a physics without one
    cannot be built, and the error names what is missing (rather than failing at the
    first step)."""
    from beacon_torch.envs.burgers import BurgersPhysics

    class Incomplete(beacon_torch.Physics):
        Params = BurgersPhysics.Params
        state_type = BurgersPhysics.state_type
        episode_length = 10
        sizes = BurgersPhysics.sizes
        initial_state = BurgersPhysics.initial_state
        observe = BurgersPhysics.observe

    with pytest.raises(TypeError, match="advance"):
        beacon_torch.base.FlowEnv(beacon_torch.registry.EnvSpec("incomplete-v0", Incomplete), 1)


def test_register_takes_a_physics_and_says_so_of_anything_else():
    """A case is its physics: register refuses an env class, a physics without a state
    type or a card that is not one, in one line naming what it takes."""
    from beacon_torch.envs.lorenz import LorenzPhysics

    with pytest.raises(TypeError, match="register needs a beacon_torch.Physics subclass or a registered EnvSpec"):
        beacon_torch.register("old-v0", beacon_torch.base.FlowEnv)

    class Stateless(LorenzPhysics):
        state_type = None

    with pytest.raises(TypeError, match="declares no state type"):
        beacon_torch.register("stateless-v0", Stateless)
    with pytest.raises(TypeError, match="card must be a beacon_torch.core.card.Card"):
        beacon_torch.register("carded-v0", LorenzPhysics, {"paper_ppo": 1.0})
    assert not {"old-v0", "stateless-v0", "carded-v0"} & set(beacon_torch.list_envs())


def test_a_physics_subclass_may_shorten_the_episode():
    """A physics that says ``episode_length = 3`` is truncated after 3 actions, with its
    own blow-up reward, and leaves its base physics as it was."""
    from beacon_torch.envs.lorenz import CARD, LorenzPhysics

    class Short(LorenzPhysics):
        episode_length = 3
        blowup_reward = -7.0

    env = beacon_torch.base.FlowEnv(beacon_torch.registry.EnvSpec("three-lorenz-v0", Short, CARD), 2)
    assert LorenzPhysics.episode_length == 500 and env.episode_length == 3
    env.reset()
    flags = [env.step_members(env.null_action())[3].tolist() for _ in range(3)]
    assert flags == [[False, False], [False, False], [True, True]] and env.physics.blowup_reward == -7.0


def test_an_env_registered_from_outside_the_package_is_not_among_its_continuous_envs(monkeypatch):
    from beacon_torch import registry
    from beacon_torch.envs.burgers import BurgersPhysics

    monkeypatch.setitem(registry.ENVS, "my-burgers-v0", registry.EnvSpec("my-burgers-v0", BurgersPhysics))
    monkeypatch.setitem(registry.ORIGIN, "my-burgers-v0", "my_envs.burgers")
    assert "my-burgers-v0" in registry.list_envs() and "my-burgers-v0" not in registry.continuous_envs()
