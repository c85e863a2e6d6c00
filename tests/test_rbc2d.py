"""FluidGym's RBC2D levels: the grid, the heaters, the stretched channel's numerics and
the env's layouts, as FluidGym's code defines them."""

from __future__ import annotations

import dataclasses

import pytest
import torch

import beacon_torch
from beacon_torch import cache, starts
from beacon_torch.envs import rbc2d
from beacon_torch.numerics.grid import NEUMANN, PERIODIC
from beacon_torch.numerics.projection import Cavity
from beacon_torch.numerics.staggered import Axis, Stretched, divergence
from beacon_torch.numerics.transport import _coefficients
from beacon_torch.params import resolve_params

F64 = torch.float64


def test_the_rows_are_fluidgyms_wall_refined_grid():
    # make_weights_exp(n, base, "BOTH"): exponents 0..n//2-1 from the bottom, then down
    # from n//2 to 0 at the top; heights base**e normalised
    heights = rbc2d.wall_refined(5, 1.5)
    expected = torch.tensor([1.0, 1.5, 2.25, 1.5, 1.0], dtype=F64)
    torch.testing.assert_close(heights, expected / expected.sum())
    rows = rbc2d.wall_refined(61, rbc2d.BASE)
    assert float(rows.sum()) == pytest.approx(1.0, abs=1e-15)
    torch.testing.assert_close(rows, rows.flip(0))
    torch.testing.assert_close(rows[1:31] / rows[:30], torch.full((30,), 1.02, dtype=F64))
    assert float(rows.min()) == pytest.approx(0.01206, abs=1e-5)  # the plates' rows
    physics, _ = make_physics("easy", num_envs=1)
    assert (physics.nx, physics.ny) == (96, 61)


def test_the_heaters_follow_fluidgyms_action_to_control():
    blend = rbc2d.blend_matrix(12, 8)
    torch.testing.assert_close(blend.sum(1), torch.ones(96, dtype=F64))
    # at 8 cells a heater's first cell is half its left neighbour's (round(0.8) = 1)
    assert blend[8, 0] == 0.5 and blend[8, 1] == 0.5 and blend[0, 11] == 0.5
    assert blend[9:16, 1].eq(1.0).all() and blend[15, 2] == 0.0
    # at 16 cells the blend is two cells wide, the last one half the right neighbour's
    wide = rbc2d.blend_matrix(12, 16)
    assert wide[16, 0] == 0.5 and wide[17, 1] == 1.0 and wide[31, 2] == 0.5 and wide[30, 1] == 1.0
    # the mean removed and scaled by 0.75: within the limit, the plate's mean stays T_HOT
    action = torch.tensor([[0.9, -0.5, 0.3, -0.1] * 3], dtype=F64)
    bottom = rbc2d.heater_temperatures(action, blend)
    assert float(bottom.mean()) == pytest.approx(rbc2d.T_HOT, abs=1e-12)
    # each heater clipped to 0.75 on its own (FluidGym's element-wise form of the limit)
    action = torch.tensor([[1.0, -1.0, 1.0, 0.2] * 3], dtype=F64)
    bottom = rbc2d.heater_temperatures(action, blend)
    expected = torch.tensor([0.525, -0.75, 0.525, -0.075] * 3, dtype=F64)
    torch.testing.assert_close(bottom[0, 3::8], rbc2d.T_HOT + expected)


def make_physics(level: str, num_envs: int = 2, dtype=F64, **given):
    settings = {**rbc2d.LEVELS[level], **given}
    p = resolve_params(rbc2d.Rbc2dParams, settings, batch_size=num_envs, device="cpu", dtype=dtype, env_id="t")
    return rbc2d.Rbc2dPhysics(p, num_envs, dtype=dtype), p


