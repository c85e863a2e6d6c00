"""The compiled path: ``make(..., compile=True)`` runs the substeps through
``torch.compile`` and follows the eager trajectories."""

import pytest
import torch
from torch._dynamo.utils import counters

import beacon_torch

from conftest import ALL_ENVS, EXPENSIVE_ENVS, make, run_actions

# The cavities' actions are hundreds of substeps of tens of milliseconds eagerly: a few
# actions there (every action is the same compiled call); whole episodes elsewhere
ACTIONS = {"rayleigh-v0": 3, "mixing-v0": 3, "mixing-continuous-v0": 3}
# Where the compiled graph fuses or reorders floating-point operations (a sum, a
# division folded into a product), the trajectories differ by round-off: at most this
# much over a whole float64 episode (measured: 0 for lorenz, burgers and vortex,
# below 1e-13 elsewhere)
ROUND_OFF = dict(rtol=1e-10, atol=1e-12)


@pytest.mark.slow(seconds=20)
@pytest.mark.parametrize("env_id", [e for e in ALL_ENVS if e not in EXPENSIVE_ENVS])
def test_one_compiled_call_per_action(env_id):
    """Compiled, a step is one call of compiled code: the substeps, their noise and
    interpolated actions, the reward, the observation and the bookkeeping."""
    env = make(env_id, 1, compile=True, seed=0)
    g = torch.Generator().manual_seed(0)
    env.reset_members()
    env.step_members(env.random_action(g))  # compiles
    calls = []
    for fn, compiled in list(env.physics.kernels._cache.items()):
        env.physics.kernels._cache[fn] = lambda *a, _c=compiled, **k: calls.append(1) or _c(*a, **k)
    for _ in range(5):
        env.step_members(env.random_action(g))
    assert len(calls) == 5


@pytest.mark.slow(seconds=30)
@pytest.mark.parametrize("env_id", ["lorenz-v0", "burgers-v0", "sloshing-v0", "mixing-v0"])
def test_the_second_step_does_not_recompile(env_id):
    """A start's views (a member of size one, a slice, an observation that is a view
    of the state) and shared zeros are given standard strides and memory of their
    own, as the steps leave them: the compiled step is specialised once."""
    for batch in (1,) if env_id in EXPENSIVE_ENVS else (1, 16):
        env = make(env_id, batch, compile=True)
        g = torch.Generator().manual_seed(0)
        env.reset_members()
        env.step_members(env.random_action(g))
        graphs = counters["stats"]["unique_graphs"]
        for _ in range(3):
            env.step_members(env.random_action(g))
        env.reset_members(torch.ones(batch, dtype=torch.bool))
        env.step_members(env.random_action(g))
        assert counters["stats"]["unique_graphs"] == graphs


def test_adapters_compile_unless_told_not_to(monkeypatch):
    """The fast path is the default where single-env users meet it: gymnasium's
    ``make`` and ``make_vec`` and Stable-Baselines3's vector env."""
    import gymnasium

    import beacon_torch.gym  # noqa: F401
    from beacon_torch.sb3 import BeaconVecEnv

    monkeypatch.delenv("BEACON_TORCH_COMPILE", raising=False)
    made = [
        gymnasium.make("beacon/lorenz-v0").unwrapped.env,
        gymnasium.make_vec("beacon/lorenz-v0", num_envs=2).env,
        BeaconVecEnv("lorenz-v0", 2).env,
    ]
    assert all(env.physics.kernels.options is not None for env in made)
    assert gymnasium.make("beacon/lorenz-v0", compile=False).unwrapped.env.physics.kernels.options is None
    monkeypatch.setenv("BEACON_TORCH_COMPILE", "0")
    assert BeaconVecEnv("lorenz-v0", 2).env.physics.kernels.options is None


