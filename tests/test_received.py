"""Received files are read within bounds: a policy, a checkpoint, a replay buffer, a
cached or stored start and a summary are checked against what they claim to hold before
anything of their claimed size is allocated, and a run that cannot fit in memory is
refused before it allocates, with the estimate. Each case plants what a hostile or
damaged file would hold."""

import json
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

import beacon_torch
from beacon_torch import cache, pretrained, received, starts
from beacon_torch.envs import shkadov
from beacon_torch.training import report
from beacon_torch.training.config import GradConfig, TD3Config, configure
from beacon_torch.training.run import BadRun, buffer_folder, load_checkpoint
from recipes import grad, td3

from conftest import TD3, copy_run

POLICY = pretrained.shipped("ppo/lorenz-v0")


def copy_file(path: Path, to: Path) -> Path:
    shutil.copyfile(path, to)
    return to


def add_zeros(file: Path, nbytes: int, compression: int) -> None:
    """Append an entry of ``nbytes`` zeros to a torch file's archive, written in chunks
    (a 2 GiB entry deflates to a few MB)."""
    chunk = bytes(2**24)
    with zipfile.ZipFile(file, "a", compression=compression) as archive:
        folder = archive.namelist()[0].split("/")[0]
        with archive.open(f"{folder}/data/padding", "w", force_zip64=True) as entry:
            for _ in range(nbytes // len(chunk)):
                entry.write(chunk)


# ---------------------------------------------------------------- torch files
def test_a_policy_with_a_compressed_entry_is_refused_before_it_expands(tmp_path):
    """The audit's 2.1 MB policy file whose zip holds an unused entry of 2 GiB of
    deflated zeros: refused without expanding it, the loading process staying small."""
    file = copy_file(POLICY, tmp_path / "policy.pt")
    add_zeros(file, 2**31, zipfile.ZIP_DEFLATED)
    assert file.stat().st_size < 5 * 2**20
    probe = (
        "from beacon_torch import pretrained\n"
        "from beacon_torch.bench import _resident_mb\n"
        "try:\n"
        f"    pretrained.load_file({str(file)!r})\n"
        "except ValueError as err:\n"
        "    print(err)\n"
        "print(int(_resident_mb()))\n"  # this program's own peak (not its forking parent's)
    )
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300)
    message, peak_mb = done.stdout.strip().splitlines()
    assert message.startswith(f"{file}: its entry ") and "/data/padding' is compressed" in message, done.stdout
    assert int(peak_mb) < 1000, f"the refusal peaked at {peak_mb} MB"


def test_a_checkpoint_with_a_compressed_entry_is_refused_by_every_command(ppo_run, tmp_path, capsys):
    from beacon_torch.cli import main as cli

    run = copy_run(ppo_run, tmp_path / "run")
    add_zeros(run / "checkpoint.pt", 2**26, zipfile.ZIP_DEFLATED)
    with pytest.raises(received.BadFile, match="is compressed"):
        load_checkpoint(run)
    assert cli(["eval", str(run), "--no-gif", "--num-envs", "1"]) == 2
    err = capsys.readouterr().err
    assert "checkpoint.pt" in err and "compressed" in err and len(err.strip().splitlines()) == 1


def test_stored_bytes_that_no_value_uses_are_refused(tmp_path):
    file = copy_file(POLICY, tmp_path / "policy.pt")
    add_zeros(file, 2**24, zipfile.ZIP_STORED)
    with pytest.raises(ValueError, match=f"{file}: 16,777,216 of its .* stored bytes belong to no value"):
        pretrained.load_file(file)


def test_a_tensor_that_repeats_one_stored_value_is_refused(tmp_path):
    """A tensor of a billion elements over one stored number (a zero stride): every use
    of it would allocate the billion."""
    record, _, _ = pretrained._read(POLICY)
    weights = dict(record["weights"])
    key = next(iter(weights))
    weights[key] = torch.zeros(1).expand(10**9)
    file = tmp_path / "policy.pt"
    torch.save({**record, "weights": weights}, file)
    assert file.stat().st_size < 2**20
    with pytest.raises(ValueError, match="reaches past its stored values"):
        pretrained.load_file(file)


