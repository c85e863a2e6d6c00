"""What the command lines share (``beacon-torch``, the recipes, the maintainer's
driver): the user's modules on the import path, argument types, help text from
docstrings. Standard library only, so that ``--help`` answers without torch."""

from __future__ import annotations

import argparse
import os
import re
import sys


def find_user_modules() -> None:
    """Put the working directory first on the import path, as ``python -m`` does (a
    console script or ``python recipes/ppo.py`` puts its own folder there instead), so
    that ``--import my_envs`` and ``my_envs.heat:heat-v0`` find the user's modules."""
    here = os.getcwd()
    if here not in sys.path and "" not in sys.path:
        sys.path.insert(0, here)


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
