"""The package's modules form layers: each imports only its own layer and those
below, and no chain of imports leads back to where it started. Read from the source
(every ``import`` statement, those inside functions included; those under
``TYPE_CHECKING`` are annotations only), so that a new import that breaks the order
fails here, not in a user's import error."""

from __future__ import annotations

from tools import house

# the floors and the import graph, as tools/house.py draws them on docs/architecture.md

graph, layer, upward, cycles = house.graph, house.layer, house.upward, house.cycles


def test_no_module_imports_a_higher_layer():
    assert upward(graph()) == []


def test_the_numerics_and_the_core_import_no_env():
    for name, targets in graph().items():
        if name.startswith("beacon_torch.numerics"):
            assert {t for t in targets if not t.startswith("beacon_torch.numerics")} == set(), name
        if layer(name) <= 1:
            assert not any(t.startswith("beacon_torch.envs") for t in targets), name


def test_no_import_cycle_not_even_through_annotations():
    """No chain of imports leads back to where it started, counting those under
    ``TYPE_CHECKING`` (an annotation's import that closes a cycle is a cycle of the
    design, which a type checker or a later real import trips on)."""
    edges, hints = graph(), graph(annotations=True)
    assert cycles(edges) == []
    assert cycles({name: edges[name] | hints[name] for name in edges}) == []
    # the search finds a cycle where there is one
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_the_architecture_page_shows_the_house_as_it_is():
    """docs/architecture.md's figures (floors, rooms, arrows, circles, lines per floor,
    the classes each case defines) are what tools/house.py reads from the source now."""
    page = (house.ROOT / "docs" / "architecture.md").read_text()
    assert f"{house.BEGIN}\n{house.block()}\n{house.END}" in page, "run tools/house.py --page docs/architecture.md"


def test_a_case_and_its_physics_as_functions_need_no_torchrl():
    """The floors below the shell (the numerics, the core, the cases, the registry)
    import torch and never TorchRL or TensorDict, read from the source; and a process
    that imports a case module and takes an id's physics as functions has imported
    neither."""
    import subprocess
    import sys

    assert house.shell_imports() == []
    assert house.outside(house.PACKAGE / "base.py") >= {"torchrl", "tensordict"}  # the check sees them
    code = (
        "import sys, beacon_torch.envs.ks, beacon_torch; beacon_torch.functional('ks-v0', 2); "
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'torchrl', 'tensordict'}))"
    )
    ran = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert ran.stdout.strip() == "[]", ran.stdout
    code = "import sys, beacon_torch; beacon_torch.make('ks-v0'); print('torchrl' in sys.modules)"
    ran = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert ran.stdout.strip() == "True"  # the subprocess sees an import where there is one


def test_the_graph_is_read_as_python_reads_it():
    """The checks above see what they claim: a known upward import and the package's
    lazy top-level names are found."""
    edges = graph()
    assert "beacon_torch.core.physics" in edges["beacon_torch.envs.burgers"]
    assert "beacon_torch.training.evaluation" in edges["beacon_torch.cli"]  # imported inside a function
    assert "beacon_torch.base" not in edges["beacon_torch.history"]  # under TYPE_CHECKING only
    assert "beacon_torch.core.state" in graph(annotations=True)["beacon_torch.history"]
    assert "beacon_torch.numerics.projection" in edges["beacon_torch.envs.cavity"]


def test_a_name_moved_to_another_layer_says_where_it_went():
    import pytest

    import beacon_torch.autograd
    from beacon_torch.training.env import horizon_bytes

    with pytest.raises(AttributeError, match="import it from beacon_torch.training.env"):
        beacon_torch.autograd.horizon_bytes  # noqa: B018
    assert callable(horizon_bytes)


def _foreign_reads(source: str) -> list[str]:
    """``Class.attribute`` for each attribute of ``self`` a class's methods use that
    neither the class nor its bases in the same module set or define."""
    import ast

    classes = [n for n in ast.walk(ast.parse(source)) if isinstance(n, ast.ClassDef)]
    used = {
        c.name: [n for n in ast.walk(c) if isinstance(n, ast.Attribute) and getattr(n.value, "id", None) == "self"]
        for c in classes
    }
    own = {
        c.name: {n.attr for n in used[c.name] if isinstance(n.ctx, ast.Store)}
        | {n.name for n in c.body if isinstance(n, ast.FunctionDef)}
        | {t.id for n in c.body if isinstance(n, ast.Assign) for t in n.targets if isinstance(t, ast.Name)}
        | {n.target.id for n in c.body if isinstance(n, ast.AnnAssign) and isinstance(n.target, ast.Name)}
        for c in classes
    }
    out = []
    for c in classes:
        known = own[c.name].union(*(own.get(getattr(b, "id", None), set()) for b in c.bases))
        out += [f"{c.name}.{n.attr}" for n in used[c.name] if n.attr not in known]
    return out


def test_the_env_is_one_class_and_its_parts_read_only_their_own_state():
    """The shell is one class on TorchRL's EnvBase, not a class cut into mixins; its
    parts (the layout, the guard, the history, the saving functions) are objects or
    functions of their own: no method of theirs uses an attribute its own class does
    not set."""
    from torchrl.envs import EnvBase

    from beacon_torch.base import FlowEnv

    ours = [c for c in FlowEnv.__mro__ if c.__module__.startswith("beacon_torch")]
    assert ours == [FlowEnv] and FlowEnv.__bases__ == (EnvBase,)
    parts = ("layout.py", "core/checks.py", "core/saving.py", "history.py")
    strays = {name: _foreign_reads((house.PACKAGE / name).read_text()) for name in parts}
    assert not any(strays.values()), f"parts using what their class does not set: {strays}"
    # a mixin's use of the env's state is what the check finds
    mixin = "class Saving:\n    def state_dict(self):\n        return self._state, self.rng\n"
    assert _foreign_reads(mixin) == ["Saving._state", "Saving.rng"]


def test_seeds_are_drawn_and_derived_in_one_place():
    """Every seeded generator, a seed drawn for an env made without one and the seeds
    derived from an env's come from ``beacon_torch.seeds``; the env only re-seeds its
    two generators in place there."""
    import re

    pattern = re.compile(r"manual_seed\(|\.random_\(|7919|0x9E3779B97F4A7C15")
    found = [
        f"{path.relative_to(house.PACKAGE)}: {line.strip()}"
        for path in sorted(house.PACKAGE.rglob("*.py"))
        if path.name != "seeds.py"
        for line in path.read_text().splitlines()
        if pattern.search(line)
    ]
    assert found == [
        "base.py: self.rng.manual_seed(seed)",
        "base.py: self.action_rng.manual_seed(seeds.actions(seed))",
    ]
