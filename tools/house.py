"""The house's figures: the package's modules as rooms on floors (its layers), their
imports as arrows, the scripts' rooms above it, and the classes each case defines;
written as the tables of docs/architecture.md.

    .venv/bin/python tools/house.py                 # print the tables
    .venv/bin/python tools/house.py --page docs/architecture.md

The imports are read from the source as Python reads them: every ``import`` statement,
those inside functions included. Those under ``if TYPE_CHECKING:`` are annotations
only; they are counted apart, and a cycle through one is a cycle of the house too.
``tests/test_layers.py`` holds the package to the floors below.
"""

from __future__ import annotations

import argparse
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "beacon_torch"
BEGIN, END = "<!-- the house: tools/house.py -->", "<!-- end of the house -->"

# the floors, lowest first, each named by the top-level names of the package it holds;
# a module on no floor fails tests/test_layers.py until it is placed
LAYERS = [
    # what needs nothing of the library: files, checks of received data, parameters,
    # the compiled-call helpers, figures, argument types, the numerics
    ("foundations", {"files", "received", "params", "compiled", "render", "arguments", "gym_ids", "seeds", "numerics"}),
    # the core: the physics' interface, the step function, the card, the state's
    # vocabulary, the checks and saved state of an env, cached starts, the history
    ("core", {"cache", "starts", "history", "autograd", "core"}),
    # the physics of each case, its card and its frame
    ("cases", {"envs"}),
    # the ids: what each names, and the physics of an id as functions
    ("registry", {"registry", "__init__", "reference", "threads"}),
    # the TorchRL shell every env is (FlowEnv, make, the layouts) and what steps it
    ("shell", {"base", "layout", "episodes", "gradcheck", "bench"}),
    # the adapters and the conformance kit that checks them
    ("adapters", {"gym", "sb3", "pettingzoo", "testing"}),
    # the training layer and the policies it ships
    ("training", {"training", "pretrained"}),
    # the command line
    ("commands", {"cli", "__main__"}),
]
# the floors that import torch and never TorchRL: a case and its physics as functions
# need nothing of the shell
TORCH_ONLY = ("foundations", "core", "cases", "registry")
SHELL_PACKAGES = ("torchrl", "tensordict")
# the scripts above the package, one folder each
SCRIPTS = ("recipes", "tools", "benchmarks", "validation", "experiments", "docs")


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(path): path for path in sorted(PACKAGE.rglob("*.py"))}


def layer(name: str) -> int:
    """The floor of a module: that of its top-level name in the package."""
    parts = name.split(".")
    top = parts[1] if len(parts) > 1 else "__init__"
    (index,) = [i for i, (_, members) in enumerate(LAYERS) if top in members] or [None]
    assert index is not None, f"{name} is in no layer: place it in LAYERS"
    return index


def type_checking_only(tree: ast.AST) -> set[int]:
    """The ids of the import nodes under ``if TYPE_CHECKING:``."""
    hidden = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and getattr(node.test, "id", getattr(node.test, "attr", "")) == "TYPE_CHECKING":
            hidden |= {id(n) for child in node.body for n in ast.walk(child)}
    return hidden


def imports(name: str, path: Path, known: set[str], annotations: bool = False) -> set[str]:
    """The package's modules that ``name`` imports, resolved to the deepest known one;
    with ``annotations``, only those imported under ``TYPE_CHECKING``."""
    tree = ast.parse(path.read_text())
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    hidden = type_checking_only(tree)
    found = set()
    for node in ast.walk(tree):
        if (id(node) in hidden) != annotations:
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


def outside(path: Path) -> set[str]:
    """The top-level names of the packages outside this one that a module imports (every
    ``import`` statement but those under ``TYPE_CHECKING``)."""
    tree = ast.parse(path.read_text())
    hidden = type_checking_only(tree)
    found = set()
    for node in ast.walk(tree):
        if id(node) in hidden:
            continue
        if isinstance(node, ast.Import):
            found |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            found.add(node.module.split(".")[0])
    return found - {"beacon_torch"}


def shell_imports() -> list[str]:
    """The modules of the torch-only floors that import TorchRL or TensorDict."""
    torch_only = {k for k, (floor, _) in enumerate(LAYERS) if floor in TORCH_ONLY}
    return [
        f"{name} (floor {LAYERS[layer(name)][0]}) imports {', '.join(sorted(outside(path) & set(SHELL_PACKAGES)))}"
        for name, path in modules().items()
        if layer(name) in torch_only and outside(path) & set(SHELL_PACKAGES)
    ]


def graph(annotations: bool = False) -> dict[str, set[str]]:
    """Each module's imports (``annotations``: its imports under ``TYPE_CHECKING``)."""
    found = modules()
    return {name: imports(name, path, set(found), annotations) for name, path in found.items()}


