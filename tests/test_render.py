"""Frames and animations."""

import numpy as np
import pytest
from PIL import Image

import beacon_torch
from beacon_torch import episodes
from beacon_torch.render import save_animation

from conftest import ALL_ENVS, CHEAP_ENVS, make


@pytest.mark.parametrize("env_id", CHEAP_ENVS)
def test_render_frame_shows_the_state(env_id):
    env = make(env_id, 2, record_history=True)
    env.reset()
    blank_ish = env.render()
    episodes.episode(env, episodes.random_policy(env))
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    assert frame.shape == blank_ish.shape
    # the trajectory drawn over a whole episode changes the picture substantially
    assert (frame != blank_ish).any(axis=2).mean() > 0.02
    assert len(env.history) == env.episode_length + 1


def test_render_without_history_draws_the_current_state():
    env = beacon_torch.make("vortex-v0", 3)
    env.rollout(5)
    assert len(env.history) == 0
    assert env.render().shape[2] == 3


def test_history_follows_each_member_through_partial_resets():
    """Any member can be drawn, each with its own episode so far; memory stays within
    one episode of the batch."""
    import torch

    env = beacon_torch.make("lorenz-v0", 3, record_history=True, rho=[28.0, 30.0, 35.0])
    env.reset()
    for _ in range(5):
        env.step_members(torch.ones(3, dtype=torch.int64))
    env.reset_members(torch.tensor([False, True, False]))
    for _ in range(3):
        env.step_members(torch.ones(3, dtype=torch.int64))
    lengths = {}
    for index in range(3):
        env.render_index = index
        lengths[index] = len(env.history)
        last = env.history.frames(env.state)[-1]
        assert torch.equal(last.xyz, env.state.xyz[index])
    assert lengths == {0: 9, 1: 4, 2: 9}
    env.render_index = 1
    assert torch.equal(env.history.frames(env.state)[0].xyz, env.physics.initial_state(env.params, None).xyz[1])
    env.reset_members(torch.tensor([True, False, True]))
    assert len(env.history.states) == 4  # what member 1 still draws; older states dropped


def test_render_before_reset_is_an_error():
    with pytest.raises(RuntimeError, match="reset"):
        beacon_torch.make("lorenz-v0").render()


def test_save_animation_writes_every_frame(tmp_path):
    frames = [np.full((20, 30, 3), 40 * i, dtype=np.uint8) for i in range(5)]
    path = save_animation(frames, tmp_path / "sub" / "a.gif", fps=10)
    with Image.open(path) as im:
        assert im.n_frames == 5 and im.size == (30, 20)
    with pytest.raises(ValueError, match="no frames"):
        save_animation([], tmp_path / "b.gif")


@pytest.mark.parametrize("env_id", sorted(set(ALL_ENVS) - set(CHEAP_ENVS)))
def test_cavity_frames(env_id):
    env = make(env_id, 1, record_history=True)
    env.rollout(2)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.shape[2] == 3 and frame.std() > 10
    assert len(env.history) == 3


@pytest.mark.parametrize("env_id", CHEAP_ENVS)
def test_the_clock_runs_without_history(env_id):
    """Without record_history the frame still shows the member's time in its episode:
    the same state drawn at action 0 and at action 10 gives two different titles."""
    env = make(env_id, 1)
    env.reset()
    state = env.state
    env.set_state(state, count=0)
    at_start = env.render()
    env.set_state(state, count=10)
    later = env.render()
    assert (at_start != later).any()


def test_shkadov_without_history_draws_no_one_row_diagram(monkeypatch):
    """A space-time diagram needs the episode's states: without them the frame says how
    to get them instead of drawing a single row as if it were the whole episode."""
    import beacon_torch.render as render

    drawn = {}

    def spy(x, h_history, *args, space_time=True, **kwargs):
        drawn.update(rows=len(h_history), space_time=space_time)
        return np.zeros((2, 2, 3), dtype=np.uint8)

    monkeypatch.setattr(render, "shkadov_frame", spy)
    env = make("shkadov-v0", 1)
    env.reset()
    env.render()
    assert drawn == {"rows": 1, "space_time": False}
    env = make("shkadov-v0", 1, record_history=True)
    env.rollout(3)
    env.render()
    assert drawn == {"rows": 4, "space_time": True}


def test_the_docs_images_replace_their_own_files_and_never_write_through_a_link(tmp_path, monkeypatch):
    """docs/make_images.py regenerates its frames and animation: what stands at their
    names, its own earlier file or a link planted there, is removed and a new file
    written; the link's target is never created."""
    from docs import make_images as images

    out = tmp_path / "img"
    out.mkdir()
    (out / "lorenz-v0.png").write_bytes(b"an earlier frame")
    gif, target = out / "pinball-periodic-v0.gif", tmp_path / "elsewhere.gif"
    gif.symlink_to(target)  # dangling: nothing may be created through it
    # the pinball's episode stands in for two frames (the test's time)
    two = [np.full((4, 4, 3), value) for value in (0, 255)]
    monkeypatch.setattr(images, "pinball_animation", lambda path: save_animation(two, path))
    images.main({"lorenz-v0", "pinball-periodic-v0.gif"}, out)
    assert Image.open(out / "lorenz-v0.png").size[0] > 100
    assert not gif.is_symlink() and Image.open(gif).n_frames == 2 and not target.exists()
    assert sorted(p.name for p in out.iterdir()) == ["lorenz-v0.png", "pinball-periodic-v0.gif"]
