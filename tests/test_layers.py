"""The package's modules form layers: each imports only its own layer and those
below, and no chain of imports leads back to where it started. Read from the source
(every ``import`` statement, those inside functions included; those under
``TYPE_CHECKING`` are annotations only), so that a new import that breaks the order
fails here, not in a user's import error."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "beacon_torch"

# lowest first; a module not listed fails the test until it is placed
LAYERS = [
    # what needs nothing of the library: files, checks of received data, parameters,
    # the compiled-call helpers, figures, argument types, the numerics
    {"files", "received", "params", "compiled", "render", "arguments", "gym_ids", "numerics", "card"},
    # the core: the physics' interface and the step function, the env machinery and
    # its caches, starts and bookkeeping, the multi-agent layout
    {"cache", "starts", "history", "autograd", "core", "base", "episodes", "agents"},
    # the physics of each case
    {"envs"},
    # the registry and what works on any registered env
    {"registry", "__init__", "reference", "gradcheck", "bench", "threads"},
    # the adapters and the conformance kit that checks them
    {"gym", "sb3", "pettingzoo", "testing"},
    # the training layer and the policies it ships
    {"training", "pretrained"},
    # the command line
    {"cli", "__main__"},
]


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(path): path for path in PACKAGE.rglob("*.py")}


def layer(name: str) -> int:
    """The layer of a module: that of its top-level name in the package."""
    parts = name.split(".")
    top = parts[1] if len(parts) > 1 else "__init__"
    (index,) = [i for i, members in enumerate(LAYERS) if top in members] or [None]
    assert index is not None, f"{name} is in no layer: place it in LAYERS"
    return index


def type_checking_only(tree: ast.AST) -> set[int]:
    """The ids of the import nodes under ``if TYPE_CHECKING:``."""
    hidden = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and getattr(node.test, "id", getattr(node.test, "attr", "")) == "TYPE_CHECKING":
            hidden |= {id(n) for child in node.body for n in ast.walk(child)}
    return hidden


def imports(name: str, path: Path, known: set[str]) -> set[str]:
    """The package's modules that ``name`` imports, resolved to the deepest known one."""
    tree = ast.parse(path.read_text())
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    hidden = type_checking_only(tree)
    found = set()
    for node in ast.walk(tree):
        if id(node) in hidden:
            continue
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base for alias in node.names]
        else:
            continue
        found |= {t for t in targets if t in known and t != name}
    return found


def graph() -> dict[str, set[str]]:
    found = modules()
    return {name: imports(name, path, set(found)) for name, path in found.items()}


def test_no_module_imports_a_higher_layer():
    upward = [
        f"{name} (layer {layer(name)}) imports {target} (layer {layer(target)})"
        for name, targets in sorted(graph().items())
        for target in sorted(targets)
        if layer(target) > layer(name)
    ]
    assert upward == []


def test_the_numerics_and_the_core_import_no_env():
    for name, targets in graph().items():
        if name.startswith("beacon_torch.numerics"):
            assert {t for t in targets if not t.startswith("beacon_torch.numerics")} == set(), name
        if layer(name) <= 1:
            assert not any(t.startswith("beacon_torch.envs") for t in targets), name


def test_no_import_cycle():
    edges = graph()
    done, stack = set(), []

    def visit(name: str) -> None:
        if name in stack:
            cycle = stack[stack.index(name) :] + [name]
            raise AssertionError("import cycle: " + " -> ".join(cycle))
        if name in done:
            return
        stack.append(name)
        for target in sorted(edges[name]):
            visit(target)
        stack.pop()
        done.add(name)

    for name in sorted(edges):
        visit(name)


def test_the_graph_is_read_as_python_reads_it():
    """The checks above see what they claim: a known upward import and the package's
    lazy top-level names are found."""
    edges = graph()
    assert "beacon_torch.base" in edges["beacon_torch.envs.burgers"]
    assert "beacon_torch.training.evaluation" in edges["beacon_torch.cli"]  # imported inside a function
    assert "beacon_torch.base" not in edges["beacon_torch.history"]  # under TYPE_CHECKING only
    assert "beacon_torch.numerics.projection" in edges["beacon_torch.envs.cavity"]


def test_a_name_moved_to_another_layer_says_where_it_went():
    import pytest

    import beacon_torch.autograd
    from beacon_torch.training.env import horizon_bytes

    with pytest.raises(AttributeError, match="import it from beacon_torch.training.env"):
        beacon_torch.autograd.horizon_bytes  # noqa: B018
    assert callable(horizon_bytes)
