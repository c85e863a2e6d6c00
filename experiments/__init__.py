"""The training trials, policy evaluations and campaigns, run by their files; a package
only so that the tests can import them from the repository's root."""
