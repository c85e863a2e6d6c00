"""A damaged cache heals: reported, computed again, never a broken ``make()``."""

import warnings

import pytest
import torch

import beacon_torch
from beacon_torch import cache

L = 0.5  # a small tank: its excited state is computed in a moment


def damaged_files(path):
    yield "garbage", lambda: path.write_bytes(b"not a torch file")
    yield "truncated", lambda: path.write_bytes(path.read_bytes()[:100])
    yield (
        "non-finite",
        lambda: torch.save(
            {k: torch.full_like(v, float("nan")) for k, v in torch.load(path, weights_only=True).items()}, path
        ),
    )
    yield (
        "wrong shape",
        lambda: torch.save({k: v[..., :3] for k, v in torch.load(path, weights_only=True).items()}, path),
    )
    yield "a pickle that runs code", lambda: torch.save({"h": _Payload()}, path)


class _Payload:
    def __reduce__(self):
        return (print, ("this must never run",))


@pytest.mark.parametrize("damage", ["garbage", "truncated", "non-finite", "wrong shape", "a pickle that runs code"])
def test_a_damaged_cache_file_is_reported_and_computed_again(damage, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("BEACON_TORCH_CACHE", str(tmp_path))
    monkeypatch.setattr(cache, "_memory", {})
    env = beacon_torch.make("sloshing-v0", 2, L=L)
    env.reset()
    (path,) = tmp_path.glob("sloshing-excited-*.pt")
    good = torch.load(path, weights_only=True)
    dict(damaged_files(path))[damage]()
    monkeypatch.setattr(cache, "_memory", {})  # a later process
    with pytest.warns(UserWarning, match="computing it again"):
        env = beacon_torch.make("sloshing-v0", 2, L=L)
        td = env.reset()
    assert (
        td["observation"].shape == env.observation_spec["observation"].shape and torch.isfinite(td["observation"]).all()
    )
    healed = torch.load(path, weights_only=True)
    assert all(torch.equal(healed[k], good[k]) for k in good)  # the file is whole again
    assert "this must never run" not in capsys.readouterr().out
    monkeypatch.setattr(cache, "_memory", {})
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # healed: no warning the next time
        beacon_torch.make("sloshing-v0", 2, L=L).reset()


def test_generating_a_start_says_so_before_and_after(tmp_path, monkeypatch, capsys):
    """A start generated from the equations can take minutes: the user is told before
    it starts and how long it took, once; a later make reads the cache silently."""
    monkeypatch.setenv("BEACON_TORCH_CACHE", str(tmp_path))
    monkeypatch.setattr(cache, "_memory", {})
    beacon_torch.make("sloshing-v0", 1, L=L).reset()
    err = capsys.readouterr().err
    assert "generating the sloshing-excited start (L=0.5" in err and str(tmp_path) in err
    assert "sloshing-excited generated in" in err
    monkeypatch.setattr(cache, "_memory", {})
    beacon_torch.make("sloshing-v0", 1, L=L).reset()
    assert "generating" not in capsys.readouterr().err


def test_a_start_is_read_once_per_process_and_copied_once_per_dtype(monkeypatch):
    """The one memo of starts: envs of a case share its developed start, read from its
    file once and copied once per device and dtype; none keeps a copy of its own."""
    monkeypatch.setattr(cache, "_memory", {})
    reads = []
    load = cache._load
    monkeypatch.setattr(cache, "_load", lambda *args: reads.append(args[0].name) or load(*args))
    first, second = beacon_torch.make("ks-v0", 2), beacon_torch.make("ks-v0", 3)
    first.reset(), second.reset()
    assert len(reads) == 1 and reads[0].startswith("ks-attractor-")
    assert first.physics.starts().data_ptr() == second.physics.starts().data_ptr()
    double = beacon_torch.make("ks-v0", 2, dtype="float64")
    double.reset()
    assert len(reads) == 1 and double.physics.starts().dtype == torch.float64
    # the process's copies: the file's float64 bank (which float64 envs share) and one in float32
    assert sorted(str(key[-1]) for key in cache._memory if key[0].startswith("ks-attractor-")) == [
        "ks-attractor-" + reads[0].removeprefix("ks-attractor-"),
        "torch.float32",
    ]
