"""Stateless numerical kernels shared by the environments.

Everything here is a pure function of tensors: no TorchRL, no env state, no in-place
writes into tensors that autograd may need. That keeps the kernels testable on their own,
compilable and differentiable.
"""

from beacon_torch.numerics.fluxes import (
    minmod,
    rusanov,
    third_derivative,
    tvd_derivative,
    tvd_faces,
    van_leer,
)
from beacon_torch.numerics.integrators import (
    LSRK4_A,
    LSRK4_B,
    LSRK4_C,
    ab2_step,
    bdf2_explicit_step,
    frequency_damping,
    interpolated_action,
    interpolation_weights,
    lsrk4_step,
)

__all__ = [
    "LSRK4_A",
    "LSRK4_B",
    "LSRK4_C",
    "ab2_step",
    "bdf2_explicit_step",
    "frequency_damping",
    "interpolated_action",
    "interpolation_weights",
    "lsrk4_step",
    "minmod",
    "rusanov",
    "third_derivative",
    "tvd_derivative",
    "tvd_faces",
    "van_leer",
]
