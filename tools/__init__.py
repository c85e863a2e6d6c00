"""The maintainer's scripts (the campaign driver, the house's figures), run by their
files; a package only so that the tests can import them from the repository's root."""
