"""Differentiable mode: exact gradients of the rewards through every continuous solver.

The gradients of the reward summed over a few steps, with respect to the action
sequence and to one physical parameter per env, are compared with central differences
in float64 at generic points (a state reached by random actions, random actions away
from the box's edges, so that no limiter, max or abs sits on its kink).
"""

import dataclasses

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

import beacon_torch
from beacon_torch.gradcheck import generic_start, summed_reward

from conftest import ENVS

F64 = torch.float64
REL = 1e-5


def relative(a, b):
    return float(abs(a - b) / abs(b))


def test_gradient_with_respect_to_the_initial_state():
    env = beacon_torch.make("lorenz-continuous-v0", dtype=F64, differentiable=True, reward_width=2.0)
    start = generic_start(env, 10)
    xyz = start.xyz.clone().requires_grad_()
    actions = torch.zeros((15, 1, 1), dtype=F64)
    total = summed_reward(env, start._replace(xyz=xyz), actions)
    (grad,) = torch.autograd.grad(total, xyz)
    direction = torch.tensor([[0.3, -1.0, 0.5]], dtype=F64)
    h = 1e-6
    with torch.no_grad():
        plus = summed_reward(env, start._replace(xyz=start.xyz + h * direction), actions)
        minus = summed_reward(env, start._replace(xyz=start.xyz - h * direction), actions)
    assert relative((grad * direction).sum(), (plus - minus) / (2 * h)) < REL


def test_a_rollout_from_a_state_given_to_set_state():
    """rollout resets first, which drops the state given to set_state and its gradient:
    said by a warning; auto_reset=False from env.current() keeps it."""
    import warnings

    env = beacon_torch.make("lorenz-continuous-v0", dtype=F64, differentiable=True, reward_width=2.0)
    start = generic_start(env, 10)
    xyz = start.xyz.clone().requires_grad_()
    env.set_state(start._replace(xyz=xyz))
    with pytest.warns(UserWarning, match="auto_reset=False, tensordict=env.current()"):
        env.rollout(3)
    env.set_state(start._replace(xyz=xyz))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rollout = env.rollout(15, auto_reset=False, tensordict=env.current())
    (grad,) = torch.autograd.grad(rollout["next", "reward"].sum(), xyz)
    assert grad.abs().sum() > 0
    env.set_state(start)  # no graph to lose: no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env.rollout(2)


@pytest.mark.parametrize(
    "env_id, name",
    [
        ("rbc2d-easy-v0", "ra"),
        ("rayleigh-v0", "ra"),
        ("cylinder-v0", "nu"),
        ("pinball-v0", "re"),
        ("shkadov-v0", "delta"),
    ],
)
def test_a_state_given_at_other_parameters_develops_no_start(env_id, name, monkeypatch):
    """Central differences in a parameter step an env made at a nearby value from a
    state given to set_state: the env takes it and steps without developing a start of
    its own (minutes for a developed flow at a value no file holds)."""
    settings = beacon_torch.registry.env_spec(env_id).card.test_settings
    source = beacon_torch.make(env_id, 2, dtype=F64, **settings)
    source.reset()
    value = getattr(source.params, name) * (1 + 1e-6)
    env = beacon_torch.make(env_id, 2, dtype=F64, **settings, **{name: value})

    def refuse(*args, **kwargs):
        raise AssertionError("the env computed a start")

    monkeypatch.setattr(env.physics, "initial_state", refuse)
    env.set_state(source.state)
    first = source.state._fields[0]
    with pytest.raises(ValueError, match=f"state.{first}"):
        env.set_state(source.state._replace(**{first: source.state[0][:, 1:]}))
    _, reward, terminated, _ = env.step_members(env.physics.null_action())
    assert torch.isfinite(reward).all() and not terminated.any()


def rollout_gradient(checkpoint, steps=12):
    env = beacon_torch.make(
        "burgers-v0", batch_size=3, dtype=F64, seed=2, differentiable=True, grad_checkpoint=checkpoint
    )
    env.reset()
    actions = (0.5 * torch.rand((steps, 3, 1), generator=torch.Generator().manual_seed(0), dtype=F64)).requires_grad_()
    saved = {}

    def pack(t):
        saved[t.untyped_storage().data_ptr()] = t.untyped_storage().nbytes()
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        total = 0.0
        for a in actions:
            total = total + env.step(TensorDict({"action": a}, batch_size=[3]))["next", "reward"].sum()
    total.backward()
    return actions.grad, sum(saved.values()), torch.rand(4, generator=env.rng, dtype=F64)