def test_a_stretched_channels_pressure_solve_is_exact_and_its_projection_divergence_free():
    axis = Axis.of_widths(rbc2d.wall_refined(21, 1.05))
    nx, dx = 16, 0.2
    cavity = Cavity(nx, 21, dx, axis, (PERIODIC, PERIODIC, NEUMANN, NEUMANN), dtype=F64, device="cpu")
    g = torch.Generator().manual_seed(0)
    rhs = torch.randn((nx, 21, 3), generator=g, dtype=F64)
    # a compatible source: zero volume-weighted mean
    weights = axis.widths[None, :, None]
    rhs = rhs - (rhs * weights).sum((0, 1)) / (nx * weights.sum())
    phi = cavity.solver.solve(rhs)
    torch.testing.assert_close(cavity.solver.apply(phi), rhs, atol=1e-10, rtol=0)
    u = torch.randn((nx + 1, 21, 3), generator=g, dtype=F64)
    u[-1] = u[0]  # the periodic face carried twice
    v = torch.randn((nx, 22, 3), generator=g, dtype=F64)
    v[:, 0], v[:, -1] = 0.0, 0.0
    from beacon_torch.numerics.staggered import project

    u, v, _ = project(u, v, torch.zeros((nx, 21, 3), dtype=F64), cavity.solver, 0.1, dx, cavity.dy)
    assert float(divergence(u, v, dx, cavity.dy).abs().max()) < 1e-10
    torch.testing.assert_close(u[-1], u[0])


def test_the_stretched_transport_on_equal_rows_is_the_uniform_one():
    g = torch.Generator().manual_seed(1)
    s = torch.randn((10, 8, 2), generator=g, dtype=F64)
    u, v = torch.randn((9, 6, 2), generator=g, dtype=F64), torch.randn((8, 7, 2), generator=g, dtype=F64)
    h = 0.125
    axis = Axis.of_widths(torch.full((6,), h, dtype=F64))
    stretched = Stretched(axis.widths[None, :, None], axis.gaps[None, :, None], 1)
    uniform, rows = _coefficients(s, u, v, 0.01, 0.02, 0.1, h), _coefficients(s, u, v, 0.01, 0.02, 0.1, stretched)
    for a, b in zip(uniform, rows, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-13, atol=1e-13)


def test_the_channel_steps_alike_when_shifted_by_a_heater():
    physics, p = make_physics("easy", period=0.05, num_envs=1)
    flow = physics._start(p)  # the bank of developed flows, shipped
    state = rbc2d.Rbc2dState(*(f[:1] for f in flow), bottom=torch.ones(1, physics.nx, dtype=F64))
    shift = p.heater_cells
    rolled = lambda f: torch.cat((f[:, :1], f[:, 1:-1].roll(shift, 1), f[:, -1:]), 1)
    # the faces of a state are ghosted as the cells: positions 1..nx+1 hold faces 0..nx
    u = state.u.clone()
    u[:, 1:-1] = state.u[:, 1:-1].roll(shift, 1)
    u[:, -1] = u[:, 1]
    shifted = rbc2d.Rbc2dState(
        u=u, v=rolled(state.v), p=state.p.roll(shift, 1), theta=rolled(state.theta), bottom=state.bottom
    )
    action = torch.linspace(-1, 1, 12, dtype=F64)[None]
    a, _ = physics.advance(p, state, action, None, {})
    b, _ = physics.advance(p, shifted, action.roll(1, 1), None, {})
    torch.testing.assert_close(b.theta[:, 1:-1, 1:-1], a.theta[:, 1:-1, 1:-1].roll(shift, 1), atol=1e-10, rtol=0)
    torch.testing.assert_close(physics.nusselt(p, b), physics.nusselt(p, a), atol=1e-10, rtol=0)


