"""The speed measurements, run by their files; a package only so that the tests can
import them from the repository's root (where it comes before TorchRL's own
``benchmarks``, which the library never imports)."""
