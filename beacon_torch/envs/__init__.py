"""One module per BEACON environment: a Params dataclass, the right-hand side, the env."""
