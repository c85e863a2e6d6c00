"""The README's two commands are the ones CI and users run."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def readme_commands():
    text = (ROOT / "README.md").read_text()
    first_section = text.split("\n## ", 2)[1]
    return re.findall(r"```(?:bash|sh)\n(.*?)\n```", first_section, flags=re.S)


def test_readme_gives_exactly_two_commands():
    commands = readme_commands()
    assert len(commands) == 2
    assert all("\n" not in c for c in commands)
    assert all(c.startswith("bash scripts/setup.sh && ") for c in commands)
    assert "recipes/ppo.py" in commands[0]  # the main job: a training
    assert "pytest" in commands[1]
    # the linter and the formatter's check run before the tests, on the tree as
    # configured in pyproject.toml
    assert commands[1].index("ruff check .") < commands[1].index("ruff format --check .") < commands[1].index("pytest")


def test_ci_runs_the_readme_test_command():
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert readme_commands()[1] in ci


def test_setup_installs_exactly_torch_2_13_0_first():
    lines = [line for line in (ROOT / "scripts" / "setup.sh").read_text().splitlines() if "pip install" in line]
    assert "torch==2.13.0" in lines[0]
    assert "-e '.[test]'" in lines[1]


def test_readme_links_the_docs():
    text = (ROOT / "README.md").read_text()
    pages = sorted(str(page.relative_to(ROOT)) for page in (ROOT / "docs").glob("*.md"))
    pages += [
        f"docs/envs/{name}.md" for name in ("lorenz", "vortex", "burgers", "sloshing", "shkadov", "rayleigh", "mixing")
    ]
    for page in pages:
        assert page in text and (ROOT / page).is_file()


def test_env_pages_list_the_parameters_and_diagnostics_as_declared():
    """Each env page's parameter and diagnostics tables are written from
    ``param(doc=...)`` and ``diagnostics`` (docs/make_env_tables.py): a parameter or a
    diagnostic added, renamed or re-ranged in the code shows on the page, or this fails."""
    from docs import make_env_tables as tables

    for env_id in tables.paged_envs():
        text = tables.page(env_id).read_text()
        block = f"{tables.BEGIN}\n{tables.block(env_id)}\n{tables.END}"
        assert block in text, f"{tables.page(env_id)} is not current: run docs/make_env_tables.py"


def test_recipes_and_tools_are_scripts_on_the_library_alone():
    """The library is what users import; the recipes and the campaign driver are scripts
    that import only the library and its dependencies (no module of their own folder),
    and nothing puts their folders on the import path: the tests import the scripts'
    folders as packages from the repository's root, the one path pytest adds. One script
    reads another: the gradient recipe is the actor-critic's loop without its critic,
    and loads that script from its file (as the driver loads every recipe)."""
    import ast

    allowed = {"__future__", "argparse", "importlib", "json", "math", "os", "shutil", "pathlib", "torch", "torchrl"}
    allowed |= {"copy", "dataclasses", "time"}
    allowed |= {"tensordict", "beacon_torch"}
    for script in [*sorted((ROOT / "recipes").glob("*.py")), ROOT / "tools" / "reproduce.py"]:
        tree = ast.parse(script.read_text())
        for node in ast.walk(tree):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
            if isinstance(node, ast.ImportFrom):
                names = [node.module or ""]
            for name in names:
                assert name.split(".")[0] in allowed, f"{script.name} imports {name}"
    readers = {p.name for p in (ROOT / "recipes").glob("*.py") if "load_script" in p.read_text()}
    assert readers == {"grad.py"} and 'with_name("shac.py")' in (ROOT / "recipes" / "grad.py").read_text()
    import tomllib

    assert tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]["pythonpath"] == ["."]
    scripts = [
        p
        for folder in ("recipes", "tools", "validation", "experiments", "benchmarks", "docs")
        for p in (ROOT / folder).rglob("*.py")
    ]
    assert not [p.name for p in scripts if "sys.path." in p.read_text()]
    assert not (ROOT / "recipes" / "config.py").exists()


def build_api_reference(config: Path, site: Path):
    import shutil
    import subprocess
    import sys

    mkdocs = shutil.which("mkdocs", path=str(Path(sys.executable).parent)) or "mkdocs"
    return subprocess.run(
        [mkdocs, "build", "--strict", "-f", str(config), "-d", str(site)],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )


def test_the_docs_site_builds_the_guides_and_the_api_reference(tmp_path):
    """The README's docs command: every link and reference resolves (a page or module
    renamed or removed fails here), the guides and every env page are in the site and
    its navigation, and the API pages hold the documented objects."""
    proc = build_api_reference(ROOT / "mkdocs.yml", tmp_path / "site")
    assert proc.returncode == 0, proc.stderr[-3000:]
    site = tmp_path / "site"
    envs = (site / "api" / "envs" / "index.html").read_text()
    assert "LorenzParams" in envs and "ShkadovSeparablePhysics" in envs
    assert "step_members" in (site / "api" / "base" / "index.html").read_text()
    start = (site / "quickstart" / "index.html").read_text()
    for page in (
        "training",
        "gradients",
        "results",
        "adding-an-env",
        *(f"envs/{p.stem}" for p in (ROOT / "docs" / "envs").glob("*.md")),
    ):
        assert (site / page / "index.html").is_file(), page
        assert f'href="../{page}/"' in start, f"{page} is not in the navigation"
    assert "mkdocs build --strict" in (ROOT / "README.md").read_text()


def test_a_broken_reference_fails_the_api_reference(tmp_path):
    import shutil

    docs = tmp_path / "docs"
    shutil.copytree(ROOT / "docs", docs)
    (docs / "api" / "tools.md").write_text(
        (docs / "api" / "tools.md").read_text() + "\n::: beacon_torch.no_such_module\n"
    )
    config = tmp_path / "mkdocs.yml"
    config.write_text((ROOT / "mkdocs.yml").read_text().replace("docs_dir: docs", f"docs_dir: {docs}"))
    proc = build_api_reference(config, tmp_path / "site")
    assert proc.returncode != 0 and "no_such_module" in proc.stderr
