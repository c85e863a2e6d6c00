"""beacon-torch: the BEACON flow-control benchmark as batched TorchRL environments."""

from beacon_torch.base import FlowEnv
from beacon_torch.registry import list_envs, make, register

__version__ = "0.1.0"

__all__ = ["FlowEnv", "list_envs", "make", "register", "__version__"]
