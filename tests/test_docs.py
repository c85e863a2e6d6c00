"""The documentation's code works as written: every Python block of the README and of
the docs pages runs, a page's blocks in order in one namespace (as a reader types them
into one session), in a fresh working folder. A block that shows part of a module
(the adding-an-env guide's excerpts of ``docs/examples/heat.py``) must be that module's
text, word for word, and the module runs. Training budgets are cut to a few
transitions: what is checked is that each call works, not what it learns."""

import importlib
import re
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = ["README.md", *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "docs").rglob("*.md"))]
BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)
# the module whose excerpts a page shows, where it shows them
EXCERPTS = {"docs/adding-an-env.md": ROOT / "docs" / "examples" / "heat.py"}
# what a test runs of a block instead of a long training (the call, not the budget)
CUT = {"learn(500_000)": "learn(1)", "rollout(800)": "rollout(8)", "rollout(500)": "rollout(5)"}


def blocks(page: str) -> list[str]:
    return [textwrap.dedent(b) for b in BLOCK.findall((ROOT / page).read_text())]


def excerpt(block: str, source: str) -> bool:
    """Whether every line of ``block`` is a line of ``source``, in the same order (an
    abridged excerpt: docstrings and other lines left out, its indentation its own)."""
    lines = iter(line.strip() for line in source.splitlines())
    return all(any(line == kept for kept in lines) for line in (x.strip() for x in block.splitlines()) if line)


def test_every_page_with_code_is_checked():
    with_code = [page for page in PAGES if blocks(page)]
    assert {"README.md", "docs/quickstart.md", "docs/gradients.md", "docs/index.md"} <= set(with_code)


@pytest.fixture
def registry_kept():
    """The registry as it was before a page's code registered envs of its own."""
    import gymnasium

    from beacon_torch import registry

    before = set(registry.ENVS)
    yield
    for env_id in set(registry.ENVS) - before:
        for table in (registry.ENVS, registry.ORIGIN):
            table.pop(env_id, None)
        gymnasium.registry.pop(f"beacon/{env_id}", None)


@pytest.mark.slow(seconds=60)
@pytest.mark.parametrize("page", [page for page in PAGES if blocks(page)])
def test_the_docs_code_runs_as_written(page, tmp_path, monkeypatch, registry_kept):
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "__docs__"}
    module = EXCERPTS.get(page)
    if module is not None:
        source = module.read_text()
        name = ".".join(module.relative_to(ROOT).with_suffix("").parts)
        sys.modules.pop(name, None)  # imported afresh, so that it registers its env again
        namespace = vars(importlib.import_module(name))
    for k, block in enumerate(blocks(page)):
        if module is not None and excerpt(block, source):
            continue  # an excerpt of the module, run with it
        for long, short in CUT.items():
            block = block.replace(long, short)
        try:
            exec(compile(block, f"{page} block {k}", "exec"), namespace)
        except Exception as err:
            raise AssertionError(f"{page}, block {k} fails: {type(err).__name__}: {err}\n{block}") from err


def test_the_excerpts_of_a_module_are_its_text():
    for page, module in EXCERPTS.items():
        source = module.read_text()
        shown = [b for b in blocks(page) if excerpt(b, source)]
        # the guide's declarations are the module's (its registrations and checks run)
        assert any(b.startswith("class HeatPhysics(Physics)") for b in shown), page
        assert len(shown) >= 6, (page, len(shown))
    assert excerpt("a = 1\n\nb = 2", "a = 1\nc = 3\n    b = 2") and not excerpt("b = 2\na = 1", "a = 1\nb = 2")
