"""The maintainer's driver publishes only what it checks: the pair, the algorithm, the
budget and the scores come from the seeds' checkpoints, evaluated again, never from
the summary beside them; a summary that says otherwise is refused in one line naming
it, and nothing in the repository changes."""

import copy
import dataclasses
import json
import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import beacon_torch
from beacon_torch.training.config import PPOConfig, configure
from beacon_torch.training.evaluation import summarise
from recipes import ppo
from tools import reproduce

SETTINGS = dict(frames=400, n_rollout=200, num_envs=1, epochs=1, progress=False, logger="csv")


@pytest.fixture(scope="module")
def pair(tmp_path_factory, short_lorenz):
    """A summarised PPO pair of two seeds (sixteen short episodes each)."""
    root = tmp_path_factory.mktemp("results") / "ppo" / short_lorenz
    for seed in (0, 1):
        ppo.main(configure(PPOConfig, short_lorenz, out=str(root / f"seed{seed}"), seed=seed, **SETTINGS))
    summarise(root, num_envs=1)
    return root


@pytest.fixture
def repo(tmp_path):
    """A repository whose recorded budget for the pair is the pair's own."""
    recorded, images, shipped = tmp_path / "recorded", tmp_path / "img", tmp_path / "shipped"
    (recorded / "ppo").mkdir(parents=True)
    earlier = {"algo": "ppo", "env": "short-lorenz-v0", "frames": 400, "uncontrolled": 1.0, "wall_s_per_seed": 1.0}
    (recorded / "ppo" / "short-lorenz-v0.json").write_text(json.dumps({**earlier, "seeds": [{"eval": -1.0}]}))
    (shipped / "ppo").mkdir(parents=True)
    (shipped / "ppo" / "short-lorenz-v0.pt").write_bytes(b"the shipped policy")
    return recorded, images, shipped


def forged(pair, tmp_path, change) -> tuple:
    """A copy of ``pair`` whose summary has ``change`` applied."""
    import shutil

    root = tmp_path / "runs" / "ppo" / "short-lorenz-v0"
    shutil.copytree(pair, root)
    summary = json.loads((root / "summary.json").read_text())
    change(summary)
    (root / "summary.json").write_text(json.dumps(summary))
    return root


@pytest.mark.parametrize(
    "change, words",
    [
        (lambda s: s.update(env="burgers-v0"), "its env 'burgers-v0' is not its seeds' \\('short-lorenz-v0'\\)"),
        (lambda s: s.update(algo="td3"), "its algo 'td3' is not its seeds' \\('ppo'\\)"),
        (lambda s: s.update(frames=10**9), "its frames 1000000000 is not its seeds' \\(400\\)"),
        (lambda s: s["seeds"][0].update(eval=1e3), "seed0's eval 1000.0 is not what its checkpoint gives"),
        (lambda s: s["seeds"][1].update(frames=10**9), "seed1's frames 1000000000 is not what its checkpoint"),
        (lambda s: s["seeds"].pop(), "its seeds \\['seed0'\\] are not the run's"),
        (lambda s: s.update(eval_mean=5.0), "its eval_mean 5.0 is not what its seeds give"),
        (lambda s: s["seeds"][1].update(test=1e3), "seed1's test 1000.0 is not what its checkpoint gives"),
        (lambda s: s["seeds"][0].pop("test"), "not a summary of trained seeds \\(test-set scores must be finite"),
        (lambda s: s.update(test_uncontrolled=0.0), "its test_uncontrolled 0.0 is not what its seeds give"),
        (lambda s: s["seeds"][0]["curve"]["score"].__setitem__(-1, 1e6), "seed0's curve .* is not what its checkpoint"),
        (lambda s: s["seeds"][1]["curve"].update(frames=[0] * 300), "not a summary of trained seeds \\(a seed's"),
    ],
)
def test_a_forged_summary_is_refused_and_the_repository_left_alone(pair, repo, tmp_path, change, words):
    recorded, images, shipped = repo
    root = forged(pair, tmp_path, change)
    with pytest.raises(ValueError, match=f"{root / 'summary.json'}: {words}") as err:
        reproduce.publish(root, recorded, images, shipped)
    assert "\n" not in str(err.value)
    assert (shipped / "ppo" / "short-lorenz-v0.pt").read_bytes() == b"the shipped policy"
    assert json.loads((recorded / "ppo" / "short-lorenz-v0.json").read_text())["frames"] == 400
    assert not images.exists()


