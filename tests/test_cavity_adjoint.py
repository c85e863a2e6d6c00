"""The cavities' substeps with their adjoint written out (``envs.cavity._Substeps``):
each piece (the ghost maps' fold, the predictor's, the projection's and the transport's
adjoints) equals autograd's gradient of the forward code to round-off in float64, and
so does a whole differentiated action of rayleigh-v0 and mixing-continuous-v0, eager and
compiled, kept or recomputed; where it does not apply (``torch.func``, differentiable
parameters, a periodic or stretched grid) the env records its substeps as before."""

import pytest
import torch

import beacon_torch
from beacon_torch.autograd import release_free_memory
from beacon_torch.envs import cavity
from beacon_torch.numerics import native
from beacon_torch.numerics.grid import GRADIENT, NEUMANN, PERIODIC, VALUE, ZERO, ZERO_GHOST, Ghosts
from beacon_torch.numerics.projection import Cavity, Flow
from beacon_torch.numerics.staggered import predict, predict_adjoint, project, project_adjoint
from beacon_torch.numerics.transport import sweep_adjoint

pytestmark = pytest.mark.skipif(not native.applies("cpu", torch.float64), reason="no C compiler")
F64 = dict(dtype=torch.float64, device="cpu")


def rand(shape, seed: int, scale: float = 1.0) -> torch.Tensor:
    return scale * torch.randn(shape, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))


def vjp(fn, inputs, weights):
    """Autograd's gradients of ``sum(w * out)`` over ``fn``'s outputs, for each input."""
    inputs = [t.detach().clone().requires_grad_() for t in inputs]
    out = fn(*inputs)
    out = out if isinstance(out, tuple) else (out,)
    total = sum((o * w).sum() for o, w in zip(out, weights, strict=True))
    return torch.autograd.grad(total, inputs)


def close(got, want):
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12 * max(1.0, float(want.abs().max())))


GHOSTS = {
    "cells, values": lambda: Ghosts.cells(6, 7, GRADIENT, ZERO, VALUE, GRADIENT, **F64),
    "cells, no corners": lambda: Ghosts.cells(6, 7, GRADIENT, GRADIENT, GRADIENT, ZERO, corners=False, **F64),
    "cells, periodic": lambda: Ghosts.cells(6, 7, PERIODIC, PERIODIC, VALUE, VALUE, **F64),
    "u faces": lambda: Ghosts.u_faces(6, 7, **F64),
    "v faces": lambda: Ghosts.v_faces(6, 7, **F64),
}


@pytest.mark.parametrize("kind", sorted(GHOSTS))
def test_a_ghost_maps_fold_is_its_adjoint(kind):
    ghosts = GHOSTS[kind]()
    shape = {"u faces": (7, 7, 3), "v faces": (6, 8, 3)}.get(kind, (6, 7, 3))
    f = rand(shape, 1)
    g = rand(ghosts(f).shape, 2)
    (want,) = vjp(ghosts, (f,), (g,))
    close(ghosts.fold(g), want)