def test_a_file_that_would_run_code_is_refused_without_torchs_advice(tmp_path):
    class Payload:
        def __reduce__(self):
            return (print, ("ran",))

    file = tmp_path / "policy.pt"
    torch.save({"env": "lorenz-v0", "payload": Payload()}, file)
    with pytest.raises(ValueError) as err:
        pretrained.load_file(file)
    text = str(err.value)
    assert text.startswith(f"{file}: not a policy file") and "could run code" in text
    assert "weights_only" not in text and "\n" not in text
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(bytes(range(256)) * 64)
    with pytest.raises(ValueError, match=f"{garbage}: not a policy file") as err:
        pretrained.load_file(garbage)
    assert "weights_only" not in str(err.value)


def test_weights_of_another_shape_or_beyond_float32_are_refused(tmp_path):
    record, _, _ = pretrained._read(POLICY)
    key = next(k for k, v in record["weights"].items() if v.ndim == 2)
    for value, words in (
        (torch.zeros(3, 3), f"{key} has shape \\(3, 3\\)"),
        # finite in float64, infinite once cast to the network's float32
        (torch.full_like(record["weights"][key], 1e300, dtype=torch.float64), "non-finite values in torch.float32"),
    ):
        file = tmp_path / "policy.pt"
        torch.save({**record, "weights": {**record["weights"], key: value}}, file)
        with pytest.raises(ValueError, match=words):
            pretrained.load_file(file)
        file.unlink()


def corrupted(data: bytes, edits: list[tuple[int, int]]) -> bytes:
    out = bytearray(data)
    for position, value in edits:
        out[position % len(out)] = value
    return bytes(out)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
# an entry name made invalid UTF-8 (zipfile's UnicodeDecodeError named no file)
@example(edits=[(22615, 128)], cut=None)
@given(
    edits=st.lists(st.tuples(st.integers(0, 10**7), st.integers(0, 255)), min_size=1, max_size=6),
    cut=st.one_of(st.none(), st.integers(0, 10**7)),
)
def test_any_damage_to_a_policy_file_is_one_clear_error_or_a_sound_policy(tmp_path, edits, cut):
    data = corrupted(POLICY.read_bytes(), edits)
    if cut is not None:
        data = data[: cut % len(data)]
    file = tmp_path / "damaged.pt"
    file.write_bytes(data)
    try:
        policy = pretrained.load_file(file)
    except (ValueError, FileNotFoundError) as err:
        assert str(err).startswith(str(file)) and "\n" not in str(err)
    else:
        out = policy(beacon_torch.make("lorenz-v0", 2).reset())
        assert torch.isfinite(out["action"]).all()


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    shapes=st.dictionaries(
        st.sampled_from(["h", "q", "x"]), st.lists(st.integers(0, 3000), min_size=0, max_size=2), max_size=3
    )
)
def test_a_cached_state_of_other_fields_or_shapes_is_computed_again(tmp_path, shapes):
    like = shkadov.Film(h=torch.ones(2900, dtype=torch.float64), q=torch.ones(2900, dtype=torch.float64))
    file = tmp_path / "film.pt"
    torch.save({k: torch.zeros(s) for k, s in shapes.items()}, file)
    fits = set(shapes) == {"h", "q"} and all(s == [2900] for s in shapes.values())
    if fits:
        assert cache._load(file, like) is not None
    else:
        with pytest.warns(UserWarning, match="computing it again"):
            assert cache._load(file, like) is None


def test_a_checkpoint_holding_more_than_its_networks_can_is_refused(ppo_run, tmp_path):
    run = copy_run(ppo_run, tmp_path / "run")
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    state["modules"]["critic"]["extra"] = torch.zeros(2**21)  # 8 MiB beside 64-wide networks
    torch.save(state, run / "checkpoint.pt")
    with pytest.raises(BadRun, match="MiB of tensors, more than a run of networks 64 wide on vortex-v0 can"):
        load_checkpoint(run)