def test_compilation_happens_once_not_per_step():
    env = make("burgers-v0", 4, compile=True)
    g = torch.Generator().manual_seed(0)
    # the start's tensors may have other strides than the stepped ones: the step's
    # bookkeeping compiles for each layout once
    run_actions(env, [env.random_action(g) for _ in range(2)])
    graphs = counters["stats"]["unique_graphs"]
    run_actions(env, [env.random_action(g) for _ in range(5)])
    # a second instance of the same shapes reuses the compiled code
    run_actions(make("burgers-v0", 4, compile=True), [env.random_action(g)])
    assert counters["stats"]["unique_graphs"] == graphs


def test_a_differentiated_loop_compiles_its_substep_once_whatever_its_length():
    """A loop recorded by autograd runs its compiled substep once per index; a substep
    that reads per-substep values (``at``: the interpolated actions, the inlet noise)
    compiles once for every index, not once per index (70 substeps, past the recompile
    limit), and differentiates as the eager loop does."""
    from beacon_torch.compiled import RECOMPILE_LIMIT, Kernels, at

    def substep(i, carried, weights):
        (x,) = carried
        return (torch.sin(x) * at(weights, i) + x,)

    n = RECOMPILE_LIMIT + 6
    weights = torch.linspace(0.0, 1.0, n, dtype=torch.float64)
    grads = []
    for compiled in (False, True):
        kernels = Kernels()
        if compiled:
            kernels.compile()
        loop = kernels.loop(substep)
        x = torch.linspace(-1.0, 1.0, 5, dtype=torch.float64, requires_grad=True)
        before = counters["stats"]["unique_graphs"]
        (y,) = loop(n, (x,), weights)
        (grad,) = torch.autograd.grad(y.sum(), x)
        grads.append(grad)
        if compiled:
            assert counters["stats"]["unique_graphs"] - before <= 2  # the substep, and its backward
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-12, atol=0.0)


def test_compile_accepts_torch_compile_options_and_rejects_nonsense():
    env = beacon_torch.make("lorenz-v0", 2, compile={"mode": "default"})
    assert env.physics.kernels.options["mode"] == "default" and env.physics.kernels.options["fullgraph"]
    with pytest.raises(TypeError, match="compile"):
        beacon_torch.make("lorenz-v0", 2, compile="yes")


def test_compiled_env_rolls_out_through_torchrl():
    env = make("vortex-v0", 8, compile=True)
    td = env.rollout(4)
    assert td.batch_size == (8, 4) and torch.isfinite(td["next", "reward"]).all()


def test_compiled_envs_leave_dynamo_settings_as_they_found_them():
    """The recompile limit is raised and loops are let into torch's graph caches while a
    kernel runs, so that many env shapes keep their compiled code and a new process
    finds it, and both are restored after: an env changes no process-wide setting."""
    import torch._dynamo
    from torch._higher_order_ops.while_loop import while_loop_op

    before = torch._dynamo.config.recompile_limit, while_loop_op.cacheable()
    env = make("lorenz-v0", 3, compile=True)
    seen = []
    env.physics.kernels._cache.clear()
    kernel = env.physics.kernels(
        lambda x: seen.append((torch._dynamo.config.recompile_limit, while_loop_op._cacheable)) or x * 2
    )
    assert torch.equal(kernel(torch.ones(2)), 2 * torch.ones(2))
    run_actions(env, [env.null_action()])
    assert seen and seen[0][0] >= 64 and seen[0][1]  # traced while the settings held
    assert (torch._dynamo.config.recompile_limit, while_loop_op.cacheable()) == before == (before[0], False)


# run twice in one fresh compile cache: two loops that differ only in their bodies, and
# a few float64 burgers steps, compiled
CACHED = """
import json, sys, torch
import beacon_torch
from beacon_torch.compiled import Kernels
from torch._dynamo.utils import counters

kernels = Kernels()
kernels.compile()
loops = [kernels.loop(lambda i, x: x * 2.0 + 1.0), kernels.loop(lambda i, x: x * 3.0 - 1.0)]
toy = [loop(5, torch.ones(3, dtype=torch.float64)).tolist() for loop in loops]
env = beacon_torch.make("burgers-v0", 2, dtype=torch.float64, seed=3, compile=True)
env.reset_members()
g = torch.Generator().manual_seed(1)
obs = [env.step_members(env.random_action(g))[0].tolist() for _ in range(3)]
json.dump({"toy": toy, "obs": obs, "counters": dict(counters["inductor"])}, sys.stdout)
"""