@pytest.mark.slow(seconds=20)
@pytest.mark.parametrize("keep", [0, None], ids=["trimmed-each-action", "trimmed-past-the-bound"])
def test_a_checkpointed_episode_holds_little_resident_memory_per_action(monkeypatch, keep):
    """What each recomputable action frees goes back to the system once the C library
    holds more than its bound free. Bound to nothing, the resident memory of a
    checkpointed rollout of the 2-D cylinder grows by far less than an action's graph,
    and its backward pass leaves about 10 MB (about 150 MB of free heap untrimmed);
    with the default bound it grows by at most that bound."""
    from beacon_torch import autograd

    if keep is not None:
        monkeypatch.setattr(autograd, "KEEP_FREE", keep)
    bound_mb = autograd.KEEP_FREE / 2**20

    def resident_mb() -> float:
        return int(open("/proc/self/status").read().split("VmRSS:")[1].split()[0]) / 1024

    env = beacon_torch.make("cylinder-v0", 2, differentiable=True, grad_checkpoint=True)
    td = env.reset()
    action = torch.zeros(2, 2, requires_grad=True)
    td = env.step(td.set("action", action.tanh()))["next"]  # the first action's allocations
    total = td["reward"].sum()
    autograd.release_free_memory(keep=0)
    before = resident_mb()
    actions = 4 if keep == 0 else 10
    for k in range(actions):
        td = env.step(td.set("action", (action + 0.1 * k).tanh()))["next"]
        total = total + td["reward"].sum()
    forward = resident_mb() - before
    # the backward pass recomputes each action, a graph of about 350 MB, in turn
    total.backward()
    backward = resident_mb() - before
    assert action.grad.abs().sum() > 0
    said = f"{forward:.0f} MB over {actions} actions, {backward:.0f} MB after backward"
    if keep == 0:
        assert forward < 15.0 * actions and backward < 80.0, said
    else:
        assert forward < bound_mb and backward < bound_mb + 300.0, said
    free = autograd.free_heap_bytes()
    if free is not None:
        assert free <= autograd.KEEP_FREE + 400 * 2**20, f"{free / 2**20:.0f} MB free in the heap"


def test_checkpointing_gives_the_same_gradient_in_a_fraction_of_the_memory():
    grad, memory, after = rollout_gradient(False)
    grad_ck, memory_ck, after_ck = rollout_gradient(True)
    # the backward pass recomputes each action with the noise the step drew ...
    assert torch.equal(grad, grad_ck)
    # ... and leaves the env's generator where the episode had taken it
    assert torch.equal(after, after_ck)
    # without checkpointing burgers' action in C keeps its 62 substeps' states, 0.25 MB
    # per member and action in float64 (the slices' graph kept about 1 MiB); with it,
    # the state an action starts from
    states = 62 * 500 * 8 * 3 * 12
    assert states <= memory < 1.2 * states
    assert memory_ck < memory / 10


def graph_nodes(t: torch.Tensor, cap: int = 20_000) -> int:
    """The autograd nodes that ``t``'s backward pass would visit (at most ``cap``)."""
    seen, todo = set(), [t.grad_fn]
    while todo and len(seen) < cap:
        node = todo.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        todo.extend(n for n, _ in node.next_functions)
    return len(seen)


