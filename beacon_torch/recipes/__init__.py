"""Training recipes built on TorchRL's own losses, collectors, buffers and transforms."""
