"""beacon-torch: the BEACON flow-control benchmark as batched TorchRL environments.

The package imports torch only when something of it is used (``beacon_torch.make``,
a submodule such as ``beacon_torch.registry``), so that the command line answers
``--help`` at once; gymnasium's ids (``beacon/<id>``) exist as soon as it is imported.
"""

from __future__ import annotations

import importlib

from beacon_torch import gym_ids as _gym_ids  # noqa: F401

__version__ = "0.1.0"

# what the package offers at its top, and the module each comes from ("module:name"
# where it is named otherwise there)
_TOP = {
    "FlowEnv": "beacon_torch.base",
    "Physics": "beacon_torch.core.physics",
    "functional": "beacon_torch.registry",
    "step": "beacon_torch.core.inputs:checked_step",
    "list_envs": "beacon_torch.registry",
    "make": "beacon_torch.base",
    "register": "beacon_torch.registry",
}

__all__ = [*_TOP, "__version__"]


def __getattr__(name: str):
    if name in _TOP:
        module, _, attribute = _TOP[name].partition(":")
        value = getattr(importlib.import_module(module), attribute or name)
    else:
        try:
            value = importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as err:
            if err.name != f"{__name__}.{name}":
                raise
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_TOP})
