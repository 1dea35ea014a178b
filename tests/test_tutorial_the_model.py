"""Tutorial 03, the model (your own surrogate and rule, adaptation): runs at tiny sizes (tutorial_runs.py)."""

from tutorial_runs import runs_at_tiny_sizes_as_committed


def test_the_model_runs_at_tiny_sizes_and_shows_what_its_full_run_shows():
    runs_at_tiny_sizes_as_committed("03_the_model")