# ---------------------------------------------------------------- replay buffers
def forge_buffer(run: Path, key: str, shape: list, dtype: str | None = None) -> None:
    """Describe the buffer's ``key`` with another shape (and dtype), its file grown to
    match and the checkpoint's record of the files too: only the description can tell."""
    meta = buffer_folder(run) / "storage" / "meta.json"
    entries = json.loads(meta.read_text())
    entries[key] = {**entries[key], "shape": shape, **({"dtype": dtype} if dtype else {})}
    meta.write_text(json.dumps(entries))
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    files = state["counters"]["buffer_files"]
    files["storage/meta.json"] = meta.stat().st_size
    memmap = buffer_folder(run) / "storage" / f"{key}.memmap"
    size = int(np.prod(shape)) * {"torch.float64": 8}.get(dtype, 4)
    with memmap.open("r+b") as f:
        f.truncate(min(size, 2**20))  # sparse files would do; the size recorded is what is compared
    files[f"storage/{key}.memmap"] = memmap.stat().st_size
    torch.save(state, run / "checkpoint.pt")


@pytest.mark.parametrize(
    "key, shape, dtype, words",
    [
        ("observation", [1280, 5_000_000], None, "not 256 transitions of at most 8 values"),
        ("observation", [256, 8], "torch.float64", "of dtype 'torch.float64'"),
    ],
)
def test_a_forged_buffer_description_is_refused_before_anything_is_allocated(
    td3_run, tmp_path, key, shape, dtype, words
):
    run = copy_run(td3_run, tmp_path / "run")
    forge_buffer(run, key, shape, dtype)
    with pytest.raises(BadRun, match=words):
        td3.main(configure(TD3Config, "vortex-v0", out=str(run), resume=True, **{**TD3, "frames": 320}))


def test_corrupt_buffer_values_and_optimiser_states_are_named_corrupt(td3_run, tmp_path):
    run = copy_run(td3_run, tmp_path / "run")
    memmap = buffer_folder(run) / "storage" / "observation.memmap"
    data = bytearray(memmap.read_bytes())
    data[40:48] = b"\xff" * 8  # a NaN among the observations
    memmap.write_bytes(bytes(data))
    more = {**TD3, "frames": 320}
    with pytest.raises(BadRun, match="replay buffer is corrupt \\(observation has non-finite values\\)"):
        td3.main(configure(TD3Config, "vortex-v0", out=str(run), resume=True, **more))
    for change, words in (
        (lambda s: s["exp_avg_sq"].neg_().sub_(1.0), "a negative second moment"),
        (lambda s: s["exp_avg"].add_(1e6), "moments no sequence of gradients gives"),
        (lambda s: s.update(exp_avg=torch.zeros(3)), "exp_avg of shape \\(3,\\)"),
    ):
        run = copy_run(td3_run, tmp_path / f"run-{len(words)}")
        state = torch.load(run / "checkpoint.pt", weights_only=True)
        change(state["modules"]["critic_optim"]["state"][0])
        torch.save(state, run / "checkpoint.pt")
        with pytest.raises(BadRun, match=f"the state of 'critic_optim' is corrupt \\({words}"):
            td3.main(configure(TD3Config, "vortex-v0", out=str(run), resume=True, **more))


# ---------------------------------------------------------------- memory before allocating
def test_a_horizon_or_a_buffer_beyond_memory_is_refused_with_its_estimate(tmp_path):
    cfg = configure(
        GradConfig, "burgers-v0", out=str(tmp_path / "grad"), num_envs=64, horizon=1_000_000, progress=False
    )
    with pytest.raises(
        ValueError, match="the graph of 1000000 differentiated actions of 64 members needs about .* GiB"
    ):
        grad.main(cfg)
    assert not (tmp_path / "grad" / "checkpoint.pt").exists()
    with pytest.raises(ValueError, match="a replay buffer of 1,000,000,000,000 transitions needs about .* GiB"):
        configure(TD3Config, "vortex-v0", frames=10**12)
    # what the recorded campaigns use fits
    configure(GradConfig, "cylinder-v0")
    configure(TD3Config, "rayleigh-v0")