def cavity_flow(nx: int, ny: int, members: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return rand((nx + 1, ny, members), seed), rand((nx, ny + 1, members), seed + 1), rand((nx, ny, members), seed + 2)


@pytest.mark.parametrize("members", [3, 8])
def test_the_predictors_adjoint_is_autograds_gradient(members):
    """The ghosted velocities, the pressure and the source, with a viscosity per member."""
    nx, ny, dt, dx, dy = 9, 7, 0.01, 1 / 9, 1 / 7
    grid = Cavity(nx, ny, dx, dy, **F64)
    u, v, p = cavity_flow(nx, ny, members, 1)
    off_u, off_v = grid.walls(0.3, -0.2, 0.1, 0.4, like=u)
    u, v = grid.u_ghosts(u, off_u), grid.v_ghosts(v, off_v)
    nu = rand((members,), 9).abs() * 0.01
    source = rand((nx, ny - 1, members), 4)
    weights = rand((nx + 1, ny, members), 5), rand((nx, ny + 1, members), 6)
    want = vjp(lambda u, v, p, s: predict(u, v, p, nu, dt, dx, dy, s), (u, v, p, source), weights)
    got = predict_adjoint(u, v, *weights, nu, dt, dx, dy)
    # the wall faces of the ghosted velocities are read by nothing but the stencils
    for g, w in zip(got, want, strict=True):
        close(g, w)


@pytest.mark.parametrize("top", [NEUMANN, ZERO_GHOST])
def test_the_projections_adjoint_is_autograds_gradient(top):
    """Between walls (rayleigh's) and with mixing's zero ghost on the top: the interior
    faces and the pressure (the wall faces are zero in what the predictor gives)."""
    nx, ny, dt, dx, dy = 10, 8, 0.01, 1 / 10, 1 / 8
    grid = Cavity(nx, ny, dx, dy, (NEUMANN, NEUMANN, NEUMANN, top), **F64)
    assert grid.adjoint
    u, v, p = cavity_flow(nx, ny, 3, 1)
    u[0], u[-1], v[:, 0], v[:, -1] = 0.0, 0.0, 0.0, 0.0
    weights = cavity_flow(nx, ny, 3, 7)
    want = vjp(lambda u, v, p: project(u, v, p, grid.solver, dt, dx, dy), (u, v, p), weights)
    got = project_adjoint(*weights, grid.solver, dt, dx, dy)
    close(got[0][1:-1], want[0][1:-1])
    close(got[1][:, 1:-1], want[1][:, 1:-1])
    close(got[2], want[2])


def test_the_transports_adjoint_is_autograds_gradient():
    """The C sweep with its coefficients, from a ghosted scalar, the face velocities and
    a diffusivity per member: the gradient of the swept field given with its ghosts."""
    nx, ny, dt, dx, dy = 9, 11, 0.01, 1 / 9, 1 / 11
    grid = Cavity(nx, ny, dx, dy, **F64)
    s = rand((nx + 2, ny + 2, 3), 1)
    u, v, _ = cavity_flow(nx, ny, 3, 2)
    kappa = rand((3,), 8).abs() * 0.05

    def transport(s, u, v):
        interior = grid.sweep(s, u, v, kappa, dt, dx, dy)
        return torch.cat((s[:1], torch.cat((s[1:-1, :1], interior, s[1:-1, -1:]), 1), s[-1:]), 0)

    weight = rand((nx + 2, ny + 2, 3), 5)
    want = vjp(transport, (s, u, v), (weight,))
    swept = transport(s, u, v)
    for g, w in zip(sweep_adjoint(weight, swept, s, u, v, kappa, dt, dx, dy), want, strict=True):
        close(g, w)


def action_gradients(env_id: str, written: bool, compile: bool = False, checkpoint: bool = False, **make):
    """The gradient of a weighted sum of two actions' rewards and observations of
    ``env_id`` (3 members, float64) with respect to the actions and the first state's
    velocities, and how many actions ran through ``_Substeps``."""
    env = beacon_torch.make(
        env_id, 3, dtype="float64", differentiable=True, seed=1, compile=compile, grad_checkpoint=checkpoint, **make
    )
    if compile:
        env.physics.kernels.chunk = 2
    if not written:
        env.physics.stored = None
    td = env.reset()
    g = torch.Generator().manual_seed(3)
    shape = (3, *env.action_spec.shape[1:])
    actions = [(2 * torch.rand(shape, generator=g, dtype=torch.float64) - 1).requires_grad_() for _ in range(2)]
    weights = torch.arange(1.0, 4.0, dtype=torch.float64)
    calls = []
    original = cavity._Substeps.apply
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(cavity._Substeps, "apply", lambda *a: calls.append(1) or original(*a))
        total = 0.0
        for a in actions:
            td = env.step(td.set(env.action_key, a)).get("next")
            total = total + (td["reward"].reshape(3, -1).sum(-1) * weights).sum() + 0.1 * td["observation"].sin().sum()
        grads = torch.autograd.grad(total, actions)
    # the recorded substeps' graph leaves gigabytes of free heap in small pieces, which
    # the tests of resident memory that may follow in this process would count
    del total, td
    release_free_memory(keep=0)
    return grads, len(calls)


@pytest.mark.slow(seconds=20)
@pytest.mark.parametrize("env_id", ["rayleigh-v0", "mixing-continuous-v0"])
def test_a_differentiated_action_through_the_written_adjoint_is_autograds_gradient(env_id):
    """Two actions of the env, eager, float64: the actions' gradient through the
    written-out adjoint (one ``_Substeps`` an action) and through the recorded substeps."""
    # mixing on its tests' 30 x 30 cavity and rayleigh with 30 substeps an action: the
    # recorded substeps of the published settings keep gigabytes in float64
    make = {"L": 0.3, "H": 0.3, "side": 0.2} if env_id.startswith("mixing") else {"period": 0.3}
    got, calls = action_gradients(env_id, True, **make)
    want, none = action_gradients(env_id, False, **make)
    assert (calls, none) == (2, 0)
    for g, w in zip(got, want, strict=True):
        assert w.abs().min() > 0
        torch.testing.assert_close(g, w, rtol=1e-10, atol=1e-13)


@pytest.mark.slow(seconds=120)
def test_the_written_adjoint_compiles_and_recomputes_to_the_same_gradient():
    """rayleigh-v0 compiled (chunks of 2 substeps a call) and, eagerly, with each
    action recomputed in the backward pass: the eager gradient through the written
    adjoint."""
    want, _ = action_gradients("rayleigh-v0", True)
    for kw in (dict(compile=True), dict(checkpoint=True)):
        got, calls = action_gradients("rayleigh-v0", True, **kw)
        assert calls >= 2
        for g, w in zip(got, want, strict=True):
            torch.testing.assert_close(g, w, rtol=1e-10, atol=1e-13)


def test_the_written_adjoint_stands_aside_where_it_does_not_apply():
    """Under ``torch.func``, with a differentiable parameter, and on a periodic or a
    stretched grid, the env records its substeps as autograd does elsewhere."""
    physics = beacon_torch.make("rayleigh-v0", 2, dtype="float64").physics
    grid = physics.cavity
    flow = Flow(*(torch.zeros(s, **F64).requires_grad_() for s in ((51, 50, 2), (50, 51, 2), (50, 50, 2), (52, 52, 2))))
    assert grid.adjoint and physics._adjoint_applies(flow, None, None, 0.01, 0.01)
    assert not physics._adjoint_applies(flow, None, None, torch.tensor(0.01, requires_grad=True), 0.01)
    with torch.no_grad():
        assert not physics._adjoint_applies(flow, None, None, 0.01, 0.01)
    inside = []

    def loss(u):
        inside.append(physics._adjoint_applies(Flow(u, *flow[1:]), None, None, 0.01, 0.01))
        return u.sum()

    torch.func.grad(loss)(flow.u.detach())
    assert inside == [False]
    assert not Cavity(8, 6, 0.1, 0.1, (PERIODIC, PERIODIC, NEUMANN, NEUMANN), **F64).adjoint
    separable = beacon_torch.make("rayleigh-separable-v0", 2, dtype="float64").physics
    assert getattr(separable, "stored", None) is None  # Vignon's channel: periodic