@pytest.mark.slow(seconds=40)
def test_a_new_process_finds_the_compiled_step_in_the_cache_and_the_same_trajectory(tmp_path):
    """Torch caches no graph holding a loop unless told; the envs tell it, so a second
    process loads the step instead of generating it again. Loops that differ only in
    their bodies are different entries, and the cached step follows the eager one."""
    import json
    import os
    import subprocess
    import sys

    environ = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": str(tmp_path / "cache"), "OMP_NUM_THREADS": "1"}
    runs = [
        json.loads(
            subprocess.run(
                [sys.executable, "-c", CACHED], env=environ, capture_output=True, text=True, check=True
            ).stdout
        )
        for _ in range(2)
    ]
    cold, warm = (r["counters"] for r in runs)
    assert cold.get("fxgraph_cache_miss", 0) >= 3 and not cold.get("fxgraph_cache_bypass")
    assert (
        warm.get("fxgraph_cache_hit", 0) >= 3
        and not warm.get("fxgraph_cache_miss")
        and not warm.get("fxgraph_cache_bypass")
    )
    for run in runs:
        assert run["toy"] == [[63.0] * 3, [122.0] * 3]  # 1 -> 3, 7, 15, 31, 63 and 1 -> 2, 5, 14, 41, 122
    eager = make("burgers-v0", 2, dtype=torch.float64, seed=3)
    eager.reset_members()
    g = torch.Generator().manual_seed(1)
    expected = torch.stack([eager.step_members(eager.random_action(g))[0] for _ in range(3)])
    for run in runs:
        torch.testing.assert_close(torch.tensor(run["obs"], dtype=torch.float64), expected, **ROUND_OFF)


@pytest.mark.parametrize("env_id", ["lorenz-v0", "lorenz-continuous-v0"])
def test_whole_step_compiled_handles_a_blow_up_as_the_eager_step(env_id):
    """Envs compiled a whole step at a time (physics and bookkeeping in one graph) end a
    blown-up member's episode exactly as the eager step does."""
    params = {"rho": [28.0, 1e6]}
    eager = beacon_torch.make(env_id, 2, dtype=torch.float64, **params)
    compiled = beacon_torch.make(env_id, 2, dtype=torch.float64, compile=True, **params)
    g = torch.Generator().manual_seed(0)
    actions = [eager.random_action(g) for _ in range(60)]
    out = []
    for env in (eager, compiled):
        env.reset_members()
        steps = [env.step_members(a) for a in actions]
        out.append([torch.stack([s[i] for s in steps]) for i in range(4)])
    (obs_e, rew_e, term_e, trunc_e), (obs_c, rew_c, term_c, trunc_c) = out
    assert term_e[:, 1].any(), "the extreme member never blew up"
    assert torch.equal(term_c, term_e) and torch.equal(trunc_c, trunc_e)
    assert (rew_c[term_c] == compiled.physics.blowup_reward).all()
    torch.testing.assert_close(obs_c, obs_e, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(rew_c, rew_e, rtol=1e-9, atol=1e-12)
    assert [fn.__name__ for fn in compiled.physics.kernels._cache] == ["step"]  # nothing compiled apart


def test_a_differentiated_loop_runs_in_chunks_to_the_eager_gradient():
    """Compiled with a graph to keep, a loop of 5 substeps at 2 a chunk is two chunk
    calls and one single substep (no while_loop: it cannot be differentiated), whose
    values and gradients are the eager loop's."""
    from beacon_torch.compiled import Kernels, _Chunk, at

    def substep(i, x, w):
        return x * at(w, i) + torch.sin(x)

    x0 = torch.linspace(-1.0, 1.0, 7, dtype=torch.float64)
    w0 = torch.linspace(0.5, 0.9, 5, dtype=torch.float64)
    out = []
    for compiled in (False, True):
        kernels = Kernels(chunk=2)
        if compiled:
            kernels.compile()
        loop = kernels.loop(substep)
        x, w = x0.clone().requires_grad_(), w0.clone().requires_grad_()
        y = loop(5, x, w)
        out.append((y.detach(), *torch.autograd.grad((y * y).sum(), (x, w))))
    for got, want in zip(out[1], out[0], strict=True):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-14)
    lengths = sorted(getattr(fn, "length", 1) for fn in kernels._cache)
    assert lengths == [1, 2] and any(isinstance(fn, _Chunk) for fn in kernels._cache)