def test_a_true_summary_is_published_from_its_checkpoints(pair, repo, tmp_path, capsys):
    recorded, images, shipped = repo
    root = forged(pair, tmp_path, lambda s: s.update(png="/elsewhere/curve.png"))
    reproduce.publish(root, recorded, images, shipped)
    published = json.loads((recorded / "ppo" / "short-lorenz-v0.json").read_text())
    true = json.loads((pair / "summary.json").read_text())
    assert [s["eval"] for s in published["seeds"]] == [s["eval"] for s in true["seeds"]]
    # each seed's training curve: its episodes' scores against transitions and minutes
    for seed in published["seeds"]:
        curve = seed["curve"]
        assert len(curve["frames"]) == len(curve["score"]) == len(curve["wall_s"]) > 0
        assert curve["frames"] == sorted(curve["frames"]) and curve["frames"][-1] <= 400
        assert all(b >= a >= 0 for a, b in zip(curve["wall_s"][:-1], curve["wall_s"][1:], strict=True))
    assert published["png"] != "/elsewhere/curve.png" and (images / "ppo" / "short-lorenz-v0.png").is_file()
    from beacon_torch import pretrained

    assert pretrained.load_file(shipped / "ppo" / "short-lorenz-v0.pt", "short-lorenz-v0") is not None
    # from the command line: a forged pair is one line and status 2
    forged_root = forged(pair, tmp_path / "again", lambda s: s.update(env="burgers-v0"))
    with pytest.raises(SystemExit) as exit_:
        reproduce.main(["publish", str(forged_root), "--doc", str(tmp_path / "results.md")])
    err = capsys.readouterr().err
    # one line (the progress bars of the re-evaluation return to its start with \r)
    assert exit_.value.code == 2 and "summary.json: its env 'burgers-v0'" in err and len(err.strip().split("\n")) == 1


def test_a_pair_of_an_env_without_a_paper_score_is_published_and_listed_by_its_own_scores(
    pair, repo, tmp_path, monkeypatch
):
    """A case from beyond the paper has no paper score on its card: its pair is
    published all the same (checked like any other), and the results page lists its
    scores beside no control outside the normalised protocol, which still refuses it."""
    from beacon_torch.training import report

    recorded, images, shipped = repo
    spec = beacon_torch.registry.ENVS["short-lorenz-v0"]  # a card without the paper's score
    monkeypatch.setitem(
        beacon_torch.registry.ENVS,
        "short-lorenz-v0",
        dataclasses.replace(spec, card=dataclasses.replace(spec.card, paper_ppo=None)),
    )
    with pytest.raises(ValueError, match="its eval_mean 5.0 is not what its seeds give"):
        reproduce.publish(
            forged(pair, tmp_path / "forged", lambda s: s.update(eval_mean=5.0)), recorded, images, shipped
        )
    reproduce.publish(forged(pair, tmp_path, lambda s: None), recorded, images, shipped)
    file = recorded / "ppo" / "short-lorenz-v0.json"
    published = json.loads(file.read_text())
    assert (shipped / "ppo" / "short-lorenz-v0.pt").read_bytes() != b"the shipped policy"
    page = tmp_path / "results.md"
    page.write_text(f"# Results\n\n{reproduce.BEGIN}\nold\n{reproduce.END}\n")
    text = reproduce.write_results_page(recorded, page, images).read_text()
    scores = [s["eval"] for s in published["seeds"]]
    (row,) = [line for line in text.splitlines() if line.startswith("| short-lorenz-v0 | ppo | own start | 2 |")]
    assert f"{report.iqm(scores):.4g} ({', '.join(f'{x:.4g}' for x in scores)})" in row
    assert f"| {published['uncontrolled']:.4g} | 400 |" in row and "normalised scores" not in text
    with pytest.raises(ValueError, match="no reference on its card"):
        report.read(file)


