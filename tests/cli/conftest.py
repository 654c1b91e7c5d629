"""The hostile-input tests' fixtures, shared through tests/_cli.py: a small simulated campaign and a kinematic run."""

from _cli import campaign, run_dir  # noqa: F401 (pytest finds fixtures by name)