def test_a_checkpointed_action_runs_its_first_pass_without_a_graph_and_keeps_every_gradient():
    """rayleigh-v0, two actions: recomputed in the backward pass, an action records no
    graph of its substeps on the way forward (a few nodes an action, against tens of
    thousands kept whole where autograd records the substeps, without their adjoint
    written out), and the gradients with respect to the actions, and to a Rayleigh
    number that requires grad (which the parameters carry, out of the step's tensor
    inputs: torch's own checkpoint then), are those of the graph kept whole."""

    def run(checkpoint: bool, ra=None, recorded: bool = True):
        params = {} if ra is None else {"ra": ra}
        env = beacon_torch.make("rayleigh-v0", 2, dtype=F64, differentiable=True, grad_checkpoint=checkpoint, **params)
        if recorded:
            env.physics.stored = None
        env.reset()
        action = torch.full((2, *env.action_spec.shape[1:]), 0.3, dtype=F64, requires_grad=True)
        total = 0.0
        for k in range(2):
            td = env.step(TensorDict({"action": (action * (k + 1)).tanh()}, batch_size=env.batch_size))
            total = total + td["next", "reward"].sum()
        wanted = (action,) if ra is None else (action, ra)
        return graph_nodes(total), torch.autograd.grad(total, wanted)

    kept, (whole,) = run(False)
    few, (recomputed,) = run(True)
    torch.testing.assert_close(recomputed, whole, rtol=1e-12, atol=1e-14)
    assert whole.abs().sum() > 0 and few < 500 < 20_000 <= kept
    ra = lambda: torch.tensor(1e4, dtype=F64, requires_grad=True)
    _, whole = run(False, ra())
    _, recomputed = run(True, ra())
    for got, want in zip(recomputed, whole, strict=True):
        assert want.abs().sum() > 0
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-14)


def test_the_first_actions_after_a_cut_keep_their_graphs_whole_and_the_later_ones_are_recomputed():
    """``grad_checkpoint_after=N``: of the actions since the graph was last cut, the
    first N keep their substeps' graphs, the later ones record a few nodes and are
    recomputed in the backward pass; detach_state and a reset of every member start the
    count again; the gradients are the graph's kept whole."""

    def run(after: int | None, actions: int = 3):
        checkpoint = after is not None
        env = beacon_torch.make(
            "vortex-v0", 2, dtype=F64, differentiable=True, grad_checkpoint=checkpoint, grad_checkpoint_after=after or 0
        )
        env.reset()
        action = torch.full((2, 2), 0.3, dtype=F64, requires_grad=True)
        total, sizes = 0.0, []
        for k in range(actions):
            reward = env.step(TensorDict({"action": (action * (k + 1)).tanh()}, batch_size=env.batch_size))
            total = total + reward["next", "reward"].sum()
            sizes.append(graph_nodes(total))
        return env, sizes, torch.autograd.grad(total, action)[0]

    _, whole_sizes, whole = run(None)
    for after in (0, 1, 2, 3):
        env, sizes, grad = run(after)
        torch.testing.assert_close(grad, whole, rtol=1e-12, atol=1e-14)
        assert sizes[:after] == whole_sizes[:after]
        # a recomputed action adds a few nodes, one kept whole its substeps' graph
        added = [b - a for a, b in zip([0, *sizes], sizes, strict=False)]
        assert all(n < 50 for n in added[after:]) and all(n > 100 for n in added[:after])
        for cut in (env.detach_state, env.reset):
            cut()
            action = torch.zeros((2, 2), dtype=F64, requires_grad=True)
            reward = env.step(TensorDict({"action": action}, batch_size=env.batch_size))["next", "reward"]
            assert (graph_nodes(reward.sum()) > 100) == (after > 0)
    with pytest.raises(ValueError, match="grad_checkpoint_after needs grad_checkpoint=True"):
        beacon_torch.make("vortex-v0", differentiable=True, grad_checkpoint_after=2)
    with pytest.raises(TypeError, match="grad_checkpoint_after must be a non-negative integer"):
        beacon_torch.make("vortex-v0", differentiable=True, grad_checkpoint=True, grad_checkpoint_after=1.5)


def test_detach_state_truncates_backpropagation():
    env = beacon_torch.make("vortex-v0", dtype=F64, differentiable=True)
    env.reset()
    first = torch.zeros((1, 2), dtype=F64, requires_grad=True)
    env.step(TensorDict({"action": first}, batch_size=[1]))
    env.detach_state()
    td = env.step(TensorDict({"action": torch.zeros((1, 2), dtype=F64)}, batch_size=[1]))
    assert not td["next", "reward"].requires_grad
    assert not env.state.ay.requires_grad


