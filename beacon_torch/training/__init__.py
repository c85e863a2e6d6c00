"""What training scripts and installed users share: the recipes' settings with their
per-env defaults (``config``), the training env with its TorchRL transforms and
collectors (``env``), the paper's networks (``networks``), the run directory with its
checkpoint and loggers (``run``), and the evaluation and learning curves of trained runs
(``evaluation``). The training scripts themselves are the recipes of the repository
(``recipes/``)."""
