"""The core of every env, below the TorchRL shell: the physics' interface
(:class:`~beacon_torch.core.physics.Physics`), the state's vocabulary and the step as
one function (:func:`~beacon_torch.core.step.step`)."""