def test_the_multi_agent_reward_mixes_the_windows_and_the_whole_flow():
    physics, p = make_physics("easy", period=0.02, num_envs=1)
    agents = rbc2d.Rbc2dSeparablePhysics(p, 1, dtype=F64)
    flow = physics._start(p)  # the bank of developed flows, shipped
    state = rbc2d.Rbc2dState(*(f[:1] for f in flow), bottom=torch.ones(1, physics.nx, dtype=F64))
    action = torch.linspace(-1, 1, 12, dtype=F64)[None]
    new, whole = physics.advance(p, state, action, None, {})
    _, mixed = agents.advance(p, state, action[..., None], None, {})
    flux = physics.column_flux(p, new).reshape(12, 8).mean(-1)
    kappa = physics.kappa(p)
    for agent in (0, 5, 11):
        seen = [(agent + k) % 12 for k in range(-5, 6)]
        local = p.nu_ref - (1.0 + flux[seen].mean() / kappa)
        assert float(mixed[0, agent]) == pytest.approx(float(0.2 * local + 0.8 * whole[0]), rel=1e-12)
    # each agent sees its window of 11 heaters' sensors, its own in the middle
    obs = agents.observe(p, new)
    assert obs.shape == (1, 12, 4 * 8 * 4 * 11)
    sensors = physics.sensors(new)  # [1, 4, 8, 48]
    window = obs[0, 3].reshape(4, 8, 11, 4)
    torch.testing.assert_close(window[:, :, 5], sensors[0][:, :, 12:16])
    torch.testing.assert_close(window[:, :, 0], sensors[0][:, :, 40:44])  # agent 3 sees heater 10 first


def test_the_levels_are_registered_with_fluidgyms_settings():
    # the reward's reference: FluidGym's table's reward + Nusselt number, alike in each row
    for level, ra, nu_ref in (("easy", 8e4, 4.896), ("medium", 4e5, 6.429), ("hard", 8e5, 7.243)):
        for env_id in (f"rbc2d-{level}-v0", f"rbc2d-{level}-ma-v0"):
            spec = beacon_torch.registry.ENVS[env_id]
            assert spec.defaults["ra"] == ra and spec.defaults["nu_ref"] == nu_ref
            assert spec.physics.episode_length == 200
            params = spec.physics.Params(**spec.physical_defaults())
            assert (params.pr, params.heaters, params.heater_cells, params.period) == (0.7, 12, 8, 1.0)
    assert beacon_torch.registry.ENVS["rbc2d-hard-ma-v0"].agents == "heater"


def test_every_level_trains_with_fluidgyms_ppo_and_sac_settings():
    # its runscripts use the same Stable-Baselines3 settings at the three levels, so
    # every cell of the table trains alike: a level left out of the recipes' tables
    # would train with another env's defaults
    from beacon_torch.training.config import PPOConfig, SACConfig, configure

    for level in rbc2d.LEVELS:
        ppo, sac = configure(PPOConfig, f"rbc2d-{level}-v0"), configure(SACConfig, f"rbc2d-{level}-v0")
        assert (ppo.frames, ppo.n_rollout, ppo.minibatches, ppo.epochs) == (50_000, 2048, 32, 10)
        assert (ppo.actor_lr, ppo.critic_lr, ppo.gae_lambda, ppo.grad_clip) == (3e-4, 3e-4, 0.95, 0.5)
        assert ppo.actor == "free-spread"  # its MlpPolicy's actor
        assert (ppo.critic, ppo.update) == ("sb3", "sb3")  # and its critic and update
        assert (sac.frames, sac.batch_size, sac.init_random_frames) == (50_000, 256, 100)
        ma_ppo, ma_sac = configure(PPOConfig, f"rbc2d-{level}-ma-v0"), configure(SACConfig, f"rbc2d-{level}-ma-v0")
        assert (
            ma_ppo.minibatches == 256 and dataclasses.replace(ma_ppo, minibatches=32, env=ppo.env, out=ppo.out) == ppo
        )
        assert (ma_sac.frames, ma_sac.batch_size, ma_sac.updates_per_batch) == (50_000, 21, 12 * 64)
        # its replay buffer (50,000) and random start (100) count agent transitions: a
        # stored flow step holds the 12 agents' (the whole run's would be 6.8 GB)
        assert (sac.buffer_size or sac.frames) == 50_000
        assert 12 * ma_sac.buffer_size <= 50_000 < 12 * (ma_sac.buffer_size + 1)
        assert 12 * (ma_sac.init_random_frames - 1) < 100 <= 12 * ma_sac.init_random_frames