def upward(edges: dict[str, set[str]]) -> list[str]:
    return [
        f"{name} (layer {layer(name)}) imports {target} (layer {layer(target)})"
        for name, targets in sorted(edges.items())
        for target in sorted(targets)
        if layer(target) > layer(name)
    ]


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected groups of more than one module (Tarjan's algorithm):
    each is at least one cycle of imports."""
    index, low, stack, on, groups = {}, {}, [], set(), []

    def visit(name: str) -> None:
        index[name] = low[name] = len(index)
        stack.append(name)
        on.add(name)
        for target in sorted(edges.get(name, ())):
            if target not in index:
                visit(target)
                low[name] = min(low[name], low[target])
            elif target in on:
                low[name] = min(low[name], index[target])
        if low[name] == index[name]:
            group = []
            while True:
                member = stack.pop()
                on.discard(member)
                group.append(member)
                if member == name:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    for name in sorted(edges):
        if name not in index:
            visit(name)
    return groups


def lines(path: Path) -> int:
    return len(path.read_text().splitlines())


def floors_table() -> str:
    found, edges, hints = modules(), graph(), graph(annotations=True)
    rows = [
        "| floor | rooms (modules) | lines | arrows from it (imports) | of them down a floor or more |",
        "|---|---|---|---|---|",
    ]
    for k, (floor, _) in enumerate(LAYERS):
        names = [n for n in found if layer(n) == k]
        arrows = sum(len(edges[n]) for n in names)
        down = sum(1 for n in names for t in edges[n] if layer(t) < k)
        rows.append(f"| {k}: {floor} | {len(names)} | {sum(lines(found[n]) for n in names):,} | {arrows} | {down} |")
    both = {n: edges[n] | hints[n] for n in edges}
    up, up_hints = upward(edges), [u for u in upward(both) if u not in upward(edges)]
    circles, circles_hints = cycles(edges), cycles(both)
    total = sum(lines(p) for p in found.values())
    arrows, hinted = sum(len(v) for v in edges.values()), sum(len(v - edges[n]) for n, v in hints.items())
    rows.append(f"| all | {len(found)} | {total:,} | {arrows} (and {hinted} under `TYPE_CHECKING`) | |")
    said = [
        "",
        f"Arrows running up a floor: {len(up)}; with the annotations' imports, {len(up) + len(up_hints)}"
        + (" (" + "; ".join(up_hints) + ")" if up_hints else "")
        + ".",
        f"Circles: {len(circles)}; with the annotations' imports, {len(circles_hints)}"
        + (" (" + "; ".join(" <-> ".join(c) for c in circles_hints) + ")" if circles_hints else "")
        + ".",
        f"Modules of the torch-only floors ({', '.join(TORCH_ONLY)}) that import TorchRL or TensorDict: "
        f"{len(shell_imports())}.",
    ]
    return "\n".join(rows + said)


def scripts_table() -> str:
    rows = ["| room above the package | scripts | lines |", "|---|---|---|"]
    for folder in SCRIPTS:
        paths = sorted(p for p in (ROOT / folder).glob("*.py") if p.name != "__init__.py")
        rows.append(f"| `{folder}/` | {len(paths)} | {sum(lines(p) for p in paths):,} |")
    return "\n".join(rows)


def kinds(path: Path) -> dict[str, list[str]]:
    """The classes a case module defines, by what they are: its state (a NamedTuple),
    its parameters (a dataclass), its physics and its env (their base classes' names
    end so), and any other."""
    found: dict[str, list[str]] = {"state": [], "params": [], "physics": [], "env": [], "other": []}
    for node in ast.parse(path.read_text()).body:
        if not isinstance(node, ast.ClassDef):
            continue
        bases = [ast.unparse(b) for b in node.bases]
        decorated = any("dataclass" in ast.unparse(d) for d in node.decorator_list)
        if "NamedTuple" in bases:
            kind = "state"
        elif decorated or node.name.endswith("Params"):
            kind = "params"
        elif node.name.endswith("Physics"):
            kind = "physics"
        elif node.name.endswith("Env"):
            kind = "env"
        else:
            kind = "other"
        found[kind].append(node.name)
    return found


def cases_table() -> str:
    rows = ["| case module | state | params | physics | env | other | classes |", "|---|---|---|---|---|---|---|"]
    totals = dict.fromkeys(("state", "params", "physics", "env", "other"), 0)
    for path in sorted((PACKAGE / "envs").rglob("*.py")):
        found = kinds(path)
        count = sum(len(v) for v in found.values())
        if not count:
            continue
        for kind, names in found.items():
            totals[kind] += len(names)
        cells = " | ".join(str(len(found[k])) for k in totals)
        rows.append(f"| `{path.relative_to(PACKAGE).as_posix()}` | {cells} | {count} |")
    rows.append("| all | " + " | ".join(str(v) for v in totals.values()) + f" | {sum(totals.values())} |")
    return "\n".join(rows)


def block() -> str:
    return "\n\n".join([floors_table(), scripts_table(), cases_table()])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--page", type=Path, help="write the tables between this page's markers")
    args = parser.parse_args(argv)
    text = block()
    if args.page is None:
        print(text)
        return
    page = args.page.read_text()
    head, sep, rest = page.partition(BEGIN)
    _, sep2, tail = rest.partition(END)
    if not (sep and sep2):
        raise SystemExit(f"{args.page}: no {BEGIN} ... {END} markers")
    args.page.write_text(f"{head}{BEGIN}\n{text}\n{END}{tail}")


if __name__ == "__main__":
    main()
