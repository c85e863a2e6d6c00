"""beacon-torch: the BEACON flow-control benchmark as batched TorchRL environments."""

from beacon_torch.base import FlowEnv
from beacon_torch.registry import list_envs, make, register

__version__ = "0.1.0"

# gymnasium's ids (beacon/<id>) exist once beacon_torch is imported; gymnasium is a
# dependency and the adapter is light beside torch
from beacon_torch import gym as _gym  # noqa: F401

__all__ = ["FlowEnv", "list_envs", "make", "register", "__version__"]