def test_each_start_is_its_own_randomised_copy_of_the_developed_flow():
    physics, p = make_physics("easy", num_envs=4, period=0.02)
    state = physics.initial_state(p, torch.Generator().manual_seed(3))
    theta = state.theta[:, 1:-1, 1:-1]
    assert float(theta.min()) >= rbc2d.T_COLD - 1e-9 and float(theta.max()) <= rbc2d.T_HOT + 1e-9
    # four members, four flows; each a solution of the channel: one face carried twice,
    # no divergence, and the developed flow's Nusselt number after 1 to 2 time units
    assert len({round(float(n), 6) for n in physics.nusselt(p, state)}) == 4
    torch.testing.assert_close(state.u[:, 1], state.u[:, -1])
    u, v = state.u[:, 1:, 1:-1].movedim(0, -1), state.v[:, 1:-1, 1:].movedim(0, -1)
    assert float(divergence(u, v, physics.dx, physics.dy).abs().max()) < 1e-8
    bank = physics._start(p)
    assert bank.u.shape[0] == len(rbc2d.BANK_SEEDS["train"]) == 10
    developed = physics.nusselt(p, rbc2d.Rbc2dState(*bank, bottom=torch.ones(10, physics.nx, dtype=F64)))
    assert (physics.nusselt(p, state) - developed.mean()).abs().max() < 1.0


def test_the_validation_and_test_starts_come_from_developed_flows_of_their_own(monkeypatch):
    # FluidGym's modes: ten developed flows each, from other seeds, all shipped
    banks = {}
    for level, settings in rbc2d.LEVELS.items():
        for domains, bank_seeds in rbc2d.BANK_SEEDS.items():
            p = rbc2d.Rbc2dParams(**settings, domains=domains)
            name = cache.file_name("rbc2d-developed", rbc2d.START_VERSION, rbc2d.start_key(p))
            assert (cache.PACKAGE_DATA / name).is_file(), (level, domains)
            assert len(bank_seeds) == 10
            banks[level, domains] = name
    assert len(set(banks.values())) == 9
    assert set(rbc2d.BANK_SEEDS["train"]).isdisjoint(rbc2d.BANK_SEEDS["test"])
    # a start set asks for its own bank; a user's env for the training one
    asked = []
    start = rbc2d.Rbc2dPhysics._start
    monkeypatch.setattr(rbc2d.Rbc2dPhysics, "_start", lambda self, p: asked.append(p.domains) or start(self, p))
    env = beacon_torch.make("rbc2d-easy-v0", 2, period=0.02, start_run=0.03, seed=0)
    env.reset()
    assert set(asked) == {"train"}
    states = starts.states(env, "validation")
    assert set(asked) == {"train", "validation"} and states.theta.shape[0] == starts.SETS["validation"][1]


@pytest.mark.parametrize("level", ["medium", "hard"])
def test_the_harder_levels_pass_torchrls_spec_check_in_both_layouts(level):
    from torchrl.envs.utils import check_env_specs

    dt = rbc2d.LEVELS[level]["dt"]
    for env_id in (f"rbc2d-{level}-v0", f"rbc2d-{level}-ma-v0"):
        env = beacon_torch.make(env_id, 2, period=2 * dt, seed=0)
        check_env_specs(env)
        td = env.rollout(2)
        assert torch.isfinite(td["next", "diagnostics", "nusselt"]).all()