def test_default_mode_keeps_no_graph():
    theta = torch.tensor(0.5, requires_grad=True)
    with pytest.warns(UserWarning, match="require grad but the env is not differentiable"):
        env = beacon_torch.make("burgers-v0", num_envs=2, u_target=theta)
    env.reset()
    action = torch.zeros((2, 1), requires_grad=True)
    with pytest.warns(UserWarning, match="gradient is dropped"):
        td = env.step(TensorDict({"action": action}, batch_size=[2]))
    assert not td["next", "reward"].requires_grad
    assert not td["next", "observation"].requires_grad


def test_policy_gradient_through_a_torchrl_rollout():
    env = beacon_torch.make("sloshing-v0", num_envs=2, seed=0, differentiable=True)
    net = torch.nn.Sequential(torch.nn.Linear(env.n_obs, 8), torch.nn.Tanh(), torch.nn.Linear(8, 1), torch.nn.Tanh())
    td = env.rollout(5, TensorDictModule(net, ["observation"], ["action"]))
    td["next", "reward"].sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in net.parameters())


def test_per_member_parameter_gets_per_member_gradients():
    g = torch.tensor([9.0, 9.81, 11.0], dtype=F64, requires_grad=True)
    env = beacon_torch.make("sloshing-v0", num_envs=3, dtype=F64, differentiable=True, g=g)
    env.reset()
    actions = torch.full((3, 3, 1), 0.2, dtype=F64)
    summed = 0.0
    for a in actions:
        summed = summed + env.step(TensorDict({"action": a}, batch_size=[3]))["next", "reward"]
    # member i's reward depends on g[i] only
    (jac,) = torch.autograd.grad(summed[1, 0], g)
    assert jac[1] != 0 and jac[0] == 0 and jac[2] == 0


def test_lorenz_smooth_reward_tends_to_the_indicator():
    x = torch.tensor([-1.0, -0.1, 0.1, 1.0], dtype=F64)
    sharp = beacon_torch.make("lorenz-continuous-v0", dtype=F64, reward_width=1e-3)
    assert torch.allclose(sharp.physics.reward(sharp.params, x), torch.tensor([1.0, 1.0, 0.0, 0.0], dtype=F64))
    indicator = beacon_torch.make("lorenz-continuous-v0")
    assert torch.equal(indicator.physics.reward(indicator.params, x.float()), torch.tensor([1.0, 1.0, 0.0, 0.0]))


def test_lorenz_straight_through_reward_is_worth_the_indicator_with_the_smooth_gradient():
    """reward_value="indicator": a rollout scores exactly the published reward and its
    gradient is the smooth reward's."""
    actions = torch.linspace(-0.8, 0.8, 40, dtype=F64).reshape(40, 1, 1)
    runs = {}
    for name, params in {
        "published": {},
        "smooth": dict(reward_width=1.0),
        "straight": dict(reward_width=1.0, reward_value="indicator"),
    }.items():
        env = beacon_torch.make("lorenz-continuous-v0", dtype=F64, differentiable=True, **params)
        start = generic_start(env, 10)
        taken = actions.clone().requires_grad_()
        rewards = []
        env.set_state(start)
        for a in taken:
            rewards.append(env.step(TensorDict({"action": a}, batch_size=[1]))["next", "reward"])
        rewards = torch.cat(rewards)
        grad = torch.autograd.grad(rewards.sum(), taken, allow_unused=True)[0] if rewards.requires_grad else None
        runs[name] = rewards.detach(), grad
    assert torch.equal(runs["straight"][0], runs["published"][0])
    assert not torch.equal(runs["smooth"][0], runs["published"][0])
    assert runs["straight"][1].abs().sum() > 0
    assert torch.allclose(runs["straight"][1], runs["smooth"][1], rtol=1e-12, atol=0)