TRUE = {
    "algo": "ppo",
    "env": "short-lorenz-v0",
    "frames": 400,
    "eval_mean": -1.5,
    "train_mean": -1.7,
    "wall_s_per_seed": 12.0,
    "uncontrolled": -2.1,
    "test_mean": -1.8,
    "test_uncontrolled": -2.4,
    "seeds": [
        {"seed": "seed0", "frames": 400, "eval": -1.4, "train_tail": -1.6, "uncontrolled": -2.1, "wall_s": 11.0},
        {"seed": "seed1", "frames": 400, "eval": -1.6, "train_tail": -1.8, "uncontrolled": -2.1, "wall_s": 13.0},
    ],
}
for seed, test in zip(TRUE["seeds"], (-1.7, -1.9), strict=True):
    seed.update(
        test=test, test_uncontrolled=-2.4, curve={"frames": [200, 400], "score": [-2.0, -1.5], "wall_s": [5.0, 11.0]}
    )
FIELDS = [
    "algo",
    "env",
    "frames",
    "eval_mean",
    "train_mean",
    "wall_s_per_seed",
    "uncontrolled",
    "test_mean",
    "test_uncontrolled",
    "seeds",
]
SEED_FIELDS = ["seed", "frames", "eval", "train_tail", "uncontrolled", "wall_s", "test", "test_uncontrolled", "curve"]
VALUES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**12), 10**12),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from(["ppo", "td3", "short-lorenz-v0", "burgers-v0", "seed0", "seed1", "seed2"]),
)


@settings(max_examples=300, deadline=None)
@given(
    field=st.one_of(st.sampled_from(FIELDS), st.tuples(st.integers(0, 1), st.sampled_from(SEED_FIELDS))),
    value=VALUES,
)
def test_any_forged_field_of_a_summary_is_found(field, value):
    summary = copy.deepcopy(TRUE)
    if isinstance(field, tuple):
        original = summary["seeds"][field[0]][field[1]]
        summary["seeds"][field[0]][field[1]] = value
    else:
        original = summary[field]
        summary[field] = value
    name = field[1] if isinstance(field, tuple) else field
    if name in ("algo", "env", "frames", "seeds", "seed", "curve"):
        same = type(value) is type(original) and value == original
    else:  # a score or a time: the same number, written as an int or a float
        number = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        same = number and math.isclose(value, original, rel_tol=1e-6, abs_tol=1e-9)
    found = reproduce.mismatch(summary, TRUE)
    assert (found == "") == same, (field, value, found)


def test_a_pairs_uncontrolled_episodes_run_once_for_all_its_seeds(pair, monkeypatch):
    """The seeds of a pair trained on the same physics: their evaluations share the
    uncontrolled episodes (the env's own starts and the held-out set), run once each and
    equal to what a seed's own evaluation gives."""
    from beacon_torch.training import evaluation

    runs = []
    null_policy = evaluation.episodes.null_policy
    monkeypatch.setattr(evaluation.episodes, "null_policy", lambda env: runs.append(env) or null_policy(env))
    summary = evaluation.summary_of(pair, num_envs=1)
    assert len(summary["seeds"]) == 2 and len(runs) == 2
    alone = evaluation.evaluate_run(pair / "seed1", num_envs=1)
    held = evaluation.evaluate_run(pair / "seed1", num_envs=8, starts="test")
    assert [s["uncontrolled"] for s in summary["seeds"]] == [alone["uncontrolled"]] * 2
    assert [s["test_uncontrolled"] for s in summary["seeds"]] == [held["uncontrolled"]] * 2
    # each test episode recorded, under control and without, with the env's diagnostics
    for s in summary["seeds"]:
        assert s["test_uncontrolled_episodes"] == held["uncontrolled_episodes"]
        assert sum(s["test_episodes"]["score"]) / 8 == pytest.approx(s["test"])
        assert len(s["test_episodes"]["score"]) == 8 and set(s["test_episodes"]) > {"score"}
    assert summary["seeds"][1]["test_episodes"] == held["episodes"]
    with pytest.raises(ValueError, match="a known uncontrolled score draws no side-by-side"):
        evaluation.evaluate_run(pair / "seed1", num_envs=1, figure="f.png", uncontrolled=1.0)


