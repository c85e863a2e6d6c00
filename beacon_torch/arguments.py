"""What the command lines share (``beacon-torch``, the recipes, the maintainer's
driver): the user's modules on the import path, a script loaded as a module, argument
types, help text from docstrings. Standard library only, so that ``--help`` answers
without torch."""

from __future__ import annotations

import argparse
import importlib.util
import os
import re
import sys
from pathlib import Path


def find_user_modules() -> None:
    """Put the working directory first on the import path, as ``python -m`` does (a
    console script or ``python recipes/ppo.py`` puts its own folder there instead), so
    that ``--import my_envs`` and ``my_envs.heat:heat-v0`` find the user's modules."""
    here = os.getcwd()
    if here not in sys.path and "" not in sys.path:
        sys.path.insert(0, here)


def load_script(path: str | Path, name: str | None = None):
    """The script at ``path`` (a recipe, a page writer) loaded from its file as a module
    of its own and registered in ``sys.modules`` as an import would register it
    (dataclasses look their module up there): how a script runs another (the driver its
    recipes), as a script's own folder is not on its import path."""
    path = Path(path)
    name = name or f"script_{path.parent.name}_{path.stem}"
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ValueError(f"{path}: not a Python script")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        sys.modules.pop(name, None)
        raise
    return module


def positive(text: str) -> int:
    """An argument that must be a positive integer."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expects a positive integer, got {text!r}")
    return value


def plain(doc: str | None) -> str:
    """A docstring as a command's description: one paragraph, without reStructuredText's
    markup (``name`` reads as name)."""
    return re.sub(r"``([^`]+)``", r"\1", " ".join((doc or "").split()))