def test_the_results_table_sets_each_cell_beside_fluidgyms(tmp_path):
    import json

    from beacon_torch import received
    from experiments import rbc2d_table

    # what tools/reproduce.py records of a pair: each seed's test episodes and no control's
    episodes = {"score": [0.0] * 8, "nusselt": [4.0] * 7 + [9.0]}
    free = {"score": [0.0] * 8, "nusselt": [5.0] * 8}
    seed = {"seed": "seed0", "frames": 51_200, "wall_s": 900.0, "test_episodes": episodes}
    seeds = [dict(seed, test_uncontrolled_episodes=free), dict(seed, seed="seed1", test_uncontrolled_episodes=free)]
    (tmp_path / "ppo").mkdir()
    (tmp_path / "ppo" / "rbc2d-easy-v0.json").write_text(json.dumps({"config": {"threads": 1}, "seeds": seeds}))
    (tmp_path / "ppo" / "burgers-v0.json").write_text("{}")
    rows = rbc2d_table.recorded(tmp_path, received)
    assert [(r["level"], r["algorithm"]) for r in rows] == [("easy", "PPO")]
    assert rbc2d_table.cell("sac", "rbc2d-hard-ma-v0") == ("hard", "MA-SAC")
    lines = rbc2d_table.table(rows).splitlines()[2:]
    assert len(lines) == 12 and sum("not run" in line for line in lines) == 11
    # the IQM over the seeds' episodes leaves the outlying episodes out, as FluidGym's
    ours = "**4.000** | 20.0 % | 5.000 | 2 x 8 | 51,200, 51,200 | 0.25 | the paper's |"
    assert lines[0] == f"| easy | PPO | 4.008 | 17.2 % | 17.6 | {ours}"
    # a run that records Stable-Baselines3's actor, or its whole PPO, says so
    for config, agent in (
        ({"actor": "free-spread"}, "Stable-Baselines3's actor"),
        ({"actor": "free-spread", "critic": "sb3", "update": "sb3"}, "Stable-Baselines3's"),
    ):
        summary = {"config": {"threads": 1, **config}, "seeds": seeds}
        (tmp_path / "ppo" / "rbc2d-easy-v0.json").write_text(json.dumps(summary))
        assert rbc2d_table.table(rbc2d_table.recorded(tmp_path, received)).splitlines()[2].endswith(f"| {agent} |")
    # SAC at FluidGym's gradient steps, one an agent transition, or at fewer, said
    (tmp_path / "sac").mkdir()
    for updates, agent in (
        (768, "SAC's"),
        (64, "SAC's, 1 gradient step a flow step (FluidGym's: 12, one an agent transition)"),
    ):
        config = {"threads": 1, "env": "rbc2d-easy-ma-v0", "updates_per_batch": updates, "frames_per_batch": 64}
        (tmp_path / "sac" / "rbc2d-easy-ma-v0.json").write_text(json.dumps({"config": config, "seeds": seeds}))
        assert rbc2d_table.table(rbc2d_table.recorded(tmp_path, received)).splitlines()[5].endswith(f"| {agent} |")
    config = {"threads": 1, "env": "rbc2d-easy-v0", "updates_per_batch": 64, "frames_per_batch": 64}
    (tmp_path / "sac" / "rbc2d-easy-v0.json").write_text(json.dumps({"config": config, "seeds": seeds}))
    assert rbc2d_table.table(rbc2d_table.recorded(tmp_path, received)).splitlines()[3].endswith("| SAC's |")


def test_a_levels_one_is_fluidgyms_best_nusselt_number_as_a_share_of_no_controls():
    from beacon_torch.training import report

    for env_id in ("rbc2d-medium-v0", "rbc2d-medium-ma-v0"):
        reference = beacon_torch.registry.ENVS[env_id].card.scale_reference()
        assert (
            reference.source == "a published result" and "SAC's Nusselt number 5.639 against 6.856" in reference.where
        )
    # no control at Nu 7.0 a step scores 200 (6.429 - 7.0); FluidGym's SAC lowers Nu by
    # 17.75 %: "= 1" is 200 (6.429 - 7.0 x 5.639 / 6.856)
    uncontrolled = 200 * (6.429 - 7.0)
    assert report.reference("rbc2d-medium-v0", uncontrolled) == pytest.approx(200 * (6.429 - 7.0 * 5.639 / 6.856))
    assert report.normalised(uncontrolled, uncontrolled, "rbc2d-medium-v0") == 0.0
