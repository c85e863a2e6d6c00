"""The recipes: one script per algorithm, run by its file (``python recipes/ppo.py``);
a package only so that the tests can import them from the repository's root."""