@pytest.mark.slow(seconds=60)
@pytest.mark.parametrize("env_id", ["vortex-v0", "lorenz-continuous-v0", "ks-v0"])
def test_a_small_action_is_one_differentiated_compiled_call_with_the_eager_gradient(env_id):
    """Where a physics asks for it (``grad_whole_action``), a differentiated action on
    the compiled path is one compiled call (substeps, bounds, observation and the
    containment of blow-ups in one graph) whose rewards and gradients are the eager
    env's, a member that blows up included (lorenz at rho = 1e6, with its smooth reward)."""
    from beacon_torch.core.step import advance_settled

    params = {"rho": [28.0, 1e6], "reward_width": 1.0} if env_id.startswith("lorenz") else {}
    out, envs = [], []
    for compiled in (False, True):
        env = beacon_torch.make(env_id, 2, dtype=torch.float64, seed=3, compile=compiled, differentiable=True, **params)
        assert env.physics.grad_whole_action
        env.reset()
        g = torch.Generator().manual_seed(1)
        actions = torch.stack([env.random_action(g) for _ in range(40)]).requires_grad_()
        steps = [env.step_members(a) for a in actions]
        rewards, terminated = torch.stack([s[1] for s in steps]), torch.stack([s[2] for s in steps])
        (grad,) = torch.autograd.grad(rewards.sum(), actions)
        out.append((rewards.detach(), terminated, grad))
        envs.append(env)
    (r_e, t_e, g_e), (r_c, t_c, g_c) = out
    if env_id.startswith("lorenz"):
        assert t_e[:, 1].any(), "the extreme member never blew up"
    assert torch.equal(t_c, t_e)
    assert torch.isfinite(g_c).all() and g_e.abs().max() > 0
    torch.testing.assert_close(r_c, r_e, **ROUND_OFF)
    torch.testing.assert_close(g_c, g_e, rtol=1e-8, atol=1e-10 * g_e.abs().max().item())
    assert advance_settled in envs[1].physics.kernels._cache  # the action compiled whole


def test_a_trace_before_the_c_kernels_are_built_takes_the_tensor_path(monkeypatch):
    """Tracing cannot build the C kernels (a compiler run under a lock): code compiled
    before they exist takes the tensor path, and is compiled again once they do."""
    from beacon_torch.numerics import native

    if native.library() is None:
        pytest.skip("no C compiler here")
    monkeypatch.setattr(native, "_tried", False)
    monkeypatch.setattr(native, "_library", None)

    @torch.compile(fullgraph=True, backend="eager")
    def which(x):
        return x + 1 if native.applies(x.device, x.dtype) else x - 1

    assert which(torch.zeros(2)).tolist() == [-1.0, -1.0]
    assert not native._tried
    assert native.library() is not None
    assert which(torch.zeros(2)).tolist() == [1.0, 1.0]


@pytest.mark.slow(seconds=40)
def test_a_compiled_env_is_the_first_thing_a_process_runs():
    """``make(..., compile=True)`` stepped first thing in a fresh process, before any
    C kernel was built (sloshing's step asks for them inside its compiled call)."""
    import subprocess
    import sys

    script = (
        "import beacon_torch\n"
        "from beacon_torch.numerics import native\n"
        "env = beacon_torch.make('sloshing-v0', 2, compile=True)\n"
        "env.reset()\n"
        "env.rand_step()\n"
        "print(native._tried)\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split()[-1] == "True"
