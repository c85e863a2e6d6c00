"""ks-v0: its solver against the published facts of the L = 22 flow (float64), the
scheme as written in Fourier space, its order, and the env's target and errors."""

import numpy as np
import pytest
import torch

import beacon_torch
from beacon_torch.envs.ks import (
    ALPHA,
    BETA,
    DT,
    GAMMA,
    PUBLISHED_EIGENVALUES,
    PUBLISHED_ENERGY,
    PUBLISHED_LYAPUNOV,
    TARGETS,
    ZETA,
    actuators,
    attractor_bank,
    equilibrium,
    ks_step,
    stage_matrices,
)
from validation import ks as validation


def test_the_equilibria_have_the_published_energies_and_leading_eigenvalues():
    rows = validation.equilibria()
    assert [r["target"] for r in rows] == list(TARGETS)
    for r in rows:
        assert r["energy"] == pytest.approx(PUBLISHED_ENERGY[r["target"]], rel=0.01)
        assert len(r["eigenvalues"]) == len(PUBLISHED_EIGENVALUES[r["target"]])
        for re, im, published_re, published_im in r["eigenvalues"]:
            assert re == pytest.approx(published_re, rel=0.01)
            assert im == pytest.approx(published_im, rel=0.01, abs=1e-9)
        # the leading values are the published unstable ones (and the translation's 0)
        unstable = [v for v in r["leading"] if v[0] > 1e-6]
        assert len(unstable) == {"E1": 4, "E2": 2, "E3": 2}[r["target"]]


def test_the_leading_lyapunov_exponent_is_the_published_one():
    row = validation.lyapunov(members=64, horizon=200.0)
    assert row["exponent"] == pytest.approx(PUBLISHED_LYAPUNOV, rel=0.1)


def test_the_time_step_is_second_order():
    row = validation.order()
    assert row["errors"] == sorted(row["errors"], reverse=True)
    assert all(1.9 < o < 2.4 for o in row["orders"])


def spectral_step(u, forcing, L, dt):
    """The scheme as published, in Fourier space (transforms, not matrices)."""
    n = u.shape[-1]
    q = 2.0 * np.pi * torch.arange(n // 2 + 1, dtype=torch.float64) / L
    lam = q**2 - q**4
    ik = 1j * q
    ik[-1] = 0.0
    f = torch.fft.rfft(forcing @ torch.as_tensor(actuators(L, n, 0.4)).T)
    v = torch.fft.rfft(u)
    before = torch.zeros_like(v)
    for alpha, beta, gamma, zeta in zip(ALPHA, BETA, GAMMA, ZETA, strict=True):
        now = -0.5 * ik * torch.fft.rfft(torch.fft.irfft(v, n=n) ** 2) + f
        v = (v + dt * (gamma * now + zeta * before + alpha * lam * v)) / (1.0 - beta * dt * lam)
        before = now
    return torch.fft.irfft(v, n=n)


def test_the_matrix_stages_are_the_published_scheme_in_fourier_space():
    u = attractor_bank(22.0, 64, 0.4).u[:16]
    forcing = 0.5 * (2.0 * torch.rand(16, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) - 1.0)
    weights = torch.as_tensor(stage_matrices(22.0, 64, 0.4))
    for _ in range(20):
        ours, theirs = ks_step(u, forcing, weights), spectral_step(u, forcing, 22.0, DT)
        assert torch.allclose(ours, theirs, rtol=0, atol=1e-12)
        u = ours


@pytest.mark.parametrize("target", TARGETS)
def test_the_target_is_a_fixed_point_of_the_step_and_scores_zero(target):
    env = beacon_torch.make("ks-v0", 2, target=target, dtype=torch.float64)
    td = env.reset()
    u_e = equilibrium(target).expand(2, -1)
    env.set_state({"u": u_e.clone(), "a": torch.zeros(2, 4, dtype=torch.float64)})
    rewards = []
    for _ in range(10):
        td["action"] = torch.zeros(2, 4, dtype=torch.float64)
        td = env.step(td)["next"]
        rewards.append(td["reward"])
    assert torch.stack(rewards).abs().max() < 1e-9
    assert torch.allclose(env.state.u, u_e, rtol=0, atol=1e-10)


def test_each_target_is_the_nearest_equilibrium_to_itself_and_the_flow_leaves_it():
    """Without control the attractor's states are far from every target, and a target
    perturbed by 1e-6 leaves it (the equilibria are unstable)."""
    weights = torch.as_tensor(stage_matrices(22.0, 64, 0.4))
    zero = torch.zeros(1, 4, dtype=torch.float64)
    for target in TARGETS:
        u = equilibrium(target)[None] + 1e-6 * torch.sin(torch.arange(64, dtype=torch.float64))[None]
        for _ in range(round(200 / DT)):
            u = ks_step(u, zero, weights)
        assert float((u - equilibrium(target)).norm()) > 1.0


def test_bad_settings_get_one_line():
    with pytest.raises(ValueError, match="no equilibrium E3 found at L = 10 .*flat state"):
        beacon_torch.make("ks-v0", 1, L=10.0, target="E3")
    with pytest.raises(ValueError, match="'n' must be a multiple of 8"):
        beacon_torch.make("ks-v0", 1, n=60)
    with pytest.raises(ValueError, match="'target' must be one of"):
        beacon_torch.make("ks-v0", 1, target="E4")


def test_the_sensors_and_actuators_are_the_papers():
    env = beacon_torch.make("ks-v0", 3, dtype=torch.float64)
    td = env.reset()
    assert td["observation"].shape == (3, 8) and env.action_spec.shape == (3, 4)
    assert torch.equal(td["observation"], env.state.u[:, ::8])
    psi = actuators(22.0, 64, 0.4)
    assert np.allclose(psi.max(0), 1.0) and list(psi.argmax(0)) == [0, 16, 32, 48]
    # the actuator at x = 0 reaches across the periodic boundary
    assert psi[63, 0] == pytest.approx(psi[1, 0])


def test_the_page_shows_the_recorded_validation_trials_and_results():
    from pathlib import Path

    from beacon_torch import received

    page = (Path(__file__).resolve().parents[1] / "docs" / "envs" / "ks.md").read_text()
    newest = sorted(validation.RECORDS.glob("ks_validation-*.json"))[-1]
    rows = received.json_file(newest, "a ks validation record")["rows"]
    assert validation.table(rows) in page
    # the recorded exponent is within a tenth of the published one, the energies within 1 %
    (lyapunov,) = [r for r in rows if r["kind"] == "lyapunov"]
    assert lyapunov["members"] == 256 and abs(lyapunov["exponent"] / PUBLISHED_LYAPUNOV - 1) < 0.1
    from experiments import ks_trials

    assert ks_trials.table() in page
    # the published three-seed results, each recipe's row as the recorded summaries give it
    results = ks_trials.results()
    assert results in page
    assert {line.split("|")[1].strip() for line in results.splitlines()[2:]} == {"ppo", "td3", "shac", "grad"}