def test_errors_name_the_problem():
    with pytest.raises(TypeError, match="'L' cannot be differentiated"):
        beacon_torch.make("burgers-v0", L=torch.tensor(2.0, requires_grad=True))
    with pytest.raises(ValueError, match="'re' must be in"):
        beacon_torch.make("vortex-v0", re=torch.tensor(-1.0, requires_grad=True))
    with pytest.raises(ValueError, match=r"shape \(2,\)"):
        beacon_torch.make("vortex-v0", num_envs=2, re=torch.ones(3, requires_grad=True))
    with pytest.raises(ValueError, match="needs differentiable=True"):
        beacon_torch.make("vortex-v0", grad_checkpoint=True)
    env = beacon_torch.make("vortex-v0", num_envs=2)
    env.reset()
    with pytest.raises(KeyError, match="missing \\['k'"):
        env.set_state({k: v for k, v in env.state._asdict().items() if k != "k"})
    with pytest.raises(ValueError, match=r"state.ay must have shape \(2, 4\)"):
        env.set_state({**env.state._asdict(), "ay": torch.zeros(2, 3)})


def test_partial_reset_keeps_the_graph_of_the_members_that_go_on():
    env = beacon_torch.make("vortex-v0", num_envs=2, dtype=F64, differentiable=True)
    env.reset()
    first = torch.full((2, 2), 0.3, dtype=F64, requires_grad=True)
    env.step(TensorDict({"action": first}, batch_size=[2]))
    env.reset(TensorDict({"_reset": torch.tensor([[True], [False]])}, batch_size=[2]))
    td = env.step(TensorDict({"action": torch.full((2, 2), 0.3, dtype=F64)}, batch_size=[2]))
    (grad,) = torch.autograd.grad(td["next", "reward"].sum(), first)
    # member 0 started again from data; member 1's reward still depends on its first action
    assert torch.all(grad[0] == 0) and torch.any(grad[1] != 0)


# env: (warm-up actions, differentiated actions, settings); burgers' inlet noise needs
# about 40 actions to reach the reward region, so sigma's derivative needs that many
REACH = {
    "lorenz-continuous-v0": (5, 2, {"reward_width": 1.0}),
    "vortex-v0": (5, 2, {}),
    "burgers-v0": (0, 45, {}),
    "sloshing-v0": (2, 2, {}),
    "shkadov-v0": (1, 2, {"random_start": 0}),
    "shkadov-separable-v0": (1, 2, {"random_start": 0}),
    "rayleigh-v0": (0, 1, {}),
    "rayleigh-separable-v0": (0, 1, ENVS["rayleigh-separable-v0"].card.test_settings),
    "mixing-continuous-v0": (0, 1, ENVS["mixing-continuous-v0"].card.test_settings),
    "cylinder-v0": (0, 1, ENVS["cylinder-v0"].card.test_settings),
    "ks-v0": (2, 2, {}),
    "pinball-v0": (0, 1, ENVS["pinball-v0"].card.test_settings),
    "pinball-periodic-v0": (0, 1, ENVS["pinball-periodic-v0"].card.test_settings),
    "pinball-chaotic-v0": (0, 1, ENVS["pinball-chaotic-v0"].card.test_settings),
    **{e: (0, 1, ENVS[e].card.test_settings) for e in ENVS if e.startswith("rbc2d-")},
}
DIFFERENTIABLE = [
    (env_id, f.name)
    for env_id, cls in beacon_torch.registry.ENVS.items()
    if not cls.physics.discrete
    for f in dataclasses.fields(cls.physics.Params)
    if f.metadata["differentiable"]
]


@pytest.mark.parametrize("env_id, name", DIFFERENTIABLE)
def test_every_differentiable_parameter_reaches_the_rewards(env_id, name):
    """A parameter that the physics read only when the env was built (under no_grad)
    would get a silent zero gradient: each one declared differentiable must not."""
    warmup, steps, settings = REACH[env_id]
    spec = beacon_torch.registry.ENVS[env_id]
    default = spec.physical_defaults().get(
        name, next(f.default for f in dataclasses.fields(spec.physics.Params) if f.name == name)
    )
    theta = torch.tensor(float(settings.get(name, default)), dtype=F64, requires_grad=True)
    env = beacon_torch.make(env_id, dtype=F64, seed=0, differentiable=True, **{**settings, name: theta})
    start = generic_start(env, warmup)
    actions = torch.full((steps, *env.full_action_spec[env.action_key].shape), 0.2, dtype=F64)
    (grad,) = torch.autograd.grad(summed_reward(env, start, actions), theta)
    assert torch.isfinite(grad) and grad != 0