def test_the_kept_campaigns_are_unpublished_run_folders_a_resume_reads_as_their_readme_says():
    """A campaign kept in the repository between sessions: each seed's folder holds a
    checkpoint that loads as a run of its folder's algorithm, env and seed, its logs
    end at the checkpoint, the README lists exactly what is there, and no kept pair is
    a published one (a published campaign's folders go)."""
    from beacon_torch.training.run import load_checkpoint, read_log

    root = reproduce.ROOT / "experiments" / "campaigns"
    readme = (root / "README.md").read_text()
    listed = {
        tuple(cell.strip(" `") for cell in line.strip("|").split("|"))
        for line in readme.splitlines()
        if line.startswith("| `")
    }
    kept = set()
    for checkpoint in sorted(root.glob("*/*/seed*/checkpoint.pt")):
        folder = checkpoint.parent
        algo, env_id, seed = folder.parts[-3:]
        state = load_checkpoint(folder)
        assert (state["algo"], state["env"], f"seed{state['config']['seed']}") == (algo, env_id, seed)
        # every update logs its reward; an episode's score only when one ended
        logs = {name: read_log(folder / algo / "scalars" / f"{name}.csv") for name in ("reward", "episode_score")}
        assert logs["reward"] and logs["reward"][-1][0] == state["frames"], folder
        # a run stops at the first update that reaches its budget (its last may pass it)
        assert len(logs["reward"]) < 2 or logs["reward"][-2][0] < state["config"]["frames"], folder
        assert logs["episode_score"] and logs["episode_score"][-1][0] <= state["frames"], folder
        assert not (reproduce.RECORDED / algo / f"{env_id}.json").exists(), f"{algo}/{env_id} is published"
        kept.add((f"{algo}/{env_id}", seed, f"{state['frames']:,}", f"{state['config']['frames']:,}"))
    # planned episodes under way (recipes/mpc.py's checkpoint, read within bounds on resume)
    for checkpoint in sorted(root.glob("mpc/*/mpc-checkpoint.pt")):
        saved = torch.load(checkpoint, weights_only=True)
        env_id = checkpoint.parent.name
        assert saved["env_id"] == env_id and saved["settings"]["env"] == env_id
        length = saved["settings"]["actions"] or beacon_torch.registry.env_spec(env_id).physics.episode_length
        assert 0 < saved["actions_done"] < length and saved["stats"]["actions"] == saved["actions_done"]
        assert not (checkpoint.parent / "mpc.json").exists(), "a finished planner's record is kept as a result"
        kept.add((f"mpc/{env_id}", saved["settings"]["starts"], f"{saved['actions_done']:,}", f"{length:,}"))
    assert listed == kept


def test_an_evaluation_compiles_the_2d_flows_unless_told_not_to(monkeypatch):
    from beacon_torch.training.evaluation import evaluation_compiles

    monkeypatch.delenv("BEACON_TORCH_COMPILE", raising=False)
    assert evaluation_compiles("rbc2d-easy-v0") and evaluation_compiles("cylinder-v0")
    assert not evaluation_compiles("lorenz-v0") and not evaluation_compiles("burgers-v0")
    monkeypatch.setenv("BEACON_TORCH_COMPILE", "0")
    assert not evaluation_compiles("rbc2d-easy-v0")
