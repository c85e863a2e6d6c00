"""The checks of the physics against published figures and independent solvers, run by
their files; a package only so that the tests can import them from the repository's root."""