def test_the_graph_estimate_is_what_a_differentiated_horizon_keeps():
    from beacon_torch.autograd import saved_storages
    from beacon_torch.training.env import horizon_bytes

    env = beacon_torch.make("burgers-v0", 4, differentiable=True)
    env.reset()
    actions = torch.zeros(5, 4, 1, requires_grad=True)
    with saved_storages() as saved:
        for a in actions:
            env.step_members(a)
    kept = sum(saved.values())
    estimate = horizon_bytes("burgers-v0", 5, 4)
    assert 0.8 * kept < estimate < 1.25 * kept
    # the first 2 actions kept whole, the other 3 recomputed: as saved, within the
    # recomputed action's graph the estimate adds for the backward pass
    env = beacon_torch.make("burgers-v0", 4, differentiable=True, grad_checkpoint=True, grad_checkpoint_after=2)
    env.reset()
    with saved_storages() as saved:
        for a in actions:
            env.step_members(a)
    partly = sum(saved.values())
    estimate = horizon_bytes("burgers-v0", 5, 4, grad_checkpoint=True, kept=2)
    assert 0.3 * kept < 0.8 * partly < estimate - kept / 5 < 1.25 * partly < 0.6 * kept


# ---------------------------------------------------------------- text and JSON records
def test_a_damaged_stored_start_is_refused_naming_its_file(tmp_path, monkeypatch):
    table = (starts.PACKAGE_DATA / "sloshing-published-start.dat").read_text().splitlines()
    (tmp_path / "sloshing-published-start.dat").write_text("\n".join(table[:100]) + "\n")
    monkeypatch.setattr(starts, "PACKAGE_DATA", tmp_path)
    monkeypatch.setattr(cache, "_memory", {})  # a process that never read the file
    with pytest.raises(ValueError, match="sloshing-published-start.dat: a table of 100 rows of 3 numbers"):
        beacon_torch.make("sloshing-v0", 1).reset()
    (tmp_path / "sloshing-published-start.dat").write_text("1 2 3\n" * 10**6)
    with pytest.raises(ValueError, match="bytes, more than a stored start of sloshing holds"):
        beacon_torch.make("sloshing-v0", 1).reset()


def test_a_summary_larger_than_any_summary_is_refused_unread(tmp_path):
    file = tmp_path / "summary.json"
    file.write_text(json.dumps({"seeds": [{"eval": 1.0}] * 200_000}))
    with pytest.raises(ValueError, match=f"{file}: .* bytes, more than a summary holds"):
        report.read(file)


@settings(max_examples=60, deadline=None)
@given(
    grads=st.lists(
        st.lists(st.floats(-1e6, 1e6, allow_subnormal=True), min_size=3, max_size=3), min_size=1, max_size=40
    ),
    nadam=st.booleans(),
    scalar=st.booleans(),
)
def test_an_optimiser_state_that_gradients_reach_is_never_called_corrupt(grads, nadam, scalar):
    """The bound the check holds Adam's moments to holds for any sequence of
    gradients, however small or large, on a vector or on a scalar parameter (SAC's
    entropy weight, whose moments are 0-dim tensors of either sign)."""
    from beacon_torch.training.run import load_optimiser

    kind = torch.optim.NAdam if nadam else torch.optim.Adam
    shape = () if scalar else (3,)
    p = torch.nn.Parameter(torch.zeros(shape))
    optim = kind([p], lr=1e-3)
    for g in grads:
        p.grad = torch.tensor(g[0] if scalar else g)
        optim.step()
    load_optimiser(kind([torch.nn.Parameter(torch.zeros(shape))], lr=1e-3), optim.state_dict(), "the state")
