"""Stateless numerical kernels shared by the environments.

Everything here is a pure function of tensors: no TorchRL, no env state, no in-place
writes into tensors that autograd may need. That keeps the kernels testable on their own,
compilable and differentiable.
"""

from beacon_torch.numerics.integrators import LSRK4_A, LSRK4_B, LSRK4_C, lsrk4_step

__all__ = ["LSRK4_A", "LSRK4_B", "LSRK4_C", "lsrk4_step"]
